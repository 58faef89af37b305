"""Frequency definitions: the exact LDOS mean, the scan-line graph, the registry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from gft_odom.core.spectral import BandMask, SpectralConfig, SpectralFilter
from gft_odom.core.spectral.bands import band_of_nu
from gft_odom.core.spectral.frequency import (
    REGISTRY,
    FrequencyDefinition,
    NodeFrequencies,
    SpectralGraph,
    make_definition,
    register,
)
from gft_odom.core.spectral.graph import GraphLaplacian, scan_line_edges, scan_line_graph
from gft_odom.core.spectral.slicing import Slices
from gft_odom.errors import ConfigError


def config(**overrides) -> SpectralConfig:
    """SpectralConfig with `overrides`; the mask follows `n_bands` (all-pass)."""
    n_bands = overrides.get('n_bands', SpectralConfig().n_bands)
    settings = {'band_mask': tuple(range(1, n_bands + 1)), **overrides}
    return dataclasses.replace(SpectralConfig(), **settings)


def random_graph(n: int, density: float, seed: int) -> sp.csr_matrix:
    """A symmetric random weighted graph with a zero diagonal."""
    rng = np.random.default_rng(seed)
    upper = sp.random(n, n, density=density, random_state=rng, format='csr')
    upper = sp.triu(upper, k=1)
    return (upper + upper.T).tocsr()


def exact_graph(W: sp.csr_matrix) -> tuple[SpectralGraph, np.ndarray, np.ndarray]:
    """A one-block SpectralGraph with the exact lambda_max, and L's eigen-decomposition."""
    n = W.shape[0]
    L = GraphLaplacian(W)
    lam, U = np.linalg.eigh(L.toarray())
    lam = np.maximum(lam, 0.0)
    order = np.arange(n)
    sl = Slices(order=order, starts=np.array([0, n]), slice_of_point=np.zeros(n, np.int64),
                in_range=np.ones(n, bool), z_bottom_m=np.zeros(1))
    graph = SpectralGraph(n_points=n, sl=sl, node_of_point=order, starts=np.array([0, n]),
                          node_block=np.zeros(n, np.int64), L=L,
                          isolated_nodes=np.diff(W.indptr) == 0, lmax=np.array([lam[-1]]),
                          finite=np.ones(n, bool))
    return graph, lam, U


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_ldos_mean_equals_the_eigendecomposition(seed):
    """nu_m = sum_l nu_l v_l(m)^2: the weighted degree over lambda_max, no eigh needed."""
    W = random_graph(40 + 10 * seed, 0.15, seed)
    graph, lam, U = exact_graph(W)
    nu_l = lam / lam[-1]
    density = U ** 2  # rho_m(lambda_l) = v_l(m)^2
    node = make_definition(config(method='ldos_mean')).assign(graph, 10)
    np.testing.assert_allclose(node.nu, density @ nu_l, atol=1e-9)
    np.testing.assert_array_equal(node.band, band_of_nu(density @ nu_l, 10))


def ring_cloud(n_rings: int = 4, n_azimuth: int = 36, radius_m: float = 5.0):
    """Points on horizontal circles (one per ring) at 10 deg azimuth steps, shuffled."""
    az = np.deg2rad(np.arange(n_azimuth) * (360.0 / n_azimuth)) - np.pi + 1e-3
    ring = np.repeat(np.arange(n_rings), n_azimuth)
    azimuth = np.tile(az, n_rings)
    xyz = np.column_stack([radius_m * np.cos(azimuth), radius_m * np.sin(azimuth),
                           0.1 * ring.astype(float)])
    perm = np.random.default_rng(0).permutation(xyz.shape[0])
    return xyz[perm], ring[perm], azimuth[perm]


def test_scan_line_graph_joins_azimuth_neighbours_on_each_ring():
    xyz, ring, azimuth = ring_cloud()
    i, j = scan_line_edges(xyz, ring)
    pairs = {tuple(sorted(p)) for p in zip(i.tolist(), j.tolist())}
    assert len(pairs) == len(i)  # every edge once
    step = 2.0 * np.pi / 36
    col = np.round((azimuth + np.pi - 1e-3) / step).astype(int) % 36
    index = {(int(r), int(c)): k for k, (r, c) in enumerate(zip(ring, col))}
    expected = {tuple(sorted((k, index[(r, c + 1)]))) for (r, c), k in index.items() if c < 35}
    assert pairs == expected  # along each ring in azimuth, never across rings
    L, order = scan_line_graph(xyz, ring, tau_m=10.0, sigma_m=0.5)
    W = L.W
    assert (W != W.T).nnz == 0 and W.diagonal().max() == 0.0
    # Nodes in scan-line order: interior points have two ring neighbours, the ends one.
    col_sorted = col[order]
    np.testing.assert_array_equal(np.diff(W.indptr), np.where(
        (col_sorted == 0) | (col_sorted == 35), 1, 2))
    np.testing.assert_allclose(L.degree, np.asarray(W.sum(axis=1)).ravel(), atol=1e-12)
    # tau cuts the edges longer than it: ring steps are 0.87 m apart.
    L_cut, _ = scan_line_graph(xyz, ring, tau_m=0.5, sigma_m=0.5)
    assert not np.any(L_cut.degree)


