r"""Exact graph Fourier transform of one slice graph and both point-frequency definitions.

L = U diag(lambda) U^T (dense `eigh`, so for slices up to a few thousand points only);
GFT f_hat = U^T f, inverse f = U f_hat. Eigenvector signs (and bases of repeated eigenvalues)
are arbitrary, so everything here that reaches a point's frequency is sign-free: band responses
use U diag(h_b) U^T, the dominant frequency uses |U|.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from gft_odom.core.spectral.bands import band_centres, band_of_nu, validate_n_bands
from gft_odom.errors import SpectralError


def fourier_basis(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending, clipped at 0) and orthonormal eigenvectors (columns) of L."""
    L = np.asarray(L.toarray() if hasattr(L, 'toarray') else L, dtype=np.float64)
    if L.ndim != 2 or L.shape[0] != L.shape[1]:
        raise SpectralError(f'Laplacian must be square, got shape {L.shape}')
    if L.shape[0] == 0:
        return np.zeros(0), np.zeros((0, 0))
    lam, U = scipy.linalg.eigh(L, driver='evd', check_finite=False)
    return np.maximum(lam, 0.0), U


def gft(U: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Graph Fourier transform f_hat = U^T f (f may be (n,) or (n, c))."""
    return U.T @ f


def igft(U: np.ndarray, f_hat: np.ndarray) -> np.ndarray:
    """Inverse graph Fourier transform f = U f_hat."""
    return U @ f_hat


def normalised_eigenvalues(lam: np.ndarray, lambda_max: float) -> np.ndarray:
    """nu = lambda / lambda_max clipped to [0, 1] (lambda_max <= 0: a graph with no edges)."""
    if not lambda_max > 0.0:
        return np.zeros_like(lam)
    return np.clip(lam / lambda_max, 0.0, 1.0)


def band_responses_exact(lam: np.ndarray, U: np.ndarray, X: np.ndarray, lambda_max: float,
                         n_bands: int) -> np.ndarray:
    r"""r_mb = \|(h_b(L) X)_m\|^2 with h_b the ideal indicator of band b on nu; (n, B)."""
    n = validate_n_bands(n_bands)
    X = np.asarray(X, dtype=np.float64).reshape(U.shape[0], -1)
    eig_band = band_of_nu(normalised_eigenvalues(lam, lambda_max), n)
    X_hat = gft(U, X)
    r = np.zeros((U.shape[0], n))
    for b in np.unique(eig_band):
        sel = eig_band == b
        part = U[:, sel] @ X_hat[sel]
        r[:, b - 1] = np.sum(part * part, axis=1)
    return r


def signal_frequency(responses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`signal` frequency from band responses (n, B): (nu, band).

    band = argmax_b r_mb (1-based); nu = response-weighted mean of the band centres. A point
    with no response at all (its component's centred signal is zero, e.g. repeated points) is
    perfectly smooth: nu = 0, band 1.
    """
    responses = np.asarray(responses)
    n_bands = responses.shape[1]
    total = responses.sum(axis=1)
    centres = band_centres(n_bands)
    safe = np.where(total > 0.0, total, 1.0)
    nu = np.where(total > 0.0, (responses @ centres) / safe, 0.0)
    band = (np.argmax(responses, axis=1) + 1).astype(np.int16)
    return nu, band
