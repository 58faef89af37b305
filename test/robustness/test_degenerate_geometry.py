"""Degenerate scans through OdometryPipeline: the motion prediction is used, the covariance
says so, the metrics count it; the next good scan registers normally."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.config import GftOdomConfig, with_values
from gft_odom.core.degeneracy import thinnest_axis_std_m
from gft_odom.core.geometry import invert_transform
from gft_odom.core.types import Scan
from gft_odom.io.bags import ScanBagReader
from gft_odom.pipeline import DEGENERATE_STATUS, OdometryPipeline
from gft_odom.replay import ReplayResult, summarize

N_GOOD = 4  # good scans before the degenerate one (a map and a velocity to predict with)


@pytest.fixture(scope='module')
def scans(small_drive):
    with ScanBagReader([small_drive.bag_path]) as reader:
        return list(reader)


def _ground_only(scan: Scan) -> Scan:
    # The sensor is ~0.7 m above the (uneven) simulated ground: returns below -0.5 m are ground.
    return scan.select(np.flatnonzero(scan.points_xyz[:, 2] < -0.5))


def _flat_plane(scan: Scan) -> Scan:
    rng = np.random.default_rng(4)
    n = 6000
    r, a = rng.uniform(2.0, 25.0, n), rng.uniform(-np.pi, np.pi, n)
    xyz = np.c_[r * np.cos(a), r * np.sin(a), -0.7 + rng.normal(0.0, 0.01, n)]
    return Scan(stamp_ns=scan.stamp_ns, points_xyz=xyz, intensity=None, ring=None,
                time_offset_s=None, frame_id=scan.frame_id)


def _few_points(scan: Scan) -> Scan:
    return scan.select(np.arange(0, len(scan), len(scan) // 50)[:50])


def _canopy_only(scan: Scan) -> Scan:
    return scan.select(np.flatnonzero(scan.points_xyz[:, 2] > 0.8))


# A mask that keeps almost nothing: one band, and no isolated points.
ALMOST_NOTHING = {'spectral.band_mask': (9,), 'spectral.keep_isolated': False}


def _run(scans, degrade, overrides=None):
    """N_GOOD good scans, the degraded one, then the next good scan; all results."""
    config = GftOdomConfig()
    pipeline = OdometryPipeline(config)
    results = [pipeline.register_frame(s) for s in scans[:N_GOOD]]
    if overrides:  # the mask changes at run time, as through the node's parameters
        pipeline.reconfigure(with_values(config, overrides))
    results.append(pipeline.register_frame(degrade(scans[N_GOOD])))
    if overrides:
        pipeline.reconfigure(config)
    results.append(pipeline.register_frame(scans[N_GOOD + 1]))
    return pipeline, results


def _prediction(results) -> np.ndarray:
    """Constant velocity from the last two poses (the sim scans are evenly spaced)."""
    a, b = results[N_GOOD - 2].T_world_sensor, results[N_GOOD - 1].T_world_sensor
    return b @ (invert_transform(a) @ b)


@pytest.fixture(scope='module')
def clean_after(scans):
    """The pose of scan N_GOOD + 1 from a run that never saw a degenerate scan."""
    clean = OdometryPipeline(GftOdomConfig())
    return [clean.register_frame(s) for s in scans[:N_GOOD + 2]][-1]


@pytest.mark.parametrize('case, degrade, overrides, status', [
    ('ground_only', _ground_only, None, DEGENERATE_STATUS),
    ('flat_plane', _flat_plane, None, DEGENERATE_STATUS),
    ('fewer_than_min_points', _few_points, None, 'fallback_too_few_points'),
    ('mask_keeps_almost_nothing', lambda s: s, ALMOST_NOTHING, 'fallback_too_few_points'),
])
def test_degenerate_scan_uses_the_prediction(scans, clean_after, case, degrade, overrides,
                                            status):
    pipeline, results = _run(scans, degrade, overrides)
    bad, after = results[N_GOOD], results[N_GOOD + 1]
    assert bad.status == status and bad.fell_back
    np.testing.assert_allclose(bad.T_world_sensor, _prediction(results), atol=1e-9)
    cfg = GftOdomConfig().registration
    np.testing.assert_allclose(np.diag(bad.covariance),
                               [cfg.fallback_std_m ** 2] * 3 + [cfg.fallback_std_rad ** 2] * 3)
    good_var = np.diag(results[N_GOOD - 1].covariance)[:3]
    assert np.all(good_var < 0.01 * cfg.fallback_std_m ** 2)  # the contrast is large
    # The next good scan registers as usual, close to the reference run without the bad one.
    assert after.status == 'ok'
    np.testing.assert_allclose(after.T_world_sensor[:3, 3], clean_after.T_world_sensor[:3, 3],
                               atol=0.05)
    assert pipeline.status_counts[status] == 1


def test_canopy_only_is_not_degenerate(scans):
    """Trunks and crowns constrain every axis: ICP is trusted, no fallback."""
    _, results = _run(scans, _canopy_only)
    assert results[N_GOOD].status == 'ok'
    assert thinnest_axis_std_m(_canopy_only(scans[N_GOOD]).points_xyz) > 0.3


def test_flatness_measure_separates_ground_from_orchard(scans):
    for scan in scans[:3]:
        assert thinnest_axis_std_m(scan.points_xyz) > 0.3
        assert thinnest_axis_std_m(_ground_only(scan).points_xyz) < 0.05
    assert thinnest_axis_std_m(np.zeros((5, 3))) == float('inf')  # too few to judge


def test_metrics_count_the_fallbacks(scans):
    pipeline, results = _run(scans, _flat_plane)
    traj = pipeline.sensor_trajectory()
    replay = ReplayResult(
        sensor_trajectory=traj, base_trajectory=pipeline.base_trajectory(),
        latency_s=np.array([r.timings_s['pipeline'] for r in results]), stage_s={},
        points_in=np.array([r.n_points_in for r in results]),
        points_kept=np.array([r.n_points_kept for r in results]),
        statuses=[r.status for r in results])
    metrics = summarize(replay, GftOdomConfig())
    assert metrics['fallbacks'] == 1
    assert metrics['status_counts'][DEGENERATE_STATUS] == 1
    assert metrics['status_counts']['ok'] == len(results) - 2  # the first scan is 'first'
