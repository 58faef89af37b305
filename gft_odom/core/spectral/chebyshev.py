r"""Band responses without eigendecomposition: Jackson-damped Chebyshev filters.

Every slice's Laplacian L_s is mapped to M_s = (2 / lambda_max_s) L_s - I, whose spectrum is
x = 2 nu - 1 in [-1, 1]. The ideal indicator h_b of band b (nu in [(b-1)/B, b/B)) is expanded as
h_b(x) ~ sum_k g_k c_bk T_k(x), with the closed-form Chebyshev coefficients of an interval
indicator and Jackson damping g_k (which removes the Gibbs overshoot, so responses stay >= 0
and bands do not leak into far-away frequencies). The three-term recursion
T_{k+1}(M) X = 2 M T_k(M) X - T_{k-1}(M) X is run ONCE on the block-diagonal matrix of all
slices and serves every band: the per-band responses are one small matrix product over the
K + 1 stored terms. Cost O(K |E|), no eigenvectors.

lambda_max of every slice comes from one batched Lanczos run over all slices at once (segment
sums instead of a loop), with ARPACK (`eigsh`) as an alternative and the Gershgorin bound
2 max degree as the safe fallback.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.linalg import ArpackError, ArpackNoConvergence, eigsh

from gft_odom.core.spectral.bands import band_edges, validate_n_bands
from gft_odom.core.spectral.graph import GraphLaplacian
from gft_odom.errors import SpectralError

log = logging.getLogger(__name__)

# Slices this small get lambda_max from a dense eigvalsh (ARPACK needs k < n and gains nothing).
_DENSE_LMAX_POINTS = 64


def jackson_damping(order: int) -> np.ndarray:
    """Jackson kernel factors g_0..g_K for an order-K Chebyshev expansion."""
    if order < 0:
        raise SpectralError(f'Chebyshev order must be >= 0, got {order}')
    k = np.arange(order + 1, dtype=np.float64)
    a = np.pi / (order + 2)
    return ((1.0 - k / (order + 2)) * np.sin(a) * np.cos(k * a)
            + np.cos(a) * np.sin(k * a) / (order + 2)) / np.sin(a)


def band_coefficients(n_bands: int, order: int, damped: bool = True) -> np.ndarray:
    """(B, K + 1) Chebyshev coefficients (on x = 2 nu - 1) of the ideal band indicators.

    For the indicator of [x_lo, x_hi] with theta = arccos(x): c_0 = (theta_lo - theta_hi) / pi,
    c_k = 2 (sin k theta_lo - sin k theta_hi) / (k pi). The bands partition [-1, 1], so the
    undamped coefficients of all bands sum to those of the constant 1.
    """
    n = validate_n_bands(n_bands)
    edges_x = 2.0 * band_edges(n) - 1.0
    theta = np.arccos(np.clip(edges_x, -1.0, 1.0))  # decreasing from pi to 0
    theta_lo, theta_hi = theta[:-1, None], theta[1:, None]
    k = np.arange(1, order + 1, dtype=np.float64)[None, :]
    coeffs = np.empty((n, order + 1))
    coeffs[:, 0] = (theta_lo - theta_hi)[:, 0] / np.pi
    coeffs[:, 1:] = 2.0 * (np.sin(k * theta_lo) - np.sin(k * theta_hi)) / (k * np.pi)
    if damped:
        coeffs *= jackson_damping(order)[None, :]
    return coeffs


def evaluate_band_polynomials(nu: np.ndarray, n_bands: int, order: int) -> np.ndarray:
    """The damped polynomial approximations of the band indicators at scalar nu: (len(nu), B)."""
    x = 2.0 * np.asarray(nu, dtype=np.float64) - 1.0
    T = np.polynomial.chebyshev.chebvander(x, order)
    return T @ band_coefficients(n_bands, order).T


def chebyshev_terms(L, scale: np.ndarray, X: np.ndarray, order: int,
                    dtype=np.float32) -> np.ndarray:
    """T_k(M) X for k = 0..K with M = diag(scale) L - I: (K + 1, n, c).

    `L` is a `GraphLaplacian` or any sparse Laplacian; `scale` is 2 / lambda_max of each row's
    slice (constant within a block, so the row scaling scales each block as a whole). M is
    never formed: M X = (scale d - 1) X - scale (W X), one product with W per order.
    """
    if not isinstance(L, GraphLaplacian):
        L = GraphLaplacian(sp.diags(sp.csr_matrix(L).diagonal()) - sp.csr_matrix(L))
    n = L.shape[0]
    X = np.asarray(X, dtype=dtype).reshape(n, -1)
    W = L.W.astype(dtype)
    s = np.asarray(scale, dtype=dtype)[:, None]
    diag = s * L.degree.astype(dtype)[:, None] - 1.0

    def apply_m(v: np.ndarray) -> np.ndarray:
        return diag * v - s * (W @ v)

    terms = np.empty((order + 1,) + X.shape, dtype=dtype)
    terms[0] = X
    if order >= 1:
        terms[1] = apply_m(X)
    for k in range(2, order + 1):
        np.subtract(2.0 * apply_m(terms[k - 1]), terms[k - 2], out=terms[k])
    return terms


def band_responses_from_terms(terms: np.ndarray, n_bands: int) -> np.ndarray:
    r"""r_mb = \|(p_b(M) X)_m\|^2 for every band from the stored terms: (n, B) float64."""
    order = terms.shape[0] - 1
    coeffs = band_coefficients(n_bands, order).astype(terms.dtype)
    k1, n, c = terms.shape
    Y = (coeffs @ terms.reshape(k1, n * c)).reshape(-1, n, c)
    Y *= Y
    return Y.sum(axis=2).T.astype(np.float64)


def band_responses_chebyshev(L, scale: np.ndarray, X: np.ndarray, n_bands: int,
                             order: int) -> np.ndarray:
    """Chebyshev band responses (n, B) in one recursion; see `chebyshev_terms`."""
    return band_responses_from_terms(chebyshev_terms(L, scale, X, order), n_bands)


def _segment_sum(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    return np.add.reduceat(values, starts[:-1]) if values.size else np.zeros(0)


def gershgorin_bound(L, starts: np.ndarray) -> np.ndarray:
    """Per-slice upper bound 2 max degree >= lambda_max (for L = D - W)."""
    degree = np.asarray(L.diagonal(), dtype=np.float64)
    if degree.size == 0:
        return np.zeros(len(starts) - 1)
    return 2.0 * np.maximum.reduceat(degree, starts[:-1])


def lambda_max_lanczos(L, starts: np.ndarray, n_iter: int = 30,
                       seed: int = 0) -> np.ndarray:
    """Largest eigenvalue of every diagonal block [starts[s], starts[s+1]) of L, all at once.

    Plain Lanczos (no re-orthogonalisation, which only adds ghost copies and does not disturb
    the largest Ritz value), run on all blocks together: one sparse product per iteration and
    segment sums for the per-block inner products. A block whose Krylov space is exhausted
    (small slices) stops cleanly. The largest Ritz value converges from below; the residual
    norm of its Ritz pair is added so that an unconverged estimate errs high in practice (a
    few nu values slightly below 1) rather than low (Chebyshev polynomials grow fast outside
    [-1, 1]); strictly, the residual bounds the distance to SOME eigenvalue, not lambda_max,
    and `lambda_max_per_slice` caps the result at the Gershgorin bound.
    """
    n_blocks = len(starts) - 1
    n = L.shape[0]
    if n == 0 or n_blocks == 0:
        return np.zeros(n_blocks)
    sizes = np.diff(starts)
    block = np.repeat(np.arange(n_blocks), sizes)
    v = np.random.default_rng(seed).standard_normal(n)
    v /= np.sqrt(_segment_sum(v * v, starts))[block]
    v_prev = np.zeros(n)
    beta_prev = np.zeros(n_blocks)
    alphas = np.zeros((n_iter, n_blocks))
    betas = np.zeros((n_iter, n_blocks))
    steps = min(n_iter, int(sizes.max()))
    for j in range(steps):
        w = L @ v
        alpha = _segment_sum(w * v, starts)
        w -= alpha[block] * v + beta_prev[block] * v_prev
        beta = np.sqrt(np.maximum(_segment_sum(w * w, starts), 0.0))
        alphas[j], betas[j] = alpha, beta
        # Krylov space exhausted (or block done): zero the vector, the block's T decouples.
        alive = beta > 1e-10 * np.maximum(np.abs(alpha), 1.0)
        inv = np.where(alive, 1.0 / np.where(alive, beta, 1.0), 0.0)
        v_prev, v = v, w * inv[block]
        beta_prev = np.where(alive, beta, 0.0)
        betas[j] = beta_prev
    lmax = np.zeros(n_blocks)
    for s in range(n_blocks):
        m = min(steps, int(sizes[s]))
        if m == 1:
            lmax[s] = alphas[0, s]
            continue
        theta, y = scipy.linalg.eigh_tridiagonal(
            alphas[:m, s], betas[:m - 1, s], select='i', select_range=(m - 1, m - 1),
            check_finite=False)
        # Residual norm of the Ritz pair: an eigenvalue lies within it of theta. Adding it
        # turns the estimate from below into a (slightly) safe one from above.
        lmax[s] = theta[0] + abs(betas[m - 1, s] * y[-1, 0])
    return lmax


def lambda_max_arpack(L, starts: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Largest eigenvalue of every diagonal block with ARPACK (`eigsh(k=1, which='LA')`)."""
    out = np.zeros(len(starts) - 1)
    # A random start: the constant vector (a tempting v0) is in L's nullspace.
    rng = np.random.default_rng(0)
    for s in range(len(starts) - 1):
        a, b = int(starts[s]), int(starts[s + 1])
        block = L.block(a, b) if isinstance(L, GraphLaplacian) else L[a:b, a:b]
        if b - a <= _DENSE_LMAX_POINTS:
            out[s] = np.linalg.eigvalsh(block.toarray())[-1] if b > a else 0.0
            continue
        try:
            out[s] = eigsh(block, k=1, which='LA', tol=tol, return_eigenvectors=False,
                           v0=rng.standard_normal(b - a))[0]
        except (ArpackNoConvergence, ArpackError) as exc:
            log.debug('ARPACK failed on a slice of %d points (%s); using Gershgorin', b - a, exc)
            out[s] = np.nan
    return out


def lambda_max_per_slice(L, starts: np.ndarray, method: str = 'lanczos',
                         n_iter: int = 30) -> np.ndarray:
    """lambda_max of each slice by `method` ('lanczos' | 'arpack'), never above the Gershgorin
    bound, replaced by it when the estimate fails (non-finite or non-positive with edges)."""
    bound = gershgorin_bound(L, starts)
    if method == 'lanczos':
        lmax = lambda_max_lanczos(L, starts, n_iter=n_iter)
    elif method == 'arpack':
        lmax = lambda_max_arpack(L, starts)
    else:
        raise SpectralError(f'unknown lambda_max method {method!r} (lanczos, arpack)')
    bad = ~np.isfinite(lmax) | ((lmax <= 0.0) & (bound > 0.0))
    if np.any(bad):
        log.debug('lambda_max estimate failed on %d slices; using the Gershgorin bound',
                  int(bad.sum()))
        lmax = np.where(bad, bound, lmax)
    return np.minimum(lmax, bound)
