"""A scan's frequencies computed after its pose (`OdometryPipeline.frequencies_after_pose`):
the same poses, frequencies and map as computed before it, and computed before it whenever
something needs them there (a mask that drops points)."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.config import GftOdomConfig, with_values
from gft_odom.pipeline import OdometryPipeline
from gft_odom.sim.simulator import ScanSimulator, SimConfig

N_SCANS = 24


@pytest.fixture(scope='module')
def row_scans():
    """A simulated row drive (half the VLP-16's azimuth resolution, for speed)."""
    sim = ScanSimulator.from_config(SimConfig(azimuth_step_deg=0.4), 'uturn', 40, 5)
    return [sim.scan(i).scan for i in range(N_SCANS)]


class _Before(OdometryPipeline):
    """The control: every scan's frequencies computed before its pose."""

    frequencies_after_pose = False


def _run(scans, overrides=None, update_map=True, between=None, before=False):
    """`between(pipeline, k)`: called after scan k's pose, before its update_map."""
    cls = _Before if before else OdometryPipeline
    pipeline = cls(with_values(GftOdomConfig(), overrides or {}))
    results, done_at_pose = [], []
    for k, scan in enumerate(scans):
        result = pipeline.register_frame(scan)
        done_at_pose.append(result.frequencies is None or result.frequencies.done)
        if between is not None:
            between(pipeline, k)
        if update_map:
            pipeline.update_map()
        results.append(result)
    return pipeline, results, done_at_pose


def _map_smoothness(pipeline):
    return [s for _, _, s in pipeline.registration.local_map._keyframes]


@pytest.mark.parametrize('overrides', [{}, {'pipeline.shuffle_frequencies': True}])
def test_after_the_pose_gives_the_same_poses_frequencies_and_map(row_scans, overrides):
    after, after_results, after_done = _run(row_scans, overrides)
    before, before_results, before_done = _run(row_scans, overrides, before=True)
    assert after.frequencies_after_pose and not before.frequencies_after_pose
    assert not any(after_done) and all(before_done)
    for a, b in zip(after_results, before_results):
        np.testing.assert_array_equal(a.T_world_sensor, b.T_world_sensor)
        assert a.status == b.status and a.n_points_kept == b.n_points_kept
        np.testing.assert_array_equal(a.nu, b.nu)
        np.testing.assert_array_equal(a.band, b.band)
        assert a.timings_s['filter'] > 0.0 and 'map_update' in a.timings_s
    kept_after, kept_before = _map_smoothness(after), _map_smoothness(before)
    assert len(kept_after) == len(kept_before) >= 2
    for a, b in zip(kept_after, kept_before):
        assert a is not None and np.isfinite(a).any()
        np.testing.assert_array_equal(a, b)


def test_the_next_scan_finishes_what_its_caller_left(row_scans):
    """A caller that never calls update_map gets the same poses and keyframe smoothness."""
    lazy, lazy_results, _ = _run(row_scans[:12], update_map=False)
    eager, eager_results, _ = _run(row_scans[:12])
    for a, b in zip(lazy_results[:-1], eager_results[:-1]):
        np.testing.assert_array_equal(a.T_world_sensor, b.T_world_sensor)
    lazy.update_map()
    for a, b in zip(_map_smoothness(lazy), _map_smoothness(eager)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('overrides', [
    {'spectral.band_mask': [1, 2, 3]},  # the mask drops points by their frequency
    {'spectral.keep_isolated': False},  # ... and band-0 points
])
def test_what_needs_the_frequencies_before_the_pose_gets_them_then(row_scans, overrides):
    pipeline, results, done_at_pose = _run(row_scans[:4], overrides)
    assert not pipeline.frequencies_after_pose and all(done_at_pose)
    if 'spectral.band_mask' in overrides:
        assert any(r.n_points_kept < r.n_points_in for r in results)


@pytest.mark.parametrize('step', ['reconfigure', 'reset', 'map_snapshot'])
def test_a_call_between_a_pose_and_its_update_map_sees_the_scan_finished(row_scans, step):
    """reconfigure, reset and map_snapshot first finish the last scan's work, in the order
    and with the settings it was registered with."""
    def between(pipeline, k):
        if k == 6:
            if step == 'reconfigure':
                pipeline.reconfigure(pipeline.config)
            elif step == 'reset':
                pipeline.reset()
            else:
                pipeline.map_snapshot()

    after, after_results, _ = _run(row_scans[:12], between=between)
    before, before_results, _ = _run(row_scans[:12], between=between, before=True)
    for a, b in zip(after_results, before_results):
        np.testing.assert_array_equal(a.T_world_sensor, b.T_world_sensor)
        np.testing.assert_array_equal(a.nu, b.nu)
    for a, b in zip(_map_smoothness(after), _map_smoothness(before)):
        np.testing.assert_array_equal(a, b)


def test_frequencies_that_fail_after_the_pose_lose_nothing_else(row_scans, caplog):
    """The second scan's frequencies raise, the published ones and the anchors' (its keyframe
    replaces the first's, which was not deskewed): its pose and keyframe stay (the keyframe
    without smoothness), the warning says so, and the scans after it are as without the
    failure."""
    pipeline = OdometryPipeline(GftOdomConfig())
    assert pipeline.anchor_filter is not None  # the anchors have their own definition

    def failing_once(compute):
        def compute_or_fail(cropped, n_bands):
            if cropped.stamp_ns == row_scans[1].stamp_ns:
                raise ValueError('a broken spectrum')
            return compute(cropped, n_bands)
        return compute_or_fail
    for spectral_filter in (pipeline.spectral_filter, pipeline.anchor_filter):
        spectral_filter.scan_frequencies = failing_once(spectral_filter.scan_frequencies)
    results = []
    for scan in row_scans[:8]:
        results.append(pipeline.register_frame(scan))
        pipeline.update_map()
    assert 'failed after its pose' in caplog.text and 'broken spectrum' in caplog.text
    assert results[1].nu is None and results[1].band is None  # that scan's only
    points, nu = pipeline.map_snapshot()  # the node's ~/save_map after it
    assert points.shape[0] and nu.shape == (points.shape[0],)
    first_keyframe = _map_smoothness(pipeline)[0]
    assert first_keyframe.size and np.isnan(first_keyframe).all()
    _, normal, _ = _run(row_scans[:8])
    for a, b in zip(results, normal):
        assert a.status == b.status
        np.testing.assert_allclose(a.T_world_sensor, b.T_world_sensor, atol=1e-9)
    assert all(np.isfinite(r.nu).any() for r in results[2:])


def test_the_anchors_keep_their_own_frequency_when_the_published_one_fails(row_scans):
    """The published frequency (range-slope weights) and the anchors' (distance weights) are
    computed apart: one failing costs the other nothing; with distance weights published, the
    anchors read those."""
    pipeline = OdometryPipeline(GftOdomConfig())

    def broken(cropped, n_bands):
        raise ValueError('a broken spectrum')
    pipeline.spectral_filter.scan_frequencies = broken
    for scan in row_scans[:8]:
        pipeline.register_frame(scan)
        pipeline.update_map()
    keyframes = _map_smoothness(pipeline)
    assert keyframes and all(np.isfinite(k).any() for k in keyframes)
    same = OdometryPipeline(with_values(GftOdomConfig(), {
        'spectral.scan_line_weight': 'distance'}))
    assert same.anchor_filter is None
