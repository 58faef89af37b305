"""Frequency sources: the scan's own graph, the local map of keyframes (the paper's merged
cloud) passed to each scan by nearest neighbour, and that map's planarity (an ablation)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gft_odom.config import ConfigError, GftOdomConfig, with_values
from gft_odom.core.spectral import SpectralConfig, SpectralFilter
from gft_odom.core.spectral.sources import (
    PLANAR_NU,
    LocalMapSource,
    MapPlanaritySource,
    ScanSource,
    make_source,
)
from gft_odom.core.types import Scan
from gft_odom.pipeline import OdometryPipeline


def wall_scan(shift_x_m: float = 0.0, seed: int = 0) -> Scan:
    """Two walls and a pole seen from the origin, as points with rings."""
    rng = np.random.default_rng(seed)
    y = rng.uniform(-5.0, 5.0, 3000)
    z = rng.uniform(-0.5, 2.0, 3000)
    wall = np.column_stack([np.full(3000, 4.0), y, z])
    pole_angle = rng.uniform(0.0, 2.0 * np.pi, 600)
    pole = np.column_stack([2.0 + 0.1 * np.cos(pole_angle), 1.0 + 0.1 * np.sin(pole_angle),
                            rng.uniform(-0.5, 2.0, 600)])
    points = np.concatenate([wall, pole]) - [shift_x_m, 0.0, 0.0]
    ring = np.clip(np.floor((points[:, 2] + 0.5) / 0.17), 0, 15).astype(np.uint16)
    return Scan(0, points, ring=ring)


def test_default_source_is_the_scan_itself():
    filt = SpectralFilter(SpectralConfig())
    source = make_source(filt)
    assert isinstance(source, ScanSource)
    scan = wall_scan()
    a = source.frequencies(scan, 10)
    b = filt.scan_frequencies(scan, 10)
    np.testing.assert_array_equal(a.band, b.band)


def test_local_map_passes_the_map_frequencies_to_the_nearest_points():
    cfg = dataclasses.replace(SpectralConfig(), frequency_source='local_map', tau_m=0.3,
                              sigma_m=0.15, local_map_voxel_m=0.02)
    source = make_source(SpectralFilter(cfg))
    assert isinstance(source, LocalMapSource)
    first = wall_scan()
    freqs = source.frequencies(first, 10)
    assert len(freqs) == len(first) and source.keyframe_updates == 1
    # The first scan is the map: its points get the map's frequencies (slice graph) back.
    own = source.map_filter.frequencies(first.points_xyz, 10)
    same = (freqs.band > 0) & (own.band > 0)
    assert np.mean(freqs.band[same] == own.band[same]) > 0.9
    # Moving 1 m adds a keyframe; a point far from the map gets no spectrum (band 0).
    T = np.eye(4)
    T[0, 3] = 1.0
    source.observe(wall_scan(1.0, seed=1), T)
    assert source.keyframe_updates == 2
    far = Scan(1, np.array([[50.0, 50.0, 0.0], [3.0, 0.0, 0.5]]), ring=np.array([0, 3]))
    out = source.frequencies(far, 10)
    assert out.band[0] == 0 and out.isolated[0]
    assert out.band[1] > 0  # on the wall, 1 m ahead of the new pose
    source.reset()
    assert source.keyframe_updates == 0


def test_map_planarity_puts_a_plane_at_the_smooth_end_and_foliage_at_the_rough_end():
    rng = np.random.default_rng(3)
    ground = np.column_stack([rng.uniform(2.0, 6.0, 4000), rng.uniform(-2.0, 2.0, 4000),
                              np.full(4000, -0.5) + rng.normal(0.0, 0.005, 4000)])
    foliage = rng.uniform(-0.6, 0.6, (2000, 3)) + [4.0, 5.0, 1.5]  # a blob, no surface
    points = np.concatenate([ground, foliage])
    cfg = dataclasses.replace(SpectralConfig(), frequency_source='map_planarity',
                              local_map_voxel_m=0.02)
    source = make_source(SpectralFilter(cfg))
    assert isinstance(source, MapPlanaritySource)
    scan = Scan(0, points, ring=np.zeros(len(points), np.uint16))
    freqs = source.frequencies(scan, 10)
    assert np.all(freqs.band > 0)  # every point is on the map (it is the map)
    assert np.median(freqs.nu[:4000]) > 0.9 * PLANAR_NU
    assert np.median(freqs.nu[4000:]) < 0.2 * PLANAR_NU
    # A stricter scale calls less of the foliage smooth, never more.
    strict = make_source(SpectralFilter(dataclasses.replace(cfg, planarity_rough_variation=0.02)))
    strict_nu = strict.frequencies(scan, 10).nu
    assert np.all(strict_nu <= freqs.nu + 1e-6)
    assert np.mean(strict_nu[4000:]) < np.mean(freqs.nu[4000:])


@pytest.mark.parametrize('field, value', [('planarity_neighbours', 2),
                                          ('planarity_neighbours', 15.0),
                                          ('planarity_rough_variation', 0.0),
                                          ('planarity_rough_variation', 0.5),
                                          ('planarity_rough_variation', float('nan'))])
def test_invalid_planarity_settings_are_refused(field, value):
    with pytest.raises(ConfigError, match=field):
        dataclasses.replace(SpectralConfig(), **{field: value}).validate()


@pytest.mark.parametrize('source', ['local_map', 'map_planarity'])
def test_pipeline_with_a_map_source_runs_and_keeps_all_with_all_pass(source):
    config = with_values(GftOdomConfig(), {'spectral.frequency_source': source})
    pipeline = OdometryPipeline(config)
    for k in range(3):
        result = pipeline.register_frame(dataclasses.replace(wall_scan(0.05 * k, seed=k),
                                                             stamp_ns=k * 100_000_000))
        assert result.nu is not None and result.n_points_kept == result.n_points_in


def test_the_shuffled_control_permutes_each_scans_frequencies_by_its_seed():
    nu = np.linspace(0.0, 1.0, 500)
    drawn = {}
    for seed in (0, 0, 1, 2):
        pipeline = OdometryPipeline(with_values(GftOdomConfig(), {
            'pipeline.shuffle_frequencies': True, 'pipeline.shuffle_seed': seed}))
        drawn.setdefault(seed, []).append(pipeline._registration_nu(nu, 123_456_789))
    for permuted, *_ in drawn.values():
        np.testing.assert_array_equal(np.sort(permuted), nu)  # the same values
        assert np.mean(permuted == nu) < 0.05  # on other points
    np.testing.assert_array_equal(*drawn[0])  # a seed draws one permutation
    assert not np.array_equal(drawn[0][0], drawn[1][0])
    assert not np.array_equal(drawn[1][0], drawn[2][0])
    unshuffled = OdometryPipeline(GftOdomConfig())
    assert unshuffled._registration_nu(nu, 123_456_789) is nu


def test_a_negative_shuffle_seed_is_refused():
    with pytest.raises(ConfigError, match='shuffle_seed'):
        with_values(GftOdomConfig(), {'pipeline.shuffle_seed': -1})
