"""Exact GFT: transform pair, Parseval, and sign-free point frequencies."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gft_odom.core.spectral.gft import (
    band_responses_exact,
    fourier_basis,
    gft,
    igft,
    signal_frequency,
)
from gft_odom.core.spectral.graph import gaussian_graph, laplacian


def small_graph(seed: int, n: int = 80):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 2.0, (n, 2))
    L = laplacian(gaussian_graph(xy, None, 0.5, 0.25)).toarray()
    X = xy - xy.mean(axis=0)
    return L, X


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_inverse_gft_of_gft_is_identity_and_parseval_holds(seed):
    L, X = small_graph(seed)
    lam, U = fourier_basis(L)
    f = np.random.default_rng(seed).normal(size=(L.shape[0], 3))
    f_hat = gft(U, f)
    np.testing.assert_allclose(igft(U, f_hat), f, atol=1e-10)
    np.testing.assert_allclose(np.sum(f_hat**2, axis=0), np.sum(f**2, axis=0), rtol=1e-10)
    np.testing.assert_allclose(L @ U, U * lam, atol=1e-9)
    assert lam[0] >= 0.0 and np.all(np.diff(lam) >= -1e-12)


def path_graph_spectrum(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Closed form for the path graph P_n (unit weights), independent of any eigensolver:
    lambda_k = 2 - 2 cos(pi k / n), v_k(m) = cos(pi k (m + 1/2) / n), normalised."""
    k = np.arange(n)
    lam = 2.0 - 2.0 * np.cos(np.pi * k / n)
    V = np.cos(np.pi * np.outer(np.arange(n) + 0.5, k) / n)
    return lam, V / np.linalg.norm(V, axis=0)


def path_laplacian(n: int) -> np.ndarray:
    W = np.diag(np.ones(n - 1), 1)
    W = W + W.T
    return np.diag(W.sum(1)) - W


def test_fourier_basis_of_a_path_graph_matches_the_closed_form():
    n = 16
    lam, U = fourier_basis(path_laplacian(n))
    lam_ref, V = path_graph_spectrum(n)
    np.testing.assert_allclose(lam, lam_ref, atol=1e-12)
    # Simple eigenvalues: each eigenvector is the closed-form one up to its sign.
    np.testing.assert_allclose(np.abs(np.sum(U * V, axis=0)), np.ones(n), atol=1e-10)
    # The GFT of a closed-form eigenvector is (+-) a unit spike at its index.
    f_hat = gft(U, V[:, 5])
    np.testing.assert_allclose(np.abs(f_hat), np.eye(n)[5], atol=1e-10)


def test_band_responses_of_a_path_graph_match_the_closed_form():
    # X = v_2 + 3 v_13 on P_16: with B = 4 bands on nu = lambda / lambda_max, v_2 lies in band
    # 1 and v_13 in band 4, so band 1 responds with v_2^2, band 4 with 9 v_13^2, bands 2-3 not.
    n, n_bands = 16, 4
    lam_ref, V = path_graph_spectrum(n)
    nu = lam_ref / lam_ref[-1]
    assert nu[2] < 0.25 and nu[13] >= 0.75
    X = V[:, 2] + 3.0 * V[:, 13]
    lam, U = fourier_basis(path_laplacian(n))
    r = band_responses_exact(lam, U, X, lam[-1], n_bands)
    expected = np.zeros((n, n_bands))
    expected[:, 0] = V[:, 2] ** 2
    expected[:, 3] = 9.0 * V[:, 13] ** 2
    np.testing.assert_allclose(r, expected, atol=1e-10)
    _, band = signal_frequency(r)
    np.testing.assert_array_equal(band, np.where(V[:, 2] ** 2 > 9.0 * V[:, 13] ** 2, 1, 4))


def test_band_responses_split_the_signal():
    L, X = small_graph(3)
    lam, U = fourier_basis(L)
    r = band_responses_exact(lam, U, X, lam[-1], 5)
    assert r.shape == (L.shape[0], 5) and np.all(r >= 0.0)
    # The band projections are orthogonal and sum to X: energies add up to ||X||^2.
    np.testing.assert_allclose(r.sum(), np.sum(X**2), rtol=1e-9)


def test_frequencies_do_not_change_when_eigenvector_signs_flip():
    L, X = small_graph(7)
    lam, U = fourier_basis(L)
    signs = np.where(np.random.default_rng(0).random(U.shape[1]) < 0.5, -1.0, 1.0)
    flipped = U * signs
    assert not np.allclose(flipped, U)
    np.testing.assert_allclose(band_responses_exact(lam, flipped, X, lam[-1], 8),
                               band_responses_exact(lam, U, X, lam[-1], 8), atol=1e-10)


def test_signal_frequency_argmax_and_weighted_centre():
    r = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 3.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    nu, band = signal_frequency(r)
    np.testing.assert_array_equal(band, [1, 3, 1])
    np.testing.assert_allclose(nu, [0.125, (0.375 + 3 * 0.625) / 4, 0.0])


def test_empty_and_single_vertex_graphs():
    lam, U = fourier_basis(np.zeros((0, 0)))
    assert lam.size == 0 and U.shape == (0, 0)
    lam, U = fourier_basis(np.zeros((1, 1)))
    np.testing.assert_allclose(lam, [0.0])