@pytest.mark.parametrize('seed', range(6))
def test_scan_line_laplacian_products_and_exact_lambda_max(seed):
    from gft_odom.core.spectral.graph import ScanLineLaplacian
    rng = np.random.default_rng(seed)
    # Small graphs, and ones with hundreds of components (lambda_max prunes most of them).
    n = int(rng.integers(2, 400)) if seed % 2 else int(rng.integers(1500, 3000))
    w = rng.uniform(0.0, 1.0, n - 1) * (rng.random(n - 1) > 0.3)  # paths with breaks
    L = ScanLineLaplacian(w)
    dense = L.toarray()
    np.testing.assert_allclose(dense, dense.T)
    np.testing.assert_allclose(dense.sum(axis=1), 0.0, atol=1e-12)  # L 1 = 0
    x = rng.standard_normal((n, 2))
    np.testing.assert_allclose(L @ x, dense @ x, atol=1e-12)
    np.testing.assert_allclose(L @ x[:, 0], dense @ x[:, 0], atol=1e-12)
    assert L.lambda_max() == pytest.approx(np.linalg.eigvalsh(dense)[-1], abs=1e-8)


def test_scan_line_filter_uses_ring_and_falls_back_without_it(caplog):
    xyz, ring, _ = ring_cloud(n_azimuth=360)
    filt = SpectralFilter(config(graph='scan_line'))
    with_ring = filt.frequencies(xyz, ring=ring)
    assert with_ring.n_slices == 1
    without = filt.frequencies(xyz)
    assert without.n_slices > 1  # the slice graph
    assert 'no `ring` field' in caplog.text


@pytest.mark.parametrize('method', sorted(REGISTRY))
def test_every_definition_gives_bands_that_masks_select_exactly(method):
    xyz, ring, _ = ring_cloud(n_rings=8, n_azimuth=180)
    xyz = xyz + np.random.default_rng(1).normal(0.0, 0.03, xyz.shape)
    cfg = config(method=method, n_bands=5, tau_m=0.3)
    filt = SpectralFilter(cfg)
    freqs = filt.frequencies(xyz, ring=ring)
    has = freqs.band > 0
    assert np.all((freqs.nu[has] >= 0.0) & (freqs.nu[has] <= 1.0))
    assert np.all(np.isnan(freqs.nu[~has]))
    for b in range(1, 6):
        keep = filt.keep_mask(freqs, BandMask(5, frozenset({b})))
        np.testing.assert_array_equal(keep & has, freqs.band == b)


def test_a_new_definition_is_one_class():
    @register
    class DegreeRank(FrequencyDefinition):
        name = 'test_degree_rank'

        def assign(self, graph, n_bands):
            rank = np.argsort(np.argsort(graph.L.degree)) / max(graph.n_nodes - 1, 1)
            return NodeFrequencies(rank, band_of_nu(rank, n_bands))

    try:
        cfg = config(method='test_degree_rank', n_bands=4)
        xyz, ring, _ = ring_cloud()
        freqs = SpectralFilter(cfg).frequencies(xyz, ring=ring)
        assert set(np.unique(freqs.band)) <= {0, 1, 2, 3, 4}
        with pytest.raises(ConfigError, match='method'):
            dataclasses.replace(cfg, method='not_registered').validate()
    finally:
        REGISTRY.pop('test_degree_rank')


def test_one_block_lanczos_is_close_to_the_exact_lambda_max():
    from gft_odom.core.spectral.chebyshev import lambda_max_lanczos
    W = random_graph(300, 0.02, 11)
    L = GraphLaplacian(W)
    exact = np.linalg.eigvalsh(L.toarray())[-1]
    one = lambda_max_lanczos(L, np.array([0, 300]), n_iter=30)
    assert one.shape == (1,)
    assert exact * 0.999 <= one[0] <= exact * 1.02
