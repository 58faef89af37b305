"""Chebyshev band filters: coefficients, lambda_max, and convergence to the exact path."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from gft_odom.core.spectral.chebyshev import (
    band_coefficients,
    band_responses_chebyshev,
    evaluate_band_polynomials,
    gershgorin_bound,
    jackson_damping,
    lambda_max_arpack,
    lambda_max_lanczos,
    lambda_max_per_slice,
)
from gft_odom.core.spectral.gft import band_responses_exact, fourier_basis
from gft_odom.core.spectral.graph import gaussian_graph, laplacian


def block_graph(seed: int = 0, sizes=(150, 90, 3, 1)):
    rng = np.random.default_rng(seed)
    xy = np.concatenate([rng.uniform(0.0, 1.5, (n, 2)) for n in sizes])
    s = np.repeat(np.arange(len(sizes)), sizes)
    L = laplacian(gaussian_graph(xy, s, 0.4, 0.2))
    starts = np.r_[0, np.cumsum(sizes)]
    return L, starts, xy


def test_undamped_band_coefficients_sum_to_the_constant_one():
    c = band_coefficients(7, 25, damped=False).sum(axis=0)
    np.testing.assert_allclose(c[0], 1.0, atol=1e-12)
    np.testing.assert_allclose(c[1:], 0.0, atol=1e-12)


def test_damped_polynomials_approximate_the_indicators_away_from_edges():
    nu = np.array([0.05, 0.35, 0.62, 0.95])
    p = evaluate_band_polynomials(nu, 4, 120)
    expected = np.eye(4)[[0, 1, 2, 3]]
    np.testing.assert_allclose(p, expected, atol=0.02)
    g = jackson_damping(30)
    assert g[0] == 1.0 and np.all(np.diff(g) < 0) and g[-1] > 0


def test_lanczos_matches_arpack_and_dense_and_stays_below_gershgorin():
    L, starts, _ = block_graph()
    dense = [np.linalg.eigvalsh(L[a:b, a:b].toarray())[-1]
             for a, b in zip(starts[:-1], starts[1:])]
    lan = lambda_max_lanczos(L, starts, n_iter=40)
    arp = lambda_max_arpack(L, starts)
    np.testing.assert_allclose(arp, dense, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(lan, dense, rtol=1e-3, atol=1e-12)
    few = lambda_max_lanczos(L, starts, n_iter=4)  # unconverged: residual bound errs high
    assert np.all(few >= np.asarray(dense) * (1 - 1e-9))
    assert np.all(gershgorin_bound(L, starts) >= np.asarray(dense) - 1e-12)
    assert lambda_max_per_slice(L, starts, 'lanczos')[-1] == 0.0  # one isolated vertex


def test_chebyshev_converges_to_exact_as_order_grows():
    L, starts, xy = block_graph(1, sizes=(120,))
    X = xy - xy.mean(axis=0)
    lam, U = fourier_basis(L)
    lmax = lam[-1]
    exact = band_responses_exact(lam, U, X, lmax, 5)
    scale = np.full(L.shape[0], 2.0 / lmax)
    errors = []
    for order in (5, 20, 80, 320):
        r = band_responses_chebyshev(sp.csr_matrix(L), scale, X, 5, order)
        errors.append(np.abs(r - exact).sum() / exact.sum())
    assert errors[-1] < 0.05
    assert errors[-1] < errors[1] < errors[0]
