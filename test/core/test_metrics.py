"""Trajectory metrics: hand-computed cases, invariances, degenerate inputs, agreement with evo."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from gft_odom.core.alignment import associate, interpolate_positions, umeyama_alignment
from gft_odom.core.geometry import rpy_transform
from gft_odom.core.metrics import (
    MetricsConfig,
    TrajectoryEvaluator,
    ate,
    evaluate,
    paper_mse,
    rpe_drift,
    rpe_segments,
)
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import ConfigError, GroundTruthError

PERIOD_NS = 100_000_000  # 10 Hz, as the VLP-16


def _poses(positions: np.ndarray, rotvecs: np.ndarray) -> np.ndarray:
    poses = np.tile(np.eye(4), (positions.shape[0], 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    poses[:, :3, 3] = positions
    return poses


def _random_trajectory(rng: np.random.Generator, n: int, start_ns: int = 1_700_000_000 * 10**9,
                       planar: bool = False) -> Trajectory:
    """A smooth ground-robot-like path: wandering heading, ~1 m/s, small roll/pitch."""
    yaw = np.cumsum(rng.normal(0.0, 0.05, n))
    speed_m = 0.1 * (1.0 + 0.3 * np.sin(np.arange(n) / 17.0))
    step = np.stack([speed_m * np.cos(yaw), speed_m * np.sin(yaw),
                     np.zeros(n) if planar else 0.01 * rng.normal(size=n)], axis=1)
    positions = np.cumsum(step, axis=0)
    tilt = np.zeros((n, 2)) if planar else 0.03 * rng.normal(size=(n, 2))
    rotvecs = np.column_stack([tilt, yaw])
    return Trajectory(start_ns + np.arange(n, dtype=np.int64) * PERIOD_NS,
                      _poses(positions, rotvecs))


def _noisy(traj: Trajectory, rng: np.random.Generator, sigma_m: float = 0.05,
           sigma_rad: float = 0.01, jitter_ns: int = 0) -> Trajectory:
    n = len(traj)
    noise = np.tile(np.eye(4), (n, 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, sigma_rad, (n, 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0.0, sigma_m, (n, 3))
    jitter = rng.integers(-jitter_ns, jitter_ns + 1, n) if jitter_ns else 0
    return Trajectory(traj.stamps_ns + jitter, traj.poses @ noise)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def ref(rng) -> Trajectory:
    return _random_trajectory(rng, 400)


# --- hand-computed cases ---------------------------------------------------------------------

@pytest.mark.parametrize('mode', ['se3', 'sim3', 'position'])
def test_identical_trajectories_score_zero(ref, mode):
    result = ate(ref, ref, mode=mode)
    assert result.n == len(ref)
    assert result.rmse_m < 1e-9 and result.max_m < 1e-9
    assert result.scale == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(result.T_ref_est, np.eye(4), atol=1e-9)
    if mode == 'se3':
        assert result.rotation_rmse_deg < 1e-6
    else:
        assert math.isnan(result.rotation_rmse_deg)
    assert paper_mse(ref, ref) < 1e-18
    for use_orientation in (False, True):
        drift = rpe_drift(ref, ref, lengths_m=(5.0, 10.0, 20.0), use_orientation=use_orientation)
        assert drift['drift_pct'] < 1e-9
        assert all(count > 0 for count in drift['count_per_length'])


@pytest.mark.parametrize('mode', ['se3', 'position'])
def test_constant_rigid_offset_is_removed_by_alignment(ref, mode):
    T_offset = rpy_transform((3.0, -7.0, 0.5), (0.02, -0.01, 1.2))
    est = ref.transformed(T_offset)
    result = ate(est, ref, mode=mode)
    assert result.rmse_m < 1e-9
    # The alignment found is the inverse of the offset applied.
    np.testing.assert_allclose(result.T_ref_est @ T_offset, np.eye(4), atol=1e-9)
    if mode == 'se3':
        assert result.rotation_rmse_deg < 1e-6
    assert rpe_drift(est, ref, use_orientation=mode == 'se3')['drift_pct'] < 1e-9


def test_known_noise_pattern_gives_hand_computed_statistics(rng):
    # The robot rests two stamps at each waypoint; est is off by +e then -e there. The errors
    # cancel in the mean and in the cross-covariance, so the best alignment is the identity and
    # the ATE is exactly the pattern's statistics.
    n_waypoints = 60
    waypoints = np.column_stack([np.cos(np.arange(n_waypoints) / 9.0) * 20.0,
                                 np.sin(np.arange(n_waypoints) / 7.0) * 12.0,
                                 np.sin(np.arange(n_waypoints) / 5.0)])
    magnitudes_m = np.resize([0.1, 0.2, 0.3], n_waypoints)
    directions = rng.normal(size=(n_waypoints, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    offsets = directions * magnitudes_m[:, None]
    ref_positions = np.repeat(waypoints, 2, axis=0)
    est_positions = ref_positions + np.stack([offsets, -offsets], axis=1).reshape(-1, 3)
    stamps = np.arange(2 * n_waypoints, dtype=np.int64) * PERIOD_NS
    zero_rot = np.zeros((2 * n_waypoints, 3))
    ref_traj = Trajectory(stamps, _poses(ref_positions, zero_rot))
    est_traj = Trajectory(stamps, _poses(est_positions, zero_rot))

    mean_sq_error_m2 = (0.1**2 + 0.2**2 + 0.3**2) / 3.0
    expected_rmse = math.sqrt(mean_sq_error_m2)
    for mode in ('position', 'se3'):
        result = ate(est_traj, ref_traj, mode=mode)
        assert result.rmse_m == pytest.approx(expected_rmse, rel=1e-9)
        assert result.mean_m == pytest.approx(0.2, rel=1e-9)
        assert result.median_m == pytest.approx(0.2, rel=1e-9)
        assert result.max_m == pytest.approx(0.3, rel=1e-9)
        assert result.std_m == pytest.approx(math.sqrt(expected_rmse**2 - 0.2**2), rel=1e-9)
        np.testing.assert_allclose(result.T_ref_est, np.eye(4), atol=1e-9)
    assert paper_mse(est_traj, ref_traj) == pytest.approx(expected_rmse**2, rel=1e-9)
    # Sim(3): the noise inflates the estimate's spread, so the best scale shrinks it:
    # s = var_ref / (var_ref + mean |e|^2), and the squared error splits into (s - 1)^2 var_ref
    # + s^2 mean |e|^2 (the cross term cancels pairwise as above).
    var_ref_m2 = float(np.mean(np.sum((ref_positions - waypoints.mean(axis=0)) ** 2, axis=1)))
    scale = var_ref_m2 / (var_ref_m2 + mean_sq_error_m2)
    sim3 = ate(est_traj, ref_traj, mode='sim3')
    assert sim3.scale == pytest.approx(scale, rel=1e-9)
    assert sim3.rmse_m == pytest.approx(
        math.sqrt((scale - 1.0) ** 2 * var_ref_m2 + scale**2 * mean_sq_error_m2), rel=1e-9)


def test_full_pose_drift_of_a_scaled_straight_run_is_hand_computed():
    # Straight line, 0.3 m a frame; est over-reports every motion by 2 %. The first frame more
    # than 5 m on is 17 frames (5.1 m) later, so each 5 m segment is 0.02 * 5.1 m off.
    n = 100
    positions = np.column_stack([0.3 * np.arange(n), np.zeros(n), np.zeros(n)])
    stamps = np.arange(n, dtype=np.int64) * PERIOD_NS
    ref_traj = Trajectory(stamps, _poses(positions, np.zeros((n, 3))))
    est_traj = Trajectory(stamps, _poses(1.02 * positions, np.zeros((n, 3))))
    drift = rpe_drift(est_traj, ref_traj, lengths_m=(5.0, 1000.0), use_orientation=True)
    assert drift['drift_pct_per_length'][0] == pytest.approx(100.0 * 0.02 * 5.1 / 5.0, rel=1e-9)
    assert drift['count_per_length'] == [n - 17, 0]
    assert math.isnan(drift['drift_pct_per_length'][1])
    assert drift['drift_pct'] == pytest.approx(drift['drift_pct_per_length'][0], rel=1e-12)
    assert drift['rot_drift_deg_per_m'] < 1e-9
    # The position-only variant needs a rigid alignment, impossible on a straight line.
    with pytest.raises(GroundTruthError, match='collinear'):
        rpe_drift(est_traj, ref_traj, use_orientation=False)


def test_position_drift_matches_a_loop_reference_implementation(rng):
    ref_traj = _random_trajectory(rng, 150, planar=True)
    centroid = ref_traj.positions_xyz.mean(axis=0)
    scaled = ref_traj.positions_xyz.copy()
    scaled = centroid + 1.02 * (scaled - centroid)
    est_traj = Trajectory(ref_traj.stamps_ns, _poses(scaled, np.zeros((150, 3))))
    length_m = 4.0
    segments = rpe_segments(est_traj, ref_traj, length_m)
    # Reference: explicit loops. A scaling about the centroid aligns to itself (R = I), so the
    # displacement error is 2 % of each chord.
    p = ref_traj.positions_xyz
    expected = []
    for i in range(len(p)):
        travelled = 0.0
        for j in range(i + 1, len(p)):
            travelled += float(np.linalg.norm(p[j] - p[j - 1]))
            if travelled > length_m:
                expected.append((i, j, 0.02 * np.linalg.norm(p[j] - p[i]) / length_m * 100.0))
                break
    expected = np.array(expected)
    np.testing.assert_array_equal(segments.first_idx, expected[:, 0].astype(int))
    np.testing.assert_array_equal(segments.last_idx, expected[:, 1].astype(int))
    np.testing.assert_allclose(segments.error_pct, expected[:, 2], rtol=1e-6)
    assert np.isnan(segments.rot_error_deg_per_m).all()


# --- invariances -----------------------------------------------------------------------------

def test_se3_ate_is_invariant_to_a_rigid_motion_of_est(rng, ref):
    est = _noisy(ref, rng)
    moved = est.transformed(rpy_transform((-40.0, 12.0, 3.0), (0.3, -0.2, 2.5)))
    a, b = ate(est, ref, mode='se3'), ate(moved, ref, mode='se3')
    assert a.rmse_m > 0.01
    for name in ('rmse_m', 'mean_m', 'median_m', 'max_m', 'std_m', 'rotation_rmse_deg'):
        assert getattr(b, name) == pytest.approx(getattr(a, name), rel=1e-7)
    full_a = rpe_drift(est, ref, use_orientation=True)
    full_b = rpe_drift(moved, ref, use_orientation=True)
    assert full_b['drift_pct'] == pytest.approx(full_a['drift_pct'], rel=1e-7)


def test_sim3_ate_is_invariant_to_scale_and_reports_it(rng, ref):
    est = _noisy(ref, rng)
    scale = 3.7
    shrunk = Trajectory(est.stamps_ns, est.poses.copy())
    shrunk.poses[:, :3, 3] = 5.0 + est.positions_xyz / scale
    moved = shrunk.transformed(rpy_transform((1.0, 2.0, 3.0), (0.0, 0.1, -0.7)))
    a, b = ate(est, ref, mode='sim3'), ate(moved, ref, mode='sim3')
    assert b.rmse_m == pytest.approx(a.rmse_m, rel=1e-7)
    assert b.max_m == pytest.approx(a.max_m, rel=1e-7)
    assert b.scale == pytest.approx(a.scale * scale, rel=1e-7)
    # Without scale, the shrunk estimate is far off.
    assert ate(moved, ref, mode='position').rmse_m > 10.0 * a.rmse_m


# --- Umeyama ---------------------------------------------------------------------------------

@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), scale=st.floats(0.1, 10.0), planar=st.booleans())
def test_umeyama_recovers_a_known_similarity(seed, scale, planar):
    rng = np.random.default_rng(seed)
    src = rng.normal(0.0, 10.0, (20, 3))
    if planar:
        src[:, 2] = 0.0  # the ground-robot case: a reflection fits as well as the rotation
    rotation = Rotation.random(random_state=seed).as_matrix()
    translation = rng.normal(0.0, 50.0, 3)
    dst = scale * src @ rotation.T + translation
    R, t, s = umeyama_alignment(src, dst, with_scale=True)
    np.testing.assert_allclose(R, rotation, atol=1e-8)
    np.testing.assert_allclose(t, translation, atol=1e-6)
    assert s == pytest.approx(scale, rel=1e-9)
    R_rigid, _, s_rigid = umeyama_alignment(src, src @ rotation.T, with_scale=False)
    np.testing.assert_allclose(R_rigid, rotation, atol=1e-8)
    assert s_rigid == 1.0


def test_umeyama_returns_a_rotation_when_a_reflection_fits_best(rng):
    src = rng.normal(0.0, 5.0, (30, 3))
    mirrored = src * np.array([1.0, 1.0, -1.0])
    R, t, _ = umeyama_alignment(src, mirrored, with_scale=False)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # It is the best proper rotation: no worse than identity.
    cost = np.sum((mirrored - (src @ R.T + t)) ** 2)
    assert cost <= np.sum((mirrored - src - (mirrored - src).mean(axis=0)) ** 2) + 1e-9


@pytest.mark.parametrize('src', [
    np.zeros((2, 3)),  # too few
    np.outer(np.arange(10.0), [1.0, 2.0, 0.5]),  # collinear
    np.ones((10, 3)),  # all identical
    np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [np.nan, 1.0, 0.0]]),  # not finite
], ids=['too-few', 'collinear', 'identical', 'nan'])
def test_umeyama_degenerate_inputs_raise(src):
    with pytest.raises(GroundTruthError):
        umeyama_alignment(src, src + 1.0, with_scale=True)


def test_umeyama_rejects_mismatched_shapes():
    with pytest.raises(GroundTruthError, match='shape'):
        umeyama_alignment(np.zeros((5, 3)), np.zeros((4, 3)))


# --- association and interpolation -----------------------------------------------------------

def test_associate_uses_each_reference_once_and_respects_tolerance():
    ref = Trajectory(np.arange(10, dtype=np.int64) * PERIOD_NS, np.tile(np.eye(4), (10, 1, 1)))
    # 20 Hz estimate: two candidates per reference stamp, 0 and 50 ms away.
    est_stamps = np.arange(20, dtype=np.int64) * (PERIOD_NS // 2)
    est = Trajectory(est_stamps, np.tile(np.eye(4), (20, 1, 1)))
    est_idx, ref_idx = associate(est, ref, max_diff_s=0.05)
    np.testing.assert_array_equal(ref_idx, np.arange(10))
    np.testing.assert_array_equal(est_idx, np.arange(0, 20, 2))
    # Tolerance is inclusive and exact in integer nanoseconds.
    shifted = Trajectory(ref.stamps_ns + 30_000_000, ref.poses)
    assert len(associate(shifted, ref, max_diff_s=0.03)[0]) == 10
    assert len(associate(shifted, ref, max_diff_s=0.029999999)[0]) == 0


def test_associate_matches_evo_on_jittered_stamps(rng, ref):
    from evo.core import sync  # a test dependency: missing evo fails, not skips
    est = _noisy(ref, rng, jitter_ns=20_000_000)
    est = Trajectory(est.stamps_ns[30:-25], est.poses[30:-25])
    est_idx, ref_idx = associate(est, ref, max_diff_s=0.05)
    evo_est, evo_ref = sync.matching_time_indices(est.stamps_s, ref.stamps_s, 0.05)
    np.testing.assert_array_equal(est_idx, evo_est)
    np.testing.assert_array_equal(ref_idx, evo_ref)


def test_interpolate_positions_is_linear_and_nan_outside_or_across_gaps():
    stamps = np.array([0, 1, 2, 10], dtype=np.int64) * 10**9
    positions = np.array([[0.0, 0.0, 0.0], [2.0, 4.0, 0.0], [4.0, 4.0, 2.0], [4.0, 4.0, 2.0]])
    ref = Trajectory(stamps, _poses(positions, np.zeros((4, 3))))
    query = np.array([-1, 0, 500_000_000, 1_250_000_000, 2_000_000_000, 5_000_000_000,
                      10_000_000_000, 11_000_000_000], dtype=np.int64)
    out = interpolate_positions(ref, query, max_gap_s=1.5)
    np.testing.assert_allclose(out[1], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(out[2], [1.0, 2.0, 0.0])
    np.testing.assert_allclose(out[3], [2.5, 4.0, 0.5])
    np.testing.assert_allclose(out[4], [4.0, 4.0, 2.0])
    np.testing.assert_allclose(out[6], [4.0, 4.0, 2.0])
    assert np.isnan(out[[0, 5, 7]]).all()  # before, inside the 8 s gap, after


def test_ate_with_interpolated_low_rate_gps(rng):
    # GPS at 2 Hz; the estimate at 10 Hz moves on straight lines between the GPS fixes.
    gps_stamps = np.arange(40, dtype=np.int64) * 500_000_000
    gps_positions = np.cumsum(rng.normal(0.0, 0.5, (40, 3)) * [1.0, 1.0, 0.1], axis=0)
    gps = Trajectory(gps_stamps, _poses(gps_positions, np.zeros((40, 3))))
    est_stamps = np.arange(196, dtype=np.int64) * PERIOD_NS
    est_positions = np.column_stack([np.interp(est_stamps, gps_stamps, gps_positions[:, k])
                                     for k in range(3)])
    est = Trajectory(est_stamps, _poses(est_positions, rng.normal(size=(196, 3))))
    est = est.transformed(rpy_transform((5.0, 1.0, 0.0), (0.0, 0.0, 0.7)))
    interpolated = ate(est, gps, mode='position', match='interpolate')
    nearest = ate(est, gps, mode='position')
    assert interpolated.n == 196 and nearest.n == 40
    assert interpolated.rmse_m < 1e-9 and nearest.rmse_m < 1e-9
    with pytest.raises(ConfigError, match='interpolate'):
        ate(est, gps, mode='se3', match='interpolate')


# --- errors ----------------------------------------------------------------------------------

def test_too_few_overlapping_stamps_names_counts_and_time_ranges(ref):
    late = Trajectory(ref.stamps_ns + 3600 * 10**9, ref.poses)
    with pytest.raises(GroundTruthError, match=r'only 0 estimated stamps overlap') as info:
        ate(late, ref)
    message = str(info.value)
    assert f'{ref.stamps_s[0]:.3f}' in message and f'{late.stamps_s[-1]:.3f}' in message
    two = Trajectory(ref.stamps_ns[:2], ref.poses[:2])
    with pytest.raises(GroundTruthError, match='only 2'):
        evaluate(two, ref)


def test_invalid_arguments_raise_config_error(ref):
    with pytest.raises(ConfigError, match='mode'):
        ate(ref, ref, mode='kitti')
    with pytest.raises(ConfigError, match='max_diff_s'):
        associate(ref, ref, max_diff_s=-0.1)
    with pytest.raises(ConfigError, match='lengths_m'):
        rpe_drift(ref, ref, lengths_m=(10.0, 0.0))
    with pytest.raises(ConfigError, match='match'):
        evaluate(ref, ref, match='cubic')
    with pytest.raises(ConfigError, match='max_gap_s'):
        MetricsConfig(max_gap_s=math.inf).validate()


def test_unsorted_stamps_raise(ref):
    shuffled = Trajectory(ref.stamps_ns[::-1].copy(), ref.poses)
    with pytest.raises(GroundTruthError, match='not sorted'):
        ate(shuffled, ref)


# --- evaluate --------------------------------------------------------------------------------

def test_evaluate_is_flat_json_and_consistent(rng, ref):
    est = _noisy(ref, rng, jitter_ns=10_000_000)
    lengths_m = (5.0, 20.0, 1000.0)
    out = evaluate(est, ref, mode='position', lengths_m=lengths_m)
    json.dumps(out, allow_nan=False)
    for key in ('ate_rmse_m', 'ate_mean_m', 'ate_median_m', 'ate_max_m', 'paper_mse_m2',
                'rpe_drift_pct', 'n_matched', 'path_length_m'):
        assert key in out
    assert all(not isinstance(v, (dict, list, tuple)) for v in out.values())
    result = ate(est, ref, mode='position')
    assert out['ate_rmse_m'] == pytest.approx(result.rmse_m, rel=1e-12)
    assert out['paper_mse_m2'] == pytest.approx(result.rmse_m**2, rel=1e-9)
    assert out['n_matched'] == len(ref)
    assert out['path_length_m'] == pytest.approx(ref.path_length_m(), rel=1e-12)
    assert out['rpe_drift_pct_1000m'] is None and out['rpe_count_1000m'] == 0
    assert out['rpe_count_5m'] > out['rpe_count_20m'] > 0
    drift = rpe_drift(est, ref, lengths_m=lengths_m)
    assert out['rpe_drift_pct'] == pytest.approx(drift['drift_pct'], rel=1e-12)
    assert out['rotation_rmse_deg'] is None
    se3 = TrajectoryEvaluator.from_config(MetricsConfig(mode='se3')).evaluate(est, ref)
    assert se3['rotation_rmse_deg'] > 0.1 and se3['paper_mse_m2'] == out['paper_mse_m2']


def test_metrics_config_defaults_are_valid_and_ros_friendly():
    cfg = MetricsConfig()
    cfg.validate()
    assert isinstance(cfg.lengths_m, tuple) and all(isinstance(v, float) for v in cfg.lengths_m)
    with pytest.raises(ConfigError):
        MetricsConfig(mode='bogus').validate()


# --- agreement with evo ----------------------------------------------------------------------

def _to_evo(traj: Trajectory):
    from evo.core.trajectory import PoseTrajectory3D
    return PoseTrajectory3D(poses_se3=list(traj.poses), timestamps=traj.stamps_s.copy())


@pytest.mark.parametrize('mode', ['se3', 'sim3', 'position'])
def test_ate_agrees_with_evo(mode):
    from evo.core import metrics as evo_metrics
    from evo.core import sync

    for seed in range(3):
        rng = np.random.default_rng(seed)
        ref = _random_trajectory(rng, 300)
        est = _noisy(ref, rng, sigma_m=0.2, sigma_rad=0.02, jitter_ns=20_000_000)
        est = Trajectory(est.stamps_ns[20:-10], est.poses[20:-10])
        # Odometry drifts in its own frame, and a wrong scale for the sim3 case.
        if mode == 'sim3':
            est = Trajectory(est.stamps_ns, est.poses.copy())
            est.poses[:, :3, 3] *= 0.8
        est = est.transformed(rpy_transform((4.0, -2.0, 0.3), (0.01, 0.02, 0.8)))

        ours = ate(est, ref, mode=mode, max_diff_s=0.05)
        evo_ref, evo_est = sync.associate_trajectories(_to_evo(ref), _to_evo(est), max_diff=0.05)
        evo_est = copy.deepcopy(evo_est)
        evo_est.align(evo_ref, correct_scale=mode == 'sim3')
        ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        ape.process_data((evo_ref, evo_est))
        stats = ape.get_all_statistics()
        assert ours.n == evo_ref.num_poses
        for name, key in (('rmse_m', 'rmse'), ('mean_m', 'mean'), ('median_m', 'median'),
                          ('max_m', 'max'), ('std_m', 'std')):
            assert getattr(ours, name) == pytest.approx(stats[key], abs=1e-6), name
        if mode == 'se3':
            ape_rot = evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg)
            ape_rot.process_data((evo_ref, evo_est))
            assert ours.rotation_rmse_deg == pytest.approx(ape_rot.get_statistic(
                evo_metrics.StatisticsType.rmse), abs=1e-6)
        if mode == 'sim3':
            assert ours.scale == pytest.approx(1.0 / 0.8, rel=0.05)


@pytest.mark.parametrize('length_m', [4.0, 10.0])
def test_rpe_segments_agree_with_evo_where_definitions_coincide(length_m):
    """evo's RPE (delta in metres, all_pairs=False) chains non-overlapping segments from frame 0,
    each ending at the first frame whose path distance reaches delta; ours starts a segment at
    every frame (KITTI). Path distance along the reference (pairs_from_reference=True) and, for
    random data, '>=' (evo) and '>' (ours) pick the same end frame. So evo's segments are the
    subset of ours starting at evo's ids, and there the per-segment errors must agree. The
    means differ by construction (different segment sets), so they are not compared.

    Full-pose variant: evo's translation_part |t((Q_i^-1 Q_j)^-1 P_i^-1 P_j)| = ours * L / 100.
    Position variant: ours equals evo's translation_part on the rigidly aligned positions with
    identity orientations (then the relative pose error is the displacement difference).
    """
    from evo.core import metrics as evo_metrics

    rng = np.random.default_rng(7)
    ref = _random_trajectory(rng, 400)
    est = _noisy(ref, rng, sigma_m=0.05, sigma_rad=0.01)
    est = est.transformed(rpy_transform((2.0, 1.0, 0.0), (0.0, 0.0, 0.4)))

    def evo_segments(ref_traj, est_traj, relation):
        rpe = evo_metrics.RPE(relation, delta=length_m, delta_unit=evo_metrics.Unit.meters,
                              all_pairs=False, pairs_from_reference=True)
        rpe.process_data((_to_evo(ref_traj), _to_evo(est_traj)))
        last = np.asarray(rpe.delta_ids)
        first = np.concatenate([[0], last[:-1]])
        return first, last, rpe.error

    ours = rpe_segments(est, ref, length_m, use_orientation=True)
    first, last, evo_err = evo_segments(ref, est, evo_metrics.PoseRelation.translation_part)
    assert first.size > 3
    lookup = {int(i): k for k, i in enumerate(ours.first_idx)}
    rows = np.array([lookup[int(i)] for i in first])
    np.testing.assert_array_equal(ours.last_idx[rows], last)
    np.testing.assert_allclose(ours.error_pct[rows] * length_m / 100.0, evo_err, atol=1e-6)
    _, _, evo_rot = evo_segments(ref, est, evo_metrics.PoseRelation.rotation_angle_deg)
    np.testing.assert_allclose(ours.rot_error_deg_per_m[rows] * length_m, evo_rot, atol=1e-6)

    # Position-only variant on the aligned positions, orientations set to identity.
    ours_pos = rpe_segments(est, ref, length_m, use_orientation=False)
    R, t, _ = umeyama_alignment(est.positions_xyz, ref.positions_xyz)
    zero = np.zeros((len(ref), 3))
    est_aligned = Trajectory(est.stamps_ns, _poses(est.positions_xyz @ R.T + t, zero))
    ref_positions_only = Trajectory(ref.stamps_ns, _poses(ref.positions_xyz, zero))
    first, last, evo_err = evo_segments(ref_positions_only, est_aligned,
                                        evo_metrics.PoseRelation.translation_part)
    rows = np.array([lookup[int(i)] for i in first])
    np.testing.assert_array_equal(ours_pos.last_idx[rows], last)
    np.testing.assert_allclose(ours_pos.error_pct[rows] * length_m / 100.0, evo_err, atol=1e-6)


# --- CitrusFarm's own scoring: mean error and end-point error after rigid alignment ------------

def _circle(n: int, radius_m: float, z_m: np.ndarray | float = 0.0) -> Trajectory:
    """A robot driving once around a circle, heading along the tangent (n poses, 10 Hz)."""
    angle = 2.0 * np.pi * np.arange(n) / n
    positions = np.column_stack([radius_m * np.cos(angle), radius_m * np.sin(angle),
                                 np.broadcast_to(z_m, (n,))])
    rotvecs = np.column_stack([np.zeros(n), np.zeros(n), angle + np.pi / 2])
    return Trajectory(1_700_000_000 * 10**9 + np.arange(n, dtype=np.int64) * PERIOD_NS,
                      _poses(positions, rotvecs))


def test_identical_trajectories_have_zero_mean_and_end_point_error(ref):
    for mode in ('position', 'se3', 'sim3'):
        out = TrajectoryEvaluator(mode=mode).metrics(ref, ref)
        assert out.ate_mean_m < 1e-9 and out.end_error_m < 1e-9
    assert ate(ref, ref, mode='position').end_error_m < 1e-9


@pytest.mark.parametrize('offset_m', [0.05, 0.4, 1.5])
def test_known_offset_gives_known_mean_and_end_point_error(offset_m):
    # est runs a circle offset_m wider than ref, its height alternating +-offset_m. By symmetry
    # the best rigid alignment is the identity (no rotation or shift brings the circles closer),
    # so every matched pose, the last included, is sqrt(2) * offset_m away.
    n = 200
    ref = _circle(n, 10.0)
    z = offset_m * np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    est = _circle(n, 10.0 + offset_m, z).transformed(rpy_transform((3.0, -2.0, 1.0),
                                                                   (0.0, 0.0, 0.7)))
    out = evaluate(est, ref, mode='position')
    expected = math.sqrt(2.0) * offset_m
    assert out['ate_mean_m'] == pytest.approx(expected, rel=1e-9)
    assert out['ate_rmse_m'] == pytest.approx(expected, rel=1e-9)
    assert out['end_error_m'] == pytest.approx(expected, rel=1e-9)


def test_mean_error_with_and_without_the_lever_arm():
    # The GPS antenna sits 0.22 m behind and 0.153 m above the LiDAR (CitrusFarm). Driving a
    # circle of radius r with the heading along the tangent, the antenna runs a circle of radius
    # sqrt(r^2 + 0.22^2), higher and a little behind in phase. Compared without the lever arm,
    # the alignment takes out the height and the phase, not the radius: every error is the
    # radius difference. Moved to the antenna first, the sensor track scores 0.
    from gft_odom.io.ground_truth import GroundTruthConfig

    radius_m = 3.0
    sensor = _circle(300, radius_m)
    T_lidar_gps = GroundTruthConfig().T_lidar_gps()
    antenna = sensor.with_body_offset(T_lidar_gps)
    lever = np.linalg.norm(GroundTruthConfig().lidar_to_gps_xyz_m[:2])
    expected = math.hypot(radius_m, lever) - radius_m
    without = evaluate(sensor, antenna, mode='position')
    assert without['ate_mean_m'] == pytest.approx(expected, rel=1e-6)
    assert without['end_error_m'] == pytest.approx(expected, rel=1e-6)
    with_arm = evaluate(sensor.with_body_offset(T_lidar_gps), antenna, mode='position')
    assert with_arm['ate_mean_m'] < 1e-9 and with_arm['end_error_m'] < 1e-9


def test_end_point_error_is_the_last_aligned_distance_and_uses_a_rigid_alignment(rng, ref):
    # A drift that grows along the run: the end is the worst place, the mean lies below it.
    est = Trajectory(ref.stamps_ns, ref.poses.copy())
    est.poses[:, :3, 3] += np.linspace(0.0, 1.0, len(ref))[:, None] * np.array([0.3, -0.2, 0.1])
    result = ate(est, ref, mode='position')
    assert result.end_error_m == pytest.approx(result.errors_m[-1])
    assert result.end_error_m > result.mean_m > 0.0
    out = evaluate(est, ref, mode='position')
    assert out['end_error_m'] == pytest.approx(result.end_error_m, rel=1e-12)
    json.dumps(out, allow_nan=False)
    # In sim3 mode the ATE figures are with scale, the end-point error stays rigid (CitrusFarm).
    sim3 = evaluate(est, ref, mode='sim3')
    assert sim3['end_error_m'] == pytest.approx(result.end_error_m, rel=1e-12)


def test_mean_and_end_point_error_agree_with_evo():
    from evo.core import metrics as evo_metrics
    from evo.core import sync

    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        ref = _random_trajectory(rng, 300)
        est = _noisy(ref, rng, sigma_m=0.2, sigma_rad=0.02, jitter_ns=20_000_000)
        est.poses[:, :3, 3] += np.cumsum(rng.normal(0.0, 0.02, (len(est), 3)), axis=0)
        est = est.transformed(rpy_transform((4.0, -2.0, 0.3), (0.01, 0.02, 0.8)))
        out = evaluate(est, ref, mode='position', max_diff_s=0.05)
        evo_ref, evo_est = sync.associate_trajectories(_to_evo(ref), _to_evo(est), max_diff=0.05)
        evo_est = copy.deepcopy(evo_est)
        evo_est.align(evo_ref, correct_scale=False)
        ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        ape.process_data((evo_ref, evo_est))
        assert out['ate_mean_m'] == pytest.approx(ape.get_statistic(
            evo_metrics.StatisticsType.mean), abs=1e-6)
        assert out['end_error_m'] == pytest.approx(float(ape.error[-1]), abs=1e-6)
        end_gap = np.linalg.norm(evo_est.positions_xyz[-1] - evo_ref.positions_xyz[-1])
        assert out['end_error_m'] == pytest.approx(end_gap, abs=1e-6)


def test_auto_match_interpolates_inside_and_takes_the_nearest_end_outside():
    """The simulator's GPS starts 37 ms after the first scan: 'auto' pairs the first pose with
    the first fix (as 'nearest' would) and interpolates the others."""
    from gft_odom.core.alignment import match_trajectories as _match
    stamps = np.arange(4, dtype=np.int64) * 100_000_000
    poses = np.repeat(np.eye(4)[None], 4, axis=0)
    poses[:, 0, 3] = np.arange(4) * 0.1  # 1 m/s along x
    est = Trajectory(stamps, poses)
    ref_poses = np.repeat(np.eye(4)[None], 4, axis=0)
    ref_poses[:, 0, 3] = (np.arange(4) * 100 + 37) * 1e-3
    ref = Trajectory(stamps + 37_000_000, ref_poses)
    matched = _match(est, ref, 0.05, 'auto', 1.0, need_orientation=False)
    np.testing.assert_array_equal(matched.est_idx, [0, 1, 2, 3])
    np.testing.assert_allclose(matched.p_ref[:, 0], [0.037, 0.1, 0.2, 0.3])
    with pytest.raises(GroundTruthError):  # plain interpolation keeps only 3 of 4: too few
        _match(Trajectory(stamps[:3], poses[:3]), ref, 0.05, 'interpolate', 1.0, False)
