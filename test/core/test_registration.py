"""Scan registration: known transforms, chaining, fallbacks, deskew, degenerate scenes.

The scenes are small orchards (trunks as vertical cylinders, canopies as ellipsoids, a wavy
ground) seen by a fake 16-ring scanner that spins clockwise (seen from above) like a VLP-16 and
fires each column at its own time from its own pose, so scans carry real motion distortion.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gft_odom.core.deskew import azimuth_time_offsets, deskew_points
from gft_odom.core.gauss_newton import IcpResult
from gft_odom.core.geometry import invert_transform, make_transform, transform_points
from gft_odom.core.local_map import voxel_downsample_indices
from gft_odom.core.registration import (
    RegistrationConfig,
    ScanRegistration,
    scale_delta,
    thinned_rough,
    transform_magnitude,
)
from gft_odom.errors import ConfigError, RegistrationError

ELEVATIONS_RAD = np.deg2rad(np.arange(-15.0, 16.0, 2.0))
SENSOR_HEIGHT_M = 0.45
SCAN_PERIOD_S = 0.1


# ---------------------------------------------------------------- synthetic orchard + scanner

def make_orchard(seed: int = 0, n_rows: int = 4, trees_per_row: int = 8,
                 row_spacing_m: float = 6.0, tree_spacing_m: float = 4.0,
                 with_trees: bool = True) -> dict:
    """Trunk circles, canopy ellipsoids and a wavy ground, in the world frame."""
    rng = np.random.default_rng(seed)
    xs = np.arange(trees_per_row) * tree_spacing_m - 8.0
    ys = (np.arange(n_rows) - (n_rows - 1) / 2.0) * row_spacing_m  # robot drives at y = 0
    X, Y = np.meshgrid(xs, ys)
    n = X.size if with_trees else 0
    trunk_xy = (np.c_[X.ravel(), Y.ravel()] + rng.normal(0.0, 0.3, (X.size, 2)))[:n]
    crown_z = rng.uniform(1.0, 1.5, n)
    blob_xy = np.repeat(trunk_xy, 3, axis=0) + rng.normal(0.0, 0.6, (3 * n, 2))
    blob_z = np.repeat(crown_z, 3) + rng.uniform(0.6, 1.4, 3 * n)
    return {
        'trunk_xy': trunk_xy, 'trunk_r': rng.uniform(0.08, 0.2, n), 'trunk_top': crown_z + 0.8,
        'blob_c': np.c_[blob_xy, blob_z], 'blob_axes': rng.uniform([0.8, 0.8, 0.6],
                                                                   [1.6, 1.6, 1.2], (3 * n, 3)),
    }


def ground_height(xy: np.ndarray) -> np.ndarray:
    return 0.15 * np.sin(0.3 * xy[..., 0]) * np.cos(0.25 * xy[..., 1])


def cast_rays(scene: dict, origins: np.ndarray, dirs: np.ndarray,
              max_range_m: float = 50.0) -> np.ndarray:
    """Range of the first hit along each unit ray, inf when nothing is hit."""
    dz = dirs[:, 2]
    down = dz < -1e-6
    with np.errstate(divide='ignore', invalid='ignore'):
        t = np.where(down, -origins[:, 2] / dz, np.inf)
        for _ in range(3):  # fixed point onto the wavy ground
            p = origins + np.where(np.isfinite(t), t, 0.0)[:, None] * dirs
            t = np.where(down, (ground_height(p[:, :2]) - origins[:, 2]) / dz, np.inf)
    best = np.where(t > 0.0, t, np.inf)
    if len(scene['trunk_r']):
        o2 = origins[:, None, :2] - scene['trunk_xy'][None]
        d2 = dirs[:, None, :2]
        a = (d2 ** 2).sum(-1)
        b = 2.0 * (o2 * d2).sum(-1)
        c = (o2 ** 2).sum(-1) - scene['trunk_r'][None] ** 2
        disc = b ** 2 - 4.0 * a * c
        with np.errstate(invalid='ignore', divide='ignore'):
            tc = (-b - np.sqrt(disc)) / (2.0 * a)
        zc = origins[:, None, 2] + tc * dirs[:, None, 2]
        hit = (disc > 0) & (tc > 0) & (zc < scene['trunk_top'][None])
        best = np.minimum(best, np.where(hit, tc, np.inf).min(1))
        oe = (origins[:, None, :] - scene['blob_c'][None]) / scene['blob_axes'][None]
        de = dirs[:, None, :] / scene['blob_axes'][None]
        a = (de ** 2).sum(-1)
        b = 2.0 * (oe * de).sum(-1)
        c = (oe ** 2).sum(-1) - 1.0
        disc = b ** 2 - 4.0 * a * c
        with np.errstate(invalid='ignore'):
            te = (-b - np.sqrt(disc)) / (2.0 * a)
        best = np.minimum(best, np.where((disc > 0) & (te > 0), te, np.inf).min(1))
    best[best > max_range_m] = np.inf
    return best


def scan_scene(scene: dict, pose_at, stamp_s: float, az_step_deg: float = 0.8,
               noise_m: float = 0.02, seed: int = 0, first_azimuth_rad: float = np.pi) -> dict:
    """One clockwise sweep starting at `stamp_s`; pose_at(times (K,)) -> (K, 4, 4).

    Returns sensor-frame points as measured (distorted), their time offsets, and the same hits
    expressed in the sensor frame at the stamp (what a perfect deskew gives).
    """
    n_columns = int(round(360.0 / az_step_deg))
    column = np.arange(n_columns)
    offsets_s = column * SCAN_PERIOD_S / n_columns
    azimuth = first_azimuth_rad - 2.0 * np.pi * column / n_columns  # clockwise from above
    poses = pose_at(stamp_s + offsets_s)
    cos_el = np.cos(ELEVATIONS_RAD)
    dirs_sensor = np.stack([
        np.cos(azimuth)[:, None] * cos_el[None], np.sin(azimuth)[:, None] * cos_el[None],
        np.broadcast_to(np.sin(ELEVATIONS_RAD)[None], (n_columns, 16))], -1)
    dirs_world = np.einsum('kij,klj->kli', poses[:, :3, :3], dirs_sensor).reshape(-1, 3)
    origins = np.repeat(poses[:, :3, 3], 16, axis=0)
    ranges = cast_rays(scene, origins, dirs_world)
    ranges = ranges + np.random.default_rng(seed).normal(0.0, noise_m, ranges.shape)
    ok = np.isfinite(ranges) & (ranges > 0.5)
    points = dirs_sensor.reshape(-1, 3)[ok] * ranges[ok, None]
    hits_world = origins[ok] + ranges[ok, None] * dirs_world[ok]
    T_stamp = pose_at(np.array([stamp_s]))[0]
    truth = (hits_world - T_stamp[:3, 3]) @ T_stamp[:3, :3]
    return {'points': points, 'time': np.repeat(offsets_s, 16)[ok].astype(np.float32),
            'undistorted': truth, 'T_world_sensor': T_stamp, 'stamp_ns': int(round(stamp_s * 1e9))}


def constant_motion(start_xy=(0.0, 0.0), speed_mps: float = 1.0, yaw_rate_rps: float = 0.0):
    """Straight-line speed along the heading plus a constant yaw rate (heading starts at 0).

    Translation is linear in the start frame and yaw linear in time: exactly the motion model
    deskew_points assumes.
    """
    def pose_at(times_s):
        times_s = np.asarray(times_s, dtype=float)
        R = Rotation.from_euler('z', yaw_rate_rps * times_s[:, None]).as_matrix()
        poses = np.tile(np.eye(4), (times_s.size, 1, 1))
        poses[:, :3, :3] = R
        poses[:, 0, 3] = start_xy[0] + speed_mps * times_s
        poses[:, 1, 3] = start_xy[1]
        poses[:, 2, 3] = SENSOR_HEIGHT_M
        return poses
    return pose_at


def weaving_drive(speed_mps: float = 1.0):
    """Along a row with a gentle S-curve: heading follows the path tangent."""
    def pose_at(times_s):
        t = np.asarray(times_s, dtype=float)
        x = speed_mps * t
        y = 0.8 * np.sin(0.3 * t)
        yaw = np.arctan2(0.24 * np.cos(0.3 * t), speed_mps)
        poses = np.tile(np.eye(4), (t.size, 1, 1))
        poses[:, :3, :3] = Rotation.from_euler('z', yaw[:, None]).as_matrix()
        poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = x, y, SENSOR_HEIGHT_M
        return poses
    return pose_at


def static_pose(T: np.ndarray):
    return lambda times_s: np.repeat(T[None], np.size(times_s), axis=0)


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    return transform_magnitude(invert_transform(T_true) @ T_est)


def registration(**overrides) -> ScanRegistration:
    return ScanRegistration.from_config(dataclasses.replace(RegistrationConfig(), **overrides))


# The turn-check tests script ICP's fitness (0.80 from the prediction, 0.90 elsewhere)
# against the recent matches' real fitness within a 1 m correspondence gate.
TURN_CHECK_SCENE = dict(max_correspondence_distance_m=1.0, min_relative_fitness=0.7)


# ---------------------------------------------------------------- fixtures

@pytest.fixture(scope='module')
def orchard() -> dict:
    return make_orchard()


@pytest.fixture(scope='module')
def static_pair(orchard) -> tuple[dict, dict, np.ndarray]:
    """Two undistorted scans and the true T_a_b between them."""
    T_a = make_transform(translation=[0.0, 0.0, SENSOR_HEIGHT_M])
    T_ab = make_transform(Rotation.from_euler('z', 3.0, degrees=True).as_matrix(),
                          [0.25, -0.08, 0.02])
    a = scan_scene(orchard, static_pose(T_a), 0.0, seed=1)
    b = scan_scene(orchard, static_pose(T_a @ T_ab), 0.1, seed=2)
    return a, b, T_ab


@pytest.fixture(scope='module')
def drive(orchard) -> list[dict]:
    """2 s along the row, S-curve, with motion distortion: 21 scans."""
    pose_at = weaving_drive()
    return [scan_scene(orchard, pose_at, k * SCAN_PERIOD_S, seed=k) for k in range(21)]


# ---------------------------------------------------------------- config

def test_default_config_is_valid_and_from_config_builds():
    cfg = RegistrationConfig()
    cfg.validate()
    reg = ScanRegistration.from_config(cfg)
    assert reg.mode == 'default' and reg.estimation == 'point_to_plane'
    assert ScanRegistration.from_config(
        dataclasses.replace(cfg, mode='paper')).estimation == 'point_to_point'


@pytest.mark.parametrize('field, value, message', [
    ('mode', 'fast', 'mode'),
    ('estimation', 'ndt', 'estimation'),
    ('robust_kernel', 'l1', 'robust_kernel'),
    ('voxel_size_m', 0.0, 'voxel_size_m'),
    ('max_correspondence_distance_m', float('nan'), 'max_correspondence_distance_m'),
    ('noise_gate_m', -0.5, 'noise_gate_m'),
    ('max_iterations', 0, 'max_iterations'),
    ('min_fitness', 1.5, 'min_fitness'),
    ('fallback_std_m', 0.001, 'fallback_std'),
    ('max_speed_mps', 0.0, 'max_speed_mps'),
    ('max_yaw_rate_rps', float('inf'), 'max_yaw_rate_rps'),
    ('motion_margin', -0.1, 'motion_margin'),
    ('max_gap_s', 0.05, 'max_gap_s'),
    ('max_consecutive_fallbacks', 0, 'max_consecutive_fallbacks'),
    ('recovery_correspondence_factor', 0.5, 'recovery_correspondence_factor'),
    ('min_relative_fitness', 1.5, 'min_relative_fitness'),
    ('solver', 'ceres', 'solver'),
    ('residual_model', 'volume', 'residual_model'),
    ('residual_model', 'frequency', "needs solver 'gauss_newton'"),
    ('rough_residual', 'along', 'rough_residual'),
    ('rough_weight', -1.0, 'rough_weight'),
    ('smooth_nu', 0.0, 'smooth_nu'),
    ('voxel_priority', 'random', 'voxel_priority'),
    ('turn_continue_min_rad', -0.01, 'turn_continue_min_rad'),
    ('turn_continue_iterations', 0, 'turn_continue_iterations'),
    ('refine_correspondence_distance_m', 1.0, 'must be below max_correspondence_distance_m'),
    ('refine_correspondence_distance_m', -0.4, 'refine_correspondence_distance_m'),
])
def test_invalid_config_names_the_field(field, value, message):
    cfg = dataclasses.replace(RegistrationConfig(), **{field: value})
    with pytest.raises(ConfigError, match=message):
        cfg.validate()
    with pytest.raises(ConfigError):
        ScanRegistration.from_config(cfg)


def test_config_fields_are_ros_parameter_types():
    for f in dataclasses.fields(RegistrationConfig):
        value = getattr(RegistrationConfig(), f.name)
        assert type(value) in (bool, int, float, str), f.name
        assert f.type in ('bool', 'int', 'float', 'str'), f.name


# ---------------------------------------------------------------- known transforms

@pytest.mark.parametrize('mode', ['default', 'paper'])
@pytest.mark.parametrize('estimation', ['point_to_point', 'point_to_plane', 'gicp'])
def test_icp_recovers_a_known_rigid_transform(static_pair, mode, estimation):
    a, _, T_ab = static_pair
    # The same cloud seen from T_ab (plus fresh range noise): pure ICP, no sampling effects.
    moved = transform_points(invert_transform(T_ab), a['points'])
    moved += np.random.default_rng(5).normal(0.0, 0.01, moved.shape)
    reg = registration(mode=mode, estimation=estimation, deskew=False)
    first = reg.register(a['points'], a['stamp_ns'])
    assert first.status == 'first'
    np.testing.assert_allclose(first.T_world_sensor, np.eye(4))
    result = reg.register(moved, b_stamp(a))
    assert result.status == 'ok'
    err_m, err_rad = pose_error(result.T_world_sensor, T_ab)
    assert err_m < 0.01, (err_m, np.rad2deg(err_rad))
    assert err_rad < np.deg2rad(0.1)
    np.testing.assert_allclose(result.T_prev_curr, result.T_world_sensor, atol=1e-12)
    assert result.fitness > 0.8 and 0.0 < result.inlier_rmse_m < 0.25  # nearest map point
    assert result.n_points_used > 500
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0.0)


@pytest.mark.parametrize('estimation', ['point_to_plane', 'gicp'])
def test_scan_to_map_recovers_the_pose_of_a_new_scan(static_pair, estimation):
    a, b, T_ab = static_pair
    reg = registration(estimation=estimation, deskew=False)
    reg.register(a['points'], a['stamp_ns'])
    result = reg.register(b['points'], b['stamp_ns'])
    assert result.status == 'ok'
    err_m, err_rad = pose_error(result.T_world_sensor, T_ab)
    assert err_m < 0.04 and err_rad < np.deg2rad(0.3), (err_m, np.rad2deg(err_rad))


def b_stamp(scan: dict) -> int:
    return scan['stamp_ns'] + 100_000_000


def test_first_scan_is_identity_and_reset_starts_over(static_pair):
    a, b, _ = static_pair
    reg = registration()
    reg.register(a['points'], a['stamp_ns'])
    reg.register(b['points'], b['stamp_ns'])
    assert not np.allclose(reg.T_world_sensor, np.eye(4))
    reg.reset()
    again = reg.register(b['points'], b['stamp_ns'])
    assert again.status == 'first'
    np.testing.assert_allclose(again.T_world_sensor, np.eye(4))


# ---------------------------------------------------------------- chaining over a drive

def _run(reg: ScanRegistration, scans: list[dict], use_time: bool = True):
    T_world0 = invert_transform(scans[0]['T_world_sensor'])
    errors, statuses = [], []
    for scan in scans:
        result = reg.register(scan['points'], scan['stamp_ns'],
                              scan['time'] if use_time else None)
        statuses.append(result.status)
        errors.append(pose_error(result.T_world_sensor, T_world0 @ scan['T_world_sensor']))
    return np.array(errors), statuses


# Paper mode: point-to-point from identity between sparse scans is biased towards "no motion"
# (ground rings move with the sensor and match themselves); it is the baseline, not a target.
@pytest.mark.parametrize('mode, limit_fraction', [('default', 0.04), ('paper', 0.6)])
def test_chaining_a_short_drive_gives_a_small_error(drive, mode, limit_fraction):
    errors, statuses = _run(registration(mode=mode), drive)
    assert statuses[0] == 'first'
    assert statuses.count('ok') >= len(drive) - 2
    path_m = np.linalg.norm(drive[-1]['T_world_sensor'][:3, 3] - drive[0]['T_world_sensor'][:3, 3])
    assert path_m > 1.9
    assert errors[-1, 0] < limit_fraction * path_m, errors[:, 0]


def test_default_mode_beats_paper_mode_on_the_drive(drive):
    default_err, _ = _run(registration(mode='default'), drive)
    paper_err, _ = _run(registration(mode='paper'), drive)
    assert default_err[:, 0].mean() < paper_err[:, 0].mean()


def test_deskew_from_azimuth_tracks_as_well_as_deskew_from_time(drive):
    with_time, _ = _run(registration(deskew=True), drive, use_time=True)
    from_azimuth, _ = _run(registration(deskew=True), drive, use_time=False)
    assert from_azimuth[-1, 0] < 0.08
    assert abs(from_azimuth[-1, 0] - with_time[-1, 0]) < 0.02


# ---------------------------------------------------------------- fallbacks

def _moving_registration(drive, n_scans: int = 4, **overrides) -> ScanRegistration:
    reg = registration(**overrides)
    for scan in drive[:n_scans]:
        assert reg.register(scan['points'], scan['stamp_ns'], scan['time']).status in (
            'first', 'ok')
    return reg


def test_too_few_points_falls_back_to_the_prediction(drive):
    reg = _moving_registration(drive)
    ok_cov = reg.register(drive[4]['points'], drive[4]['stamp_ns'], drive[4]['time']).covariance
    dt_s = (drive[5]['stamp_ns'] - drive[4]['stamp_ns']) * 1e-9
    T_before, delta = reg.T_world_sensor.copy(), reg.predicted_delta(dt_s)
    assert transform_magnitude(delta)[0] > 0.05  # it has a velocity to predict with
    few = drive[5]['points'][:20]
    result = reg.register(few, drive[5]['stamp_ns'], drive[5]['time'][:20])
    assert result.status == 'fallback_too_few_points' and result.fell_back
    np.testing.assert_allclose(result.T_world_sensor, T_before @ delta, atol=1e-9)
    assert np.all(np.diag(result.covariance) > 10.0 * np.diag(ok_cov))
    assert reg.n_fallbacks == 1
    # Processing goes on: the next full scan registers against the untouched map.
    after = reg.register(drive[6]['points'], drive[6]['stamp_ns'], drive[6]['time'])
    assert after.status == 'ok'
    T_world0 = invert_transform(drive[0]['T_world_sensor'])
    assert pose_error(after.T_world_sensor, T_world0 @ drive[6]['T_world_sensor'])[0] < 0.1


def test_a_run_of_fallbacks_while_moving_is_reacquired_from_the_last_trusted_pose(drive):
    """Six unusable scans at 1 m/s: the velocity is dropped after three, so the pose stands
    still while the robot goes on. The next full scan lies 0.7 m from the last trusted pose
    after 0.7 s (plausible), though 0.4 m from the previous, extrapolated one after 0.1 s
    (4 m/s, not): it must be re-acquired, not rejected as implausible."""
    reg = _moving_registration(drive, n_scans=6)
    for scan in drive[6:12]:
        assert reg.register(scan['points'][:20], scan['stamp_ns']).fell_back
    assert reg.recovering
    result = reg.register(drive[12]['points'], drive[12]['stamp_ns'], drive[12]['time'])
    assert result.status == 'recovered'
    T_world0 = invert_transform(drive[0]['T_world_sensor'])
    assert pose_error(result.T_world_sensor, T_world0 @ drive[12]['T_world_sensor'])[0] < 0.1
    after = reg.register(drive[13]['points'], drive[13]['stamp_ns'], drive[13]['time'])
    assert after.status == 'ok'


def headland_turn(x0_m: float, speed_mps: float = 1.8, t_turn_s: float = 1.0,
                  rate_rps: float = 2.0, ramp_s: float = 0.1):
    """Straight along x from (x0, 0), then a turn whose yaw rate ramps to `rate_rps` within
    `ramp_s` (the squared headland corner of the edge drives)."""
    grid = np.linspace(0.0, 4.0, 4001)
    rate = np.clip((grid - t_turn_s) / ramp_s, 0.0, 1.0) * rate_rps
    yaw = np.r_[0.0, np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(grid))]
    x = x0_m + np.r_[0.0, np.cumsum(speed_mps * np.cos(yaw[:-1]) * np.diff(grid))]
    y = np.r_[0.0, np.cumsum(speed_mps * np.sin(yaw[:-1]) * np.diff(grid))]

    def pose_at(times_s):
        t = np.asarray(times_s, dtype=float)
        poses = np.tile(np.eye(4), (t.size, 1, 1))
        poses[:, :3, :3] = Rotation.from_euler('z', np.interp(t, grid, yaw)[:, None]).as_matrix()
        poses[:, 0, 3], poses[:, 1, 3] = np.interp(t, grid, x), np.interp(t, grid, y)
        poses[:, 2, 3] = SENSOR_HEIGHT_M
        return poses
    return pose_at


@pytest.fixture(scope='module')
def open_ground_turn(orchard) -> list[dict]:
    """1.8 m/s, 14 m past the row ends, then 2 rad/s within 0.1 s: 20 scans."""
    return [scan_scene(orchard, headland_turn(34.0), k * SCAN_PERIOD_S, seed=k)
            for k in range(20)]


def _yaw_errors(scans: list[dict], **overrides) -> list[float]:
    """Each scan's heading error [rad] through a registration with `overrides`."""
    reg = registration(**overrides)
    T_world0 = invert_transform(scans[0]['T_world_sensor'])
    return [pose_error(reg.register(scan['points'], scan['stamp_ns']).T_world_sensor,
                       T_world0 @ scan['T_world_sensor'])[1] for scan in scans]


@pytest.mark.parametrize('yaw_guesses, deskew, gate_m, tracked', [
    (2, False, 1.0, True), (0, False, 1.0, False), (0, True, 1.0, True), (2, True, 1.0, True),
    (0, True, 0.4, False), (2, True, 0.4, True)])
def test_a_sharp_turn_in_open_ground_is_tracked_with_turn_guesses(open_ground_turn, yaw_guesses,
                                                                  deskew, gate_m, tracked):
    """From a prediction without the turn, ICP fits the ground at any yaw and slides; the row
    ends that fix the yaw lie outside its gate. Re-acquisition's turned guesses find the turn;
    without them, and without deskew, the heading is lost (1.6 rad after 1 s here). Deskewed
    (azimuth times), this turn is tracked even without them within a 1 m correspondence gate,
    not within 0.4 m (a smaller basin: the turned guesses are needed)."""
    # Each gate with the relative fitness that keeps this turn (session 36).
    yaw_errors = _yaw_errors(open_ground_turn, recovery_yaw_guesses=yaw_guesses, deskew=deskew,
                             max_correspondence_distance_m=gate_m,
                             min_relative_fitness={1.0: 0.7, 0.4: 0.5}[gate_m])
    assert max(yaw_errors[:10]) < 0.02  # straight: no trouble either way
    if tracked:
        assert max(yaw_errors) < 0.1, np.round(yaw_errors, 3)
    else:
        assert yaw_errors[-1] > 0.5, np.round(yaw_errors, 3)


@pytest.mark.parametrize('min_relative_fitness, tracked', [(0.7, False), (0.5, True)])
def test_within_a_narrow_gate_the_open_ground_turn_needs_a_lower_relative_fitness(
        open_ground_turn, min_relative_fitness, tracked):
    """ICP pairing within 0.4 m: while turning into unseen ground even the true pose has
    few points that close to the map (~0.57 x the recent matches' fitness), so at 0.7 x the
    trust policy refuses the turn and the heading is lost."""
    yaw_errors = _yaw_errors(open_ground_turn, max_correspondence_distance_m=0.4,
                             min_relative_fitness=min_relative_fitness)
    if tracked:
        assert max(yaw_errors) < 0.1, np.round(yaw_errors, 3)
    else:
        assert yaw_errors[-1] > 0.3, np.round(yaw_errors, 3)


def test_a_refine_within_a_narrow_gate_keeps_the_wide_gates_trust(open_ground_turn, static_pair):
    """`refine_correspondence_distance_m`: the match at 1 m is refined at 0.4 m from where it
    ended, and trusted by the 1 m match's fitness: the open-ground turn a 0.4 m gate loses at
    min_relative_fitness 0.7 is kept; the pose is the refined one."""
    yaw_errors = _yaw_errors(open_ground_turn, refine_correspondence_distance_m=0.4)
    assert max(yaw_errors) < 0.1, np.round(yaw_errors, 3)
    a, b, _ = static_pair
    results = {}
    for refine_m in (0.0, 0.4):
        reg = registration(refine_correspondence_distance_m=refine_m)
        reg.register(a['points'], a['stamp_ns'])
        results[refine_m] = reg.register(b['points'], b['stamp_ns'])
    # Fitness and noise are the 1 m match's (the covariance is not cut short by 0.4 m).
    assert results[0.4].fitness == results[0.0].fitness
    assert results[0.4].inlier_rmse_m == results[0.0].inlier_rmse_m
    assert not np.array_equal(results[0.4].T_world_sensor, results[0.0].T_world_sensor)


def test_the_noise_gate_measures_a_matchs_rmse_without_moving_it(static_pair):
    """At the correspondence gate it is ICP's own RMSE (of the points with a map point that
    close); wider, further points count too and the covariance grows; the pose and the
    fitness are ICP's either way."""
    a, b, _ = static_pair
    results = {}
    for noise_gate_m in (0.0, 0.4, 1.0):
        reg = registration(max_correspondence_distance_m=0.4, noise_gate_m=noise_gate_m)
        reg.register(a['points'], a['stamp_ns'])
        results[noise_gate_m] = reg.register(b['points'], b['stamp_ns'])
    assert results[0.4].inlier_rmse_m == pytest.approx(results[0.0].inlier_rmse_m, rel=1e-2)
    assert results[1.0].inlier_rmse_m > 1.05 * results[0.0].inlier_rmse_m
    assert results[1.0].covariance[0, 0] > results[0.0].covariance[0, 0]
    for result in results.values():
        assert result.status == 'ok'
        assert result.fitness == results[0.0].fitness
        np.testing.assert_allclose(result.T_world_sensor, results[0.0].T_world_sensor,
                                   atol=1e-9)


def test_empty_and_non_finite_points_do_not_raise(drive):
    reg = _moving_registration(drive)
    empty = reg.register(np.zeros((0, 3)), drive[4]['stamp_ns'])
    assert empty.status == 'fallback_too_few_points'
    noisy = drive[5]['points'].copy()
    noisy[::7] = np.nan
    noisy[1::7, 0] = np.inf
    result = reg.register(noisy, drive[5]['stamp_ns'], drive[5]['time'])
    assert result.status == 'ok'
    assert np.all(np.isfinite(result.T_world_sensor))


def test_a_jump_far_from_the_prediction_is_flagged_diverged(static_pair):
    a, b, T_ab = static_pair
    # b is 0.26 m away while the robot was standing still: more than a 0.1 m allowance.
    reg = registration(max_translation_jump_m=0.1, retry_failed_match=False)
    reg.register(a['points'], a['stamp_ns'])
    result = reg.register(b['points'], b['stamp_ns'])
    assert result.status == 'fallback_diverged'
    np.testing.assert_allclose(result.T_world_sensor, np.eye(4), atol=1e-12)
    assert result.covariance[0, 0] == pytest.approx(RegistrationConfig().fallback_std_m ** 2)
    # The same pair with the default allowance is accepted.
    reg = registration()
    reg.register(a['points'], a['stamp_ns'])
    assert reg.register(b['points'], b['stamp_ns']).status == 'ok'


def test_a_scan_of_another_place_is_flagged_low_fitness(static_pair, drive):
    a, _, _ = static_pair
    reg = registration()
    reg.register(a['points'], a['stamp_ns'])
    elsewhere = make_orchard(seed=7, tree_spacing_m=7.0, row_spacing_m=9.0)
    far = scan_scene(elsewhere, static_pose(make_transform(translation=[0, 0, 3.0])), 0.1)
    result = reg.register(far['points'] + [0.0, 0.0, 2.5], far['stamp_ns'])
    assert result.status in ('fallback_low_fitness', 'fallback_diverged')
    assert result.fitness < RegistrationConfig().min_fitness or result.status.endswith('diverged')
    np.testing.assert_allclose(result.T_world_sensor, np.eye(4), atol=1e-12)


@pytest.mark.parametrize('points, offsets, message', [
    (np.zeros((10, 2)), None, r'shape \(N, 3\)'),
    (np.zeros(30), None, r'shape \(N, 3\)'),
    (np.zeros((10, 3)), np.zeros(9), 'time_offset_s has 9 values for 10 points'),
])
def test_malformed_input_raises_registration_error(points, offsets, message):
    with pytest.raises(RegistrationError, match=message):
        registration().register(points, 0, offsets)


# ---------------------------------------------------------------- deskew

@pytest.fixture(scope='module')
def fast_scan(orchard) -> tuple[dict, np.ndarray]:
    """A sweep at 2 m/s and 0.8 rad/s (the Jackal's limits) and its true per-scan delta."""
    pose_at = constant_motion(speed_mps=2.0, yaw_rate_rps=0.8)
    scan = scan_scene(orchard, pose_at, 0.0, noise_m=0.0)
    T0, T1 = pose_at(np.array([0.0, SCAN_PERIOD_S]))
    return scan, invert_transform(T0) @ T1


def test_deskew_with_the_time_field_undoes_a_known_distortion(fast_scan):
    scan, delta = fast_scan
    before = np.linalg.norm(scan['points'] - scan['undistorted'], axis=1)
    fixed = deskew_points(scan['points'], scan['time'], delta, SCAN_PERIOD_S)
    after = np.linalg.norm(fixed - scan['undistorted'], axis=1)
    assert before.max() > 0.15
    assert after.max() < 1e-3, after.max()


def test_deskew_from_the_azimuth_undoes_a_known_distortion(fast_scan):
    scan, delta = fast_scan
    offsets = azimuth_time_offsets(scan['points'], SCAN_PERIOD_S)
    np.testing.assert_allclose(offsets, scan['time'], atol=1e-6)
    fixed = deskew_points(scan['points'], offsets, delta, SCAN_PERIOD_S)
    assert np.linalg.norm(fixed - scan['undistorted'], axis=1).max() < 1e-3


def test_azimuth_offsets_follow_clockwise_spin_and_stamp_choice():
    azimuth = np.deg2rad([10.0, 0.0, -90.0, -170.0, 100.0, 20.0, 12.0])  # clockwise, wraps
    points = np.c_[np.cos(azimuth), np.sin(azimuth), np.zeros(azimuth.size)]
    offsets = azimuth_time_offsets(points, 0.1)
    expected = np.array([0.0, 10.0, 100.0, 180.0, 270.0, 350.0, 358.0]) / 360.0 * 0.1
    np.testing.assert_allclose(offsets, expected, atol=1e-12)
    assert np.all(np.diff(offsets) > 0.0)
    np.testing.assert_allclose(azimuth_time_offsets(points, 0.1, stamp_at_sweep_end=True),
                               expected - 0.1, atol=1e-12)
    # Past a full turn (the driver cuts on packet boundaries): the last points stay late.
    over = np.r_[points, [[np.cos(np.deg2rad(8.0)), np.sin(np.deg2rad(8.0)), 0.0]]]
    assert azimuth_time_offsets(over, 0.1)[-1] == pytest.approx(0.1 * 362.0 / 360.0)


def test_deskew_turns_each_point_by_its_share_of_a_3d_twist():
    """The vectorised Rodrigues form agrees with each point's own rotation matrix, for a twist
    with roll and pitch as well as yaw (a robot on a slope)."""
    rng = np.random.default_rng(3)
    points = rng.normal(0.0, 10.0, (500, 3))
    offsets_s = rng.uniform(-SCAN_PERIOD_S, 0.0, 500)
    omega_rps, velocity_mps = np.array([0.3, -0.2, 1.1]), np.array([1.5, 0.1, -0.05])
    delta = make_transform(Rotation.from_rotvec(omega_rps * SCAN_PERIOD_S).as_matrix(),
                           velocity_mps * SCAN_PERIOD_S)
    expected = (Rotation.from_rotvec(offsets_s[:, None] * omega_rps).apply(points)
                + offsets_s[:, None] * velocity_mps)
    np.testing.assert_allclose(deskew_points(points, offsets_s, delta, SCAN_PERIOD_S),
                               expected, atol=1e-9)


def test_deskew_without_motion_is_the_identity(fast_scan):
    scan, _ = fast_scan
    out = deskew_points(scan['points'], scan['time'], np.eye(4), SCAN_PERIOD_S)
    np.testing.assert_array_equal(out, scan['points'])


def start_moving(speed_mps: float = 1.5, yaw_rate_rps: float = 1.0, start_s: float = 0.25):
    """Standing still, then driving and turning hard: the map holds undistorted scans."""
    def pose_at(times_s):
        moving_s = np.clip(np.asarray(times_s, dtype=float) - start_s, 0.0, None)
        poses = np.tile(np.eye(4), (moving_s.size, 1, 1))
        poses[:, :3, :3] = Rotation.from_euler('z', yaw_rate_rps * moving_s[:, None]).as_matrix()
        poses[:, 0, 3], poses[:, 2, 3] = speed_mps * moving_s, SENSOR_HEIGHT_M
        return poses
    return pose_at


def test_deskew_makes_registration_after_a_start_more_accurate(orchard):
    pose_at = start_moving()
    scans = [scan_scene(orchard, pose_at, k * SCAN_PERIOD_S, seed=k) for k in range(10)]
    on, _ = _run(registration(deskew=True), scans)
    off, _ = _run(registration(deskew=False), scans)
    assert on[-1, 0] < 0.6 * off[-1, 0], (on[-1], off[-1])
    assert on[-1, 1] < off[-1, 1]


def test_deskewed_points_are_returned_on_request(drive):
    reg = registration(deskew=True, output_deskewed_points=True)
    results = [reg.register(s['points'], s['stamp_ns'], s['time']) for s in drive[:4]]
    last, scan = results[-1], drive[3]
    assert last.status == 'ok' and last.deskewed_points.shape == scan['points'].shape
    # Closer to the truth than the raw sweep (the robot moved ~0.1 m during it).
    err_raw = np.linalg.norm(scan['points'] - scan['undistorted'], axis=1).mean()
    err_fixed = np.linalg.norm(last.deskewed_points - scan['undistorted'], axis=1).mean()
    assert err_fixed < 0.5 * err_raw
    assert registration().register(scan['points'], 0).deskewed_points is None


# ---------------------------------------------------------------- degenerate geometry

def test_ground_plane_only_does_not_crash_and_reports_degeneracy():
    flat = make_orchard(with_trees=False)
    pose_at = constant_motion(speed_mps=1.0)
    reg = registration()
    results = [reg.register(s['points'], s['stamp_ns'], s['time'])
               for s in (scan_scene(flat, pose_at, k * SCAN_PERIOD_S, seed=k) for k in range(5))]
    assert results[0].status == 'first'
    for result in results[1:]:
        assert result.status in ('ok', 'fallback_low_fitness', 'fallback_diverged')
        assert np.all(np.isfinite(result.T_world_sensor))
        assert np.all(np.isfinite(result.covariance))
        # Sliding along the ground is unobservable: x/y/yaw much less certain than z/roll/pitch.
        var = np.diag(result.covariance)
        assert min(var[0], var[1], var[5]) > 10.0 * max(var[2], var[3], var[4])


# ---------------------------------------------------------------- helpers

def test_voxel_downsample_keeps_one_point_per_voxel_in_input_order():
    rng = np.random.default_rng(3)
    points = rng.uniform(-5.0, 5.0, (5000, 3))
    keep = voxel_downsample_indices(points, 1.0)
    assert np.all(np.diff(keep) > 0)
    cells = np.floor(points[keep] / 1.0)
    assert len(np.unique(cells, axis=0)) == len(keep) == len(np.unique(np.floor(points), axis=0))
    # Each voxel keeps its first point in input order.
    _, first = np.unique(np.floor(points), axis=0, return_index=True)
    np.testing.assert_array_equal(keep, np.sort(first))


def test_scale_delta_doubles_a_constant_twist():
    T = make_transform(Rotation.from_euler('z', 0.1).as_matrix(), [0.2, 0.0, 0.0])
    T2 = scale_delta(T, 2.0)
    assert transform_magnitude(T2)[1] == pytest.approx(0.2)
    np.testing.assert_allclose(T2[:3, 3], [0.4, 0.0, 0.0])
    np.testing.assert_allclose(scale_delta(T, 0.0), np.eye(4), atol=1e-15)


def test_motion_beyond_the_physical_bounds_is_implausible_and_stays_out_of_the_map(static_pair):
    a, b, T_ab = static_pair
    # b is 0.26 m from a, 0.1 s later: 2.6 m/s, within 2.0 m/s x 1.5 but not 1.0 m/s x 1.5.
    reg = registration(max_speed_mps=1.0)
    reg.register(a['points'], a['stamp_ns'])
    map_before = reg.local_map.points_xyz.copy()
    result = reg.register(b['points'], b['stamp_ns'])
    assert result.status == 'fallback_implausible' and result.fell_back
    np.testing.assert_allclose(result.T_world_sensor, np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(reg.local_map.points_xyz, map_before)
    np.testing.assert_array_equal(reg.velocity, np.zeros(6))
    default = registration()
    assert default.is_plausible(T_ab, 0.1) and not default.is_plausible(T_ab, 0.01)


@pytest.mark.parametrize('from_refused', [False, True])
def test_a_match_refused_for_the_bounds_is_remembered_only_with_plausible_from_refused(
        static_pair, from_refused):
    a, b, T_ab = static_pair
    reg = registration(max_speed_mps=1.0, plausible_from_refused=from_refused)
    reg.register(a['points'], a['stamp_ns'])
    assert reg.register(b['points'], b['stamp_ns']).status == 'fallback_implausible'
    if not from_refused:
        assert reg.motion.refused_match is None
        return
    T_refused, stamp_ns = reg.motion.refused_match
    assert stamp_ns == b['stamp_ns']
    # The match's pose, not the prediction the scan fell back to.
    np.testing.assert_allclose(T_refused[:3, 3], T_ab[:3, 3], atol=0.05)


def test_prediction_is_per_second_and_capped_by_the_bounds():
    reg = registration()
    capped = reg.capped(np.array([0.0, 0.0, 10.0, 3.0, 4.0, 0.0]))
    np.testing.assert_allclose(capped, [0.0, 0.0, 4.0, 1.2, 1.6, 0.0])
    reg.velocity = np.array([0.0, 0.0, 0.5, 1.0, 0.0, 0.0])
    distance_m, angle_rad = transform_magnitude(reg.predicted_delta(0.05))
    assert distance_m == pytest.approx(0.05) and angle_rad == pytest.approx(0.025)
    np.testing.assert_array_equal(reg.predicted_delta(-0.1), np.eye(4))


def test_advance_with_prediction_is_a_counted_fallback(drive):
    reg = _moving_registration(drive)
    dt_s = (drive[4]['stamp_ns'] - drive[3]['stamp_ns']) * 1e-9
    expected = reg.T_world_sensor @ reg.predicted_delta(dt_s)
    result = reg.advance_with_prediction(drive[4]['stamp_ns'])
    assert result.status == 'fallback_degenerate' and reg.n_fallbacks == 1
    np.testing.assert_allclose(result.T_world_sensor, expected, atol=1e-12)
    with pytest.raises(RegistrationError, match='fallback status'):
        reg.advance_with_prediction(drive[5]['stamp_ns'], 'ok')


def test_every_status_is_listed():
    from gft_odom.core.registration import STATUSES, TRUSTED_STATUSES
    assert set(TRUSTED_STATUSES) < set(STATUSES)
    assert {'fallback_degenerate', 'fallback_implausible', 'recovered'} <= set(STATUSES)


def test_farthest_eviction_keeps_a_revisited_place_mapped():
    from gft_odom.core.local_map import LocalMap

    def keyframe_at(x):
        T = np.eye(4)
        T[0, 3] = x
        return np.array([[x, 5.0, 0.0], [x, -5.0, 0.0], [x, 5.0, 2.0]]), T

    maps = {e: LocalMap(0.1, 100.0, 10_000, 3, 1.0, 0.2, 5, with_normals=False, eviction=e)
            for e in ('oldest', 'farthest')}
    # Out along x and back again: 0, 10, 20, then 1 (next to where it started).
    for x in (0.0, 10.0, 20.0, 1.0):
        for local_map in maps.values():
            local_map.add_keyframe(*keyframe_at(x))
    xs = {e: sorted(set(np.round(m.points_xyz[:, 0]))) for e, m in maps.items()}
    assert xs['oldest'] == [1.0, 10.0, 20.0]  # the start is gone
    assert xs['farthest'] == [0.0, 1.0, 10.0]  # the far end is gone, the start stays
    with pytest.raises(ValueError, match='eviction'):
        LocalMap(0.1, 100.0, 10, 3, 1.0, 0.2, 5, eviction='random')
    with pytest.raises(ConfigError, match='map_keyframe_eviction'):
        RegistrationConfig(map_keyframe_eviction='random').validate()


def test_a_voxel_keeps_the_newest_or_the_oldest_keyframes_point():
    from gft_odom.core.local_map import LocalMap
    maps = {k: LocalMap(1.0, 100.0, 10_000, 5, 0.1, 0.2, 5, with_normals=False, voxel_keeps=k)
            for k in ('newest', 'oldest')}
    # Two keyframes see the same voxel, 0.2 m apart (a drifted second view).
    for x in (0.3, 0.5):
        for local_map in maps.values():
            T = np.eye(4)
            T[0, 3] = x
            local_map.add_keyframe(np.array([[x, 0.5, 0.5]]), T)
    assert maps['newest'].points_xyz[:, 0].tolist() == [0.5]
    assert maps['oldest'].points_xyz[:, 0].tolist() == [0.3]
    with pytest.raises(ValueError, match='voxel_keeps'):
        LocalMap(1.0, 100.0, 10, 3, 1.0, 0.2, 5, voxel_keeps='random')
    with pytest.raises(ConfigError, match='map_voxel_keeps'):
        RegistrationConfig(map_voxel_keeps='random').validate()


def test_a_voxel_keeps_the_mean_of_its_views_when_asked():
    """'mean': the centroid of every keyframe's point in the voxel; 'mean_rough': the
    oldest point where the voxel is smooth on average (ground, trunks), the mean elsewhere."""
    from gft_odom.core.local_map import LocalMap
    maps = {k: LocalMap(1.0, 100.0, 10_000, 5, 0.1, 0.2, 5, with_normals=False, voxel_keeps=k,
                        anchor_smoothness=0.75) for k in ('mean', 'mean_rough')}
    # Two voxels seen by two keyframes: a smooth one (0.9, 1.0) and a rough one (0.1, 0.3).
    for x, smooth in ((0.3, (0.9, 0.1)), (0.5, (1.0, 0.3))):
        T = np.eye(4)
        T[0, 3] = x
        for local_map in maps.values():
            local_map.add_keyframe(np.array([[x, 0.5, 0.5], [x, 5.5, 0.5]]), T,
                                   np.array(smooth))
    for kind, local_map in maps.items():
        at = np.argsort(local_map.points_xyz[:, 1])
        smooth_x, rough_x = local_map.points_xyz[at, 0]
        assert rough_x == pytest.approx(0.4)
        assert smooth_x == pytest.approx(0.4 if kind == 'mean' else 0.3)
        assert local_map.smoothness[at] == pytest.approx([0.95, 0.2])
        assert local_map.viewpoints[at][:, 0] == pytest.approx(
            [0.4 if kind == 'mean' else 0.3, 0.4])
    # Without frequencies every voxel is the mean of its views.
    plain = LocalMap(1.0, 100.0, 10_000, 5, 0.1, 0.2, 5, with_normals=False,
                     voxel_keeps='mean_rough', anchor_smoothness=0.75)
    for x in (0.3, 0.5):
        T = np.eye(4)
        T[0, 3] = x
        plain.add_keyframe(np.array([[x, 0.5, 0.5]]), T)
    assert plain.points_xyz[:, 0] == pytest.approx([0.4])
    assert plain.smoothness is None


def test_voxel_means_leave_unknown_values_out():
    from gft_odom.core.local_map import voxel_means
    points = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [2.5, 0.0, 0.0]])
    centroids, values, first = voxel_means(points, 1.0, np.array([np.nan, 2.0, np.nan]))
    assert centroids == pytest.approx(np.array([[0.2, 0.1, 0.1], [2.5, 0.0, 0.0]]))
    assert values[0] == 2.0 and np.isnan(values[1])
    assert first.tolist() == [0, 2]


def test_map_points_from_the_scan_are_denser_than_the_registrations(static_pair):
    a, _, _ = static_pair
    sizes = {}
    for source in ('registration', 'scan'):
        reg = registration(map_points_from=source, voxel_size_m=0.6, map_voxel_size_m=0.2)
        reg.register(a['points'], a['stamp_ns'])
        sizes[source] = len(reg.local_map)
    assert sizes['scan'] > 1.5 * sizes['registration']
    with pytest.raises(ConfigError, match='map_points_from'):
        RegistrationConfig(map_points_from='everything').validate()


def test_a_failed_match_is_retried_from_other_guesses_when_asked(static_pair):
    """ICP from the prediction fails (forced here: on the robot it slid 0.45 m along a row at
    a pivot's start); the retry, from its own guesses, finds the true pose."""
    a, b, T_ab = static_pair
    results = {}
    for retry in (False, True):
        reg = registration(retry_failed_match=retry)
        reg.register(a['points'], a['stamp_ns'])
        reg._match = lambda source_xyz, T_pred, stamp_ns: (
            'fallback_implausible', T_pred, 0.0, 0.0, None)
        results[retry] = reg.register(b['points'], b['stamp_ns'])
    assert results[False].status == 'fallback_implausible'
    assert results[True].status == 'recovered'
    error_m, error_rad = pose_error(results[True].T_world_sensor, T_ab)
    assert error_m < 0.05 and error_rad < 0.01
    # The velocity is the motion the retry found (0.26 m in 0.1 s, capped at 2 m/s).
    heading = reg.velocity[3:] / np.linalg.norm(reg.velocity[3:])
    assert np.linalg.norm(reg.velocity[3:]) == pytest.approx(2.0)
    assert heading @ (T_ab[:3, 3] / np.linalg.norm(T_ab[:3, 3])) > 0.99


def test_a_retry_passes_the_checks_a_match_does(static_pair):
    """b is 0.26 m from a standing prediction; with a 0.1 m jump bound neither the match
    nor its retry may take it."""
    a, b, _ = static_pair
    reg = registration(max_translation_jump_m=0.1, retry_failed_match=True)
    reg.register(a['points'], a['stamp_ns'])
    assert reg.register(b['points'], b['stamp_ns']).status == 'fallback_diverged'


# ---------------------------------------------------------------- Gauss-Newton, frequency-aware

GAUSS_NEWTON = dict(solver='gauss_newton', convergence_m=5e-4)


@pytest.mark.parametrize('model', ['plane', 'frequency', 'planarity'])
def test_gauss_newton_tracks_the_drive_like_open3d(drive, model):
    errors, statuses = _run(registration(residual_model=model, **GAUSS_NEWTON), drive)
    reference, _ = _run(registration(), drive)
    assert statuses.count('ok') >= len(drive) - 2
    assert errors[-1, 0] < max(2.0 * reference[-1, 0], 0.05), (errors[-1], reference[-1])


def test_the_frequency_steers_the_gauss_newton_registration(static_pair):
    """Same scans, same registration: smoothness from nu changes the estimate and its
    information (with nu = NaN everywhere, every pair is rough: no plane row at all)."""
    a, b, _ = static_pair
    results = {}
    for name, nu in (('none', None), ('smooth', np.full(len(b['points']), 0.5)),
                     ('rough', np.full(len(b['points']), np.nan))):
        reg = registration(residual_model='frequency', **GAUSS_NEWTON)
        reg.register(a['points'], a['stamp_ns'])
        results[name] = reg.register(b['points'], b['stamp_ns'], nu=nu)
    # All smooth (s = 1) is exactly the plane model, i.e. no frequency.
    np.testing.assert_allclose(results['smooth'].T_world_sensor,
                               results['none'].T_world_sensor, atol=1e-12)
    assert not np.allclose(results['rough'].information, results['none'].information)
    assert results['rough'].status == 'ok'


def test_nu_must_match_the_points():
    reg = registration(residual_model='frequency', **GAUSS_NEWTON)
    with pytest.raises(RegistrationError, match='nu has 2 values'):
        reg.register(np.zeros((3, 3)), 0, nu=np.zeros(2))


def test_a_voxel_keeps_its_smoothest_point_when_asked():
    points = np.array([[0.1, 0.0, 0.0], [0.2, 0.0, 0.0], [1.1, 0.0, 0.0], [0.15, 0.0, 0.0]])
    np.testing.assert_array_equal(voxel_downsample_indices(points, 1.0), [0, 2])
    nu = np.array([0.1, np.nan, 0.3, 0.5])  # NaN (no spectrum) never wins over a value
    np.testing.assert_array_equal(voxel_downsample_indices(points, 1.0, nu), [2, 3])
    np.testing.assert_array_equal(
        voxel_downsample_indices(points, 1.0, np.full(4, np.nan)), [0, 2])


def test_smoothest_voxel_priority_changes_which_points_register(static_pair):
    a, b, _ = static_pair
    rng = np.random.default_rng(0)
    nu = rng.uniform(0.0, 0.5, len(b['points']))
    used = {}
    for priority in ('first', 'smoothest'):
        reg = registration(voxel_priority=priority)
        reg.register(a['points'], a['stamp_ns'])
        result = reg.register(b['points'], b['stamp_ns'], nu=nu)
        assert result.status == 'ok'
        used[priority] = result.T_world_sensor
    assert not np.allclose(used['first'], used['smoothest'], atol=1e-9)


def test_rough_source_points_are_thinned_and_smooth_ones_kept():
    # Four rough points (nu 0: canopy) in one 1 m voxel, two smooth ones (nu 0.4) beside them,
    # one point without a spectrum (counted rough) in its own voxel.
    points = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [0.5, 0.1, 0.1], [0.7, 0.1, 0.1],
                       [0.2, 0.4, 0.1], [0.6, 0.4, 0.1], [5.1, 0.1, 0.1]])
    nu = np.array([0.0, 0.0, 0.0, 0.0, 0.4, 0.4, np.nan])
    keep = np.arange(7)
    cfg = RegistrationConfig(rough_voxel_size_m=1.0)
    np.testing.assert_array_equal(thinned_rough(points, keep, nu, cfg), [0, 4, 5, 6])
    # Only the kept indices are read: a subset stays a subset.
    np.testing.assert_array_equal(thinned_rough(points, keep[2:], nu, cfg), [2, 4, 5, 6])


def test_thinned_rough_source_changes_the_match_only_with_frequencies(static_pair):
    a, b, _ = static_pair
    nu = np.random.default_rng(0).uniform(0.0, 0.5, len(b['points']))
    poses, used = {}, {}
    for size, with_nu in ((0.0, True), (1.2, True), (1.2, False)):
        reg = registration(rough_voxel_size_m=size)
        reg.register(a['points'], a['stamp_ns'])
        result = reg.register(b['points'], b['stamp_ns'], nu=nu if with_nu else None)
        assert result.status == 'ok'
        poses[size, with_nu], used[size, with_nu] = result.T_world_sensor, result.n_points_used
    assert used[1.2, True] < used[0.0, True] == used[1.2, False]
    assert not np.allclose(poses[0.0, True], poses[1.2, True], atol=1e-9)
    np.testing.assert_allclose(poses[1.2, False], poses[0.0, True], atol=1e-9)


def test_a_shifted_source_grid_keeps_other_points_and_still_matches(static_pair):
    a, b, _ = static_pair
    poses, used = {}, {}
    for offset in (0.0, 0.2):
        reg = registration(voxel_grid_offset_m=offset)
        reg.register(a['points'], a['stamp_ns'])
        result = reg.register(b['points'], b['stamp_ns'])
        assert result.status == 'ok'
        poses[offset], used[offset] = result.T_world_sensor, result.n_points_used
    assert used[0.0] != used[0.2] or not np.allclose(poses[0.0], poses[0.2], atol=1e-9)
    np.testing.assert_allclose(poses[0.2][:3, 3], poses[0.0][:3, 3], atol=0.02)
    with pytest.raises(ConfigError, match='voxel_grid_offset_m'):
        RegistrationConfig(voxel_grid_offset_m=0.4).validate()


def test_a_voxel_keeps_the_point_seen_from_closest_when_asked():
    from gft_odom.core.local_map import LocalMap
    local_map = LocalMap(1.0, 100.0, 10_000, 5, 0.1, 0.2, 5, with_normals=False,
                         voxel_keeps='nearest')
    # The same voxel seen from 5 m, then from 1 m, then from 3 m: the 1 m view stays.
    for sensor_x, point_x in ((-5.0, 0.2), (-1.0, 0.5), (-3.0, 0.8)):
        T = np.eye(4)
        T[0, 3] = sensor_x
        local_map.add_keyframe(np.array([[point_x, 0.5, 0.5]]), T)
    assert local_map.points_xyz[:, 0].tolist() == [0.5]


def test_the_map_remembers_each_points_smoothness():
    from gft_odom.core.local_map import LocalMap
    local_map = LocalMap(1.0, 100.0, 10_000, 5, 0.1, 0.2, 5, with_normals=False)
    T = np.eye(4)
    local_map.add_keyframe(np.array([[0.5, 0.5, 0.5], [5.5, 0.5, 0.5], [0.6, 0.5, 0.5]]), T,
                           np.array([0.2, 0.9, 0.7]))
    T[0, 3] = 0.5
    local_map.add_keyframe(np.array([[9.5, 0.5, 0.5]]), T)  # no smoothness: unknown
    by_x = dict(zip(local_map.points_xyz[:, 0].round(1), local_map.smoothness))
    assert set(by_x) == {0.5, 5.5, 9.5}  # 0.6 shared 0.5's voxel
    assert by_x[0.5] == 0.2 and by_x[5.5] == 0.9 and np.isnan(by_x[9.5])
    np.testing.assert_array_equal(local_map.target().point_smoothness, local_map.smoothness)


def test_frequency_affinity_needs_the_gauss_newton_solver():
    with pytest.raises(ConfigError, match='frequency_affinity_m'):
        RegistrationConfig(frequency_affinity_m=0.5).validate()
    with pytest.raises(ConfigError, match='frequency_affinity_m'):
        RegistrationConfig(solver='gauss_newton', frequency_affinity_m=-1.0).validate()
    RegistrationConfig(solver='gauss_newton', frequency_affinity_m=0.5).validate()


def test_anchors_keep_the_smooth_points_of_a_keyframe_leaving_the_window():
    from gft_odom.core.local_map import LocalMap

    def at(x):
        T = np.eye(4)
        T[0, 3] = x
        # A smooth point (ground, trunk) and a rough one (canopy) per keyframe.
        return np.array([[x, 2.0, 0.0], [x, -2.0, 2.0]]), T, np.array([0.9, 0.1])

    maps = {a: LocalMap(0.1, 100.0, 10_000, 2, 1.0, 0.2, 5, with_normals=False,
                        anchor_smoothness=a) for a in (None, 0.75)}
    for x in (0.0, 10.0, 20.0):
        for local_map in maps.values():
            local_map.add_keyframe(*at(x))
    plain = {tuple(p) for p in maps[None].points_xyz.round(1)}
    anchored = {tuple(p) for p in maps[0.75].points_xyz.round(1)}
    assert (0.0, 2.0, 0.0) not in plain  # the first keyframe left the window
    assert anchored - plain == {(0.0, 2.0, 0.0)}  # its smooth point stays, its canopy not
    assert maps[0.75].n_anchors == 1
    # A keyframe without frequencies anchors nothing; clear() forgets the anchors.
    bare = LocalMap(0.1, 100.0, 10_000, 1, 1.0, 0.2, 5, with_normals=False,
                    anchor_smoothness=0.75)
    for x in (0.0, 10.0):
        points, T, _ = at(x)
        bare.add_keyframe(points, T)
    assert bare.n_anchors == 0
    maps[0.75].clear()
    assert maps[0.75].n_anchors == 0 and len(maps[0.75]) == 0


def test_anchors_drop_out_of_range_and_yield_a_voxel_to_nothing():
    from gft_odom.core.local_map import LocalMap
    local_map = LocalMap(1.0, 15.0, 10_000, 1, 1.0, 0.2, 5, with_normals=False,
                         anchor_smoothness=0.5)
    T = np.eye(4)
    local_map.add_keyframe(np.array([[0.2, 0.5, 0.5]]), T, np.array([1.0]))
    T2 = T.copy()
    T2[0, 3] = 0.5
    local_map.add_keyframe(np.array([[0.7, 0.5, 0.5]]), T2, np.array([1.0]))
    # The anchor (0.2) is older than the window's point in the same voxel: it stays.
    assert local_map.points_xyz[:, 0].tolist() == [0.2]
    T3 = T.copy()
    T3[0, 3] = 30.0
    local_map.add_keyframe(np.array([[30.2, 0.5, 0.5]]), T3, np.array([1.0]))
    assert local_map.points_xyz[:, 0].tolist() == [30.2]  # anchors beyond 15 m not served
    assert local_map.n_anchors == 1  # the 0.7 point's voxel was already anchored


def test_anchors_at_zero_keep_every_point_with_or_without_frequencies():
    from gft_odom.core.local_map import LocalMap
    local_map = LocalMap(0.1, 100.0, 10_000, 1, 1.0, 0.2, 5, with_normals=False,
                         anchor_smoothness=0.0)
    for x in (0.0, 10.0, 20.0):
        T = np.eye(4)
        T[0, 3] = x
        local_map.add_keyframe(np.array([[x, 2.0, 0.0], [x, -2.0, 2.0]]), T)
    assert local_map.n_anchors == 4  # both points of the two keyframes that left
    assert len(local_map) == 6


def test_anchors_are_bounded_by_dropping_the_farthest():
    from gft_odom.core.local_map import LocalMap
    local_map = LocalMap(0.1, 100.0, 10_000, 1, 1.0, 0.2, 5, with_normals=False,
                         anchor_smoothness=0.0, anchor_max_points=2)
    for x in (0.0, 10.0, 20.0, 30.0):
        T = np.eye(4)
        T[0, 3] = x
        local_map.add_keyframe(np.array([[x, 2.0, 0.0]]), T)
    # Keyframes 0, 10 and 20 left the window; the newest is at 30: 0 is the farthest.
    assert local_map.n_anchors == 2
    assert sorted(local_map.points_xyz[:, 0].round()) == [10.0, 20.0, 30.0]


def test_rough_anchors_are_served_only_when_seen_from_their_side():
    from gft_odom.core.local_map import LocalMap
    # A smooth point (trunk) and a rough one (canopy) at y = 2, seen from the lane at y = 0.
    local_map = LocalMap(0.1, 100.0, 10_000, 1, 1.0, 0.2, 5, with_normals=False,
                         anchor_smoothness=0.75, rough_anchor_view_rad=np.radians(60.0))

    def keyframe(x, y):
        T = np.eye(4)
        T[:2, 3] = x, y
        return T

    local_map.add_keyframe(np.array([[0.0, 2.0, 0.0], [0.5, 2.0, 2.0]]), keyframe(0.0, 0.0),
                           np.array([0.9, 0.1]))
    # The keyframe leaves the window; a new one is in the same lane, a little further on.
    local_map.add_keyframe(np.array([[5.0, -3.0, 0.0]]), keyframe(1.0, 0.0), np.array([0.9]))
    assert local_map.n_anchors == 2
    served = {tuple(p) for p in local_map.points_xyz.round(1)}
    assert {(0.0, 2.0, 0.0), (0.5, 2.0, 2.0)} <= served  # both seen from their own side
    # From the far lane (y = 4) the canopy's other face is another cloud: only the trunk.
    local_map.add_keyframe(np.array([[5.0, 6.0, 0.0]]), keyframe(1.0, 4.0), np.array([0.9]))
    served = {tuple(p) for p in local_map.points_xyz.round(1)}
    assert (0.0, 2.0, 0.0) in served and (0.5, 2.0, 2.0) not in served
    # Without rough anchors the canopy leaves with its keyframe.
    plain = LocalMap(0.1, 100.0, 10_000, 1, 1.0, 0.2, 5, with_normals=False,
                     anchor_smoothness=0.75)
    plain.add_keyframe(np.array([[0.0, 2.0, 0.0], [0.5, 2.0, 2.0]]), keyframe(0.0, 0.0),
                       np.array([0.9, 0.1]))
    plain.add_keyframe(np.array([[5.0, -3.0, 0.0]]), keyframe(1.0, 0.0), np.array([0.9]))
    assert plain.n_anchors == 1


@pytest.mark.parametrize('smoothness', [np.array([0.9, 0.1]), None])
def test_the_windows_rough_points_are_served_from_their_side_when_asked(smoothness):
    from gft_odom.core.local_map import LocalMap

    def keyframe(y):
        T = np.eye(4)
        T[1, 3] = y
        return T

    trunk_and_canopy = np.array([[0.0, 2.0, 0.0], [0.5, 2.0, 2.0]])
    served = {}
    for view_deg in (None, 60.0):
        # Two keyframes in the window: the row at y = 2 from the lane at y = 0, then the
        # far lane at y = 4, which sees the row's other face.
        local_map = LocalMap(0.1, 100.0, 10_000, 10, 1.0, 0.2, 5, with_normals=False,
                             anchor_smoothness=0.75,
                             rough_window_view_rad=None if view_deg is None
                             else np.radians(view_deg))
        local_map.add_keyframe(trunk_and_canopy, keyframe(0.0), smoothness)
        local_map.add_keyframe(np.array([[5.0, 6.0, 0.0]]), keyframe(4.0),
                               None if smoothness is None else np.array([0.9]))
        served[view_deg] = {tuple(p) for p in local_map.points_xyz.round(1)}
    assert {(0.0, 2.0, 0.0), (0.5, 2.0, 2.0)} <= served[None]
    # The canopy's other face is another cloud; the trunk stays when the frequency says
    # smooth, and without frequencies every point is rough.
    assert (0.5, 2.0, 2.0) not in served[60.0]
    assert ((0.0, 2.0, 0.0) in served[60.0]) == (smoothness is not None)
    assert (5.0, 6.0, 0.0) in served[60.0]  # the newest keyframe's own points


@pytest.mark.parametrize('where', ['window', 'anchors'])
def test_smooth_points_are_served_from_their_side_when_asked(where):
    from gft_odom.core.local_map import LocalMap

    def keyframe(x, y):
        T = np.eye(4)
        T[:2, 3] = x, y
        return T

    trunk = np.array([[0.0, 2.0, 0.0]])
    served = {}
    for smooth_view_deg in (None, 60.0):
        for lane_x, lane_y in ((1.0, 0.0), (0.0, 4.0)):  # the same side (27 deg), the far side
            # A window of two keyframes, or of one (the trunk's keyframe leaves, an anchor).
            local_map = LocalMap(
                0.1, 100.0, 10_000, 2 if where == 'window' else 1, 1.0, 0.2, 5,
                with_normals=False, anchor_smoothness=0.75,
                rough_anchor_view_rad=np.radians(60.0),
                rough_window_view_rad=np.radians(60.0) if where == 'window' else None,
                smooth_view_rad=None if smooth_view_deg is None else np.radians(smooth_view_deg))
            local_map.add_keyframe(trunk, keyframe(0.0, 0.0), np.array([0.9]))
            local_map.add_keyframe(np.array([[5.0, 6.0, 0.0]]), keyframe(lane_x, lane_y),
                                   np.array([0.9]))
            served[smooth_view_deg, lane_y] = (0.0, 2.0, 0.0) in {
                tuple(p) for p in local_map.points_xyz.round(1)}
    # From any side by default; asked, the trunk's far face is not served, its near one is.
    assert served[None, 0.0] and served[None, 4.0]
    assert served[60.0, 0.0] and not served[60.0, 4.0]


def test_a_smooth_point_takes_over_a_rough_anchors_voxel():
    from gft_odom.core.local_map import LocalMap
    local_map = LocalMap(1.0, 100.0, 10_000, 1, 1.0, 0.2, 5, with_normals=False,
                         anchor_smoothness=0.75, rough_anchor_view_rad=np.radians(60.0))
    T = np.eye(4)
    # First seen far off, as rough; then near, as smooth; the voxel's anchor becomes smooth.
    for x, s in ((0.2, 0.1), (0.6, 0.9), (0.4, 0.2)):
        local_map.add_keyframe(np.array([[x, 0.5, 0.5]]), T, np.array([s]))
        T = T.copy()
        T[0, 3] += 20.0
    local_map.add_keyframe(np.array([[99.0, 0.5, 0.5]]), T, np.array([0.9]))
    assert local_map.n_anchors == 1
    # Served from the far side too (it is smooth): the voxel holds the smooth point.
    assert 0.6 in local_map.points_xyz[:, 0].round(1).tolist()


def test_without_frequencies_rough_anchors_keep_every_point_view_gated():
    from gft_odom.core.local_map import LocalMap
    local_map = LocalMap(0.1, 100.0, 10_000, 1, 1.0, 0.2, 5, with_normals=False,
                         anchor_smoothness=0.75, rough_anchor_view_rad=np.radians(60.0))
    T = np.eye(4)
    local_map.add_keyframe(np.array([[0.0, 2.0, 0.0], [0.5, 2.0, 2.0]]), T)
    T2 = T.copy()
    T2[1, 3] = 4.0  # the far lane
    local_map.add_keyframe(np.array([[5.0, 6.0, 0.0]]), T2)
    assert local_map.n_anchors == 2
    assert local_map.points_xyz.round(1).tolist() == [[5.0, 6.0, 0.0]]


def test_a_share_of_rough_anchors_drawn_by_voxel_is_served_from_any_side():
    from gft_odom.core.local_map import LocalMap, voxel_draw
    rng = np.random.default_rng(3)
    canopy = np.column_stack([rng.uniform(-1.0, 1.0, 4000), rng.uniform(1.5, 2.5, 4000),
                              rng.uniform(0.0, 1.0, 4000)])
    draw = voxel_draw(canopy, 0.1)
    # Fixed by the voxel, spread evenly over [0, 1).
    np.testing.assert_array_equal(draw, voxel_draw(canopy + 1e-4 * (canopy % 0.1 < 0.05), 0.1))
    assert np.all((draw >= 0.0) & (draw < 1.0))
    assert abs(np.mean(draw < 0.25) - 0.25) < 0.03
    served = {}
    for share in (0.0, 0.25, 1.0):
        local_map = LocalMap(0.1, 100.0, 100_000, 1, 1.0, 0.2, 5, with_normals=False,
                             anchor_smoothness=0.75, rough_anchor_view_rad=np.radians(60.0),
                             rough_anchor_any_side_share=share)
        T = np.eye(4)
        local_map.add_keyframe(canopy, T, np.full(len(canopy), 0.1))
        T2 = T.copy()
        T2[1, 3] = 4.0  # the far lane: the canopy is seen from its other side
        local_map.add_keyframe(np.array([[0.0, 6.0, 0.0]]), T2, np.array([0.9]))
        served[share] = len(local_map) - 1
    anchors = local_map.n_anchors
    assert served[0.0] == 0 and served[1.0] == anchors
    assert abs(served[0.25] / anchors - 0.25) < 0.05
    with pytest.raises(ConfigError, match='map_anchor_rough_any_side_share'):
        RegistrationConfig(map_anchor_rough_any_side_share=1.5).validate()


@pytest.mark.parametrize('name', ['map_anchor_rough_view_deg', 'map_window_rough_view_deg',
                                  'map_smooth_view_deg'])
def test_view_angles_are_validated(name):
    with pytest.raises(ConfigError, match=name):
        RegistrationConfig(**{name: 200.0}).validate()
    with pytest.raises(ConfigError, match=name):
        RegistrationConfig(**{name: float('nan')}).validate()
    RegistrationConfig(**{name: 90.0}).validate()
    # Without anchors the map is served from any side, and the message says how.
    with pytest.raises(ConfigError, match='map_anchors false needs the map served from any '
                                          'side: set map_window_rough_view_deg 0'):
        RegistrationConfig(map_anchors=False).validate()
    RegistrationConfig(map_anchors=False, map_window_rough_view_deg=0.0,
                       map_smooth_view_deg=180.0).validate()
    with pytest.raises(ConfigError, match='needs a view rule'):
        RegistrationConfig(map_smooth_view_deg=60.0, map_anchor_rough_view_deg=0.0,
                           map_window_rough_view_deg=0.0).validate()


def test_a_deferred_map_update_gives_the_same_poses_and_waits_for_update_map(drive):
    """The pose comes before the keyframe's map work; the poses do not depend on who does
    that work (the caller's update_map or the next register) or when."""
    inline, deferred = registration(), registration()
    pending_seen = updated_s = 0
    for scan in drive:
        a = inline.register(scan['points'], scan['stamp_ns'], scan['time'])
        assert not inline.map_update_pending
        n_before = len(deferred.local_map)
        b = deferred.register(scan['points'], scan['stamp_ns'], scan['time'],
                              defer_map_update=True)
        np.testing.assert_allclose(b.T_world_sensor, a.T_world_sensor, atol=1e-12)
        if deferred.map_update_pending:
            pending_seen += 1
            assert deferred.has_reference
            assert len(deferred.local_map) == n_before  # nothing added yet
            if pending_seen % 2 == 0:  # every other one is left to the next register
                seconds = deferred.update_map()
                assert seconds > 0.0 and not deferred.map_update_pending
                assert len(deferred.local_map) == len(inline.local_map)
                updated_s += 1
    assert pending_seen >= 3 and updated_s >= 1
    deferred.reset()
    assert not deferred.map_update_pending and not deferred.has_reference


@pytest.mark.parametrize('turn_check, margin, replaced',
                         [(True, 0.03, True), (False, 0.03, False), (True, 0.2, False)])
def test_a_poor_trusted_fit_is_replaced_by_a_turned_fit_that_fits_clearly_better(
        drive, turn_check, margin, replaced):
    """turn_check: a match trusted at a fit well below the recent ones is matched again from
    turned guesses; a turned fit replaces it only when it fits better by the margin. The
    ICP here reports fitness 0.80 from the prediction and 0.90 from anywhere else."""
    reg = _moving_registration(drive, n_scans=8, turn_check=turn_check,
                               turn_check_fitness_margin=margin, turn_check_gate_m=0.0,
                               **TURN_CHECK_SCENE)
    real_register, inits = reg.icp.register, []

    def scripted(source, target, init, distance_m, **kwargs):
        result = real_register(source, target, init, distance_m, **kwargs)
        inits.append(np.asarray(init, dtype=float))
        return IcpResult(inits[-1], 0.80 if len(inits) == 1 else 0.90, result.inlier_rmse,
                         np.asarray(result.correspondence_set), None, 1)

    reg.icp.register = scripted
    scan = drive[8]
    result = reg.register(scan['points'], scan['stamp_ns'], scan['time'])
    assert result.status == 'ok'
    turned_rad = transform_magnitude(invert_transform(inits[0]) @ result.T_world_sensor)[1]
    assert reg.n_turn_checks == (1 if turn_check else 0)
    assert reg.n_turns_found == (1 if replaced else 0)
    if replaced:  # one step of 1 rad/s over the scan period
        assert turned_rad == pytest.approx(RegistrationConfig().recovery_yaw_rate_step_rps
                                           * SCAN_PERIOD_S, rel=0.05)
    else:
        assert turned_rad < 1e-6


@pytest.mark.parametrize('gate_m, replaced', [(0.0, True), (0.3, False)])
def test_with_a_gate_the_turn_check_compares_fits_by_their_points_near_the_map(
        drive, gate_m, replaced):
    """turn_check_gate_m: ICP's fitness counts pairs within 1 m, which open ground gives any
    heading; within the gate the true pose stands out. Here ICP reports 0.80 for the match
    from the prediction (the true pose: the drive is straight) and 0.90 for each turned guess
    left where it started (0.1 rad off): by fitness a turn wins, by the gate the match."""
    reg = _moving_registration(drive, n_scans=8, turn_check_gate_m=gate_m, **TURN_CHECK_SCENE)
    real_register, inits = reg.icp.register, []

    def scripted(source, target, init, distance_m, **kwargs):
        result = real_register(source, target, init, distance_m, **kwargs)
        inits.append(np.asarray(init, dtype=float))
        first = len(inits) == 1
        T = np.asarray(result.transformation) if first else inits[-1]
        return IcpResult(T, 0.80 if first else 0.90, result.inlier_rmse,
                         np.asarray(result.correspondence_set), None, 1)

    reg.icp.register = scripted
    scan = drive[8]
    result = reg.register(scan['points'], scan['stamp_ns'], scan['time'])
    assert result.status == 'ok' and reg.n_turn_checks == 1
    assert reg.n_turns_found == (1 if replaced else 0)
    assert result.fitness == pytest.approx(0.90 if replaced else 0.80)


@pytest.mark.parametrize('screen, screened_fitness, carried_on', [
    (10, (0.70, 0.85, 0.70, 0.85), (1, 3)),  # the better half, both as good as the match
    (10, (0.50, 0.60, 0.75, 0.55), (1, 2)),  # none fits as well: the better half
    (10, (0.82, 0.85, 0.75, 0.81), (0, 1, 3)),  # three fit as well as the match (0.80)
    (0, None, ())])
def test_the_turn_check_carries_on_only_the_better_screened_guesses(
        drive, screen, screened_fitness, carried_on):
    """turn_check_screen_iterations: each turned guess is matched for that many iterations;
    the better half of them and those then fitting at least as well as the match go on, from
    where they stopped, for the rest of max_iterations. The ICP here reports 0.80 from the
    prediction, `screened_fitness` for the guesses after the screen and 0.90 once carried on
    (0: no screen, every guess to the full budget at 0.85)."""
    reg = _moving_registration(drive, n_scans=8, turn_check_gate_m=0.0,
                               turn_check_screen_iterations=screen, **TURN_CHECK_SCENE)
    real_register, calls = reg.icp.register, []

    def scripted(source, target, init, distance_m, **kwargs):
        result = real_register(source, target, init, distance_m, **kwargs)
        budget = kwargs.get('max_iterations')
        n_screened = sum(1 for _, b, _ in calls if b == screen)
        if not calls:
            fitness = 0.80
        elif screen and budget == screen:
            fitness = screened_fitness[n_screened]
        else:
            fitness = 0.90 if screen else 0.85
        T = np.asarray(init, dtype=float).copy()
        T[2, 3] += 0.01  # where this call stopped
        calls.append((np.asarray(init, dtype=float), budget, T))
        return IcpResult(T, fitness, result.inlier_rmse, np.asarray(result.correspondence_set),
                         None, budget or RegistrationConfig().max_iterations)

    reg.icp.register = scripted
    scan = drive[8]
    result = reg.register(scan['points'], scan['stamp_ns'], scan['time'])
    assert reg.n_turn_checks == 1 and reg.n_turns_found == 1
    budgets = [budget for _, budget, _ in calls[1:]]
    if not screen:
        assert budgets == [None] * 4
        assert result.fitness == pytest.approx(0.85)
        return
    full = RegistrationConfig().max_iterations
    assert budgets == [screen] * 4 + [full - screen] * len(carried_on)
    for call, guess in zip(calls[5:], carried_on):  # each from where its screen stopped
        np.testing.assert_array_equal(call[0], calls[1 + guess][2])
    assert result.fitness == pytest.approx(0.90)


@pytest.mark.parametrize('share_ratio, offset_rad, checked', [
    (0.0, 0.15, False),  # only the fitness trigger: the fitness is as recent ones'
    (0.9, 0.15, True),  # few points near the map for the recent matches: checked
    (0.9, 0.0, False)])  # the match where the recent ones were: not checked
def test_a_match_with_few_points_near_the_map_is_turn_checked(
        drive, share_ratio, offset_rad, checked):
    """turn_check_share_ratio: at a turn's onset in open ground the ground keeps ICP's
    fitness while the match is off; its share of points within turn_check_gate_m of the map
    falls. Here ICP's match from the prediction reports its real fitness at a pose turned
    by `offset_rad`."""
    # A keyframe every scan: the share does not fall as the scan leaves its keyframe.
    reg = _moving_registration(drive, n_scans=8, turn_check_share_ratio=share_ratio,
                               keyframe_distance_m=0.01)
    assert len(reg.recovery.recent_share) == (7 if share_ratio else 0)  # scans 1-7 matched
    assert reg.n_turn_checks == 0
    real_register, n_calls = reg.icp.register, []

    def scripted(source, target, init, distance_m, **kwargs):
        result = real_register(source, target, init, distance_m, **kwargs)
        n_calls.append(1)
        T = np.asarray(result.transformation).copy()
        if len(n_calls) == 1:
            T[:3, :3] = T[:3, :3] @ Rotation.from_euler('z', offset_rad).as_matrix()
        return IcpResult(T, result.fitness, result.inlier_rmse,
                         np.asarray(result.correspondence_set), None, 1)

    reg.icp.register = scripted
    scan = drive[8]
    recent = float(np.median(reg.trust.recent_fitness))
    result = reg.register(scan['points'], scan['stamp_ns'], scan['time'])
    assert result.status == 'ok' and result.fitness >= 0.95 * recent  # no fitness trigger
    assert reg.n_turn_checks == (1 if checked else 0)
    with pytest.raises(ConfigError, match='turn_check_gate_m'):
        RegistrationConfig(turn_check_share_ratio=0.9, turn_check_gate_m=0.0).validate()


def onset_of_turn(onset_s: float, speed_mps: float = 1.5, yaw_rate_rps: float = 2.0):
    """Straight along x until `onset_s`, then a turn at `yaw_rate_rps` (a headland corner)."""
    def pose_at(times_s):
        t = np.asarray(times_s, dtype=float)
        turning_s = np.maximum(t - onset_s, 0.0)
        yaw = yaw_rate_rps * turning_s
        # Along the heading: straight, then the arc of the turn.
        x = speed_mps * np.minimum(t, onset_s) + speed_mps * np.where(
            turning_s > 0, np.sin(yaw) / yaw_rate_rps, 0.0)
        y = speed_mps * np.where(turning_s > 0, (1.0 - np.cos(yaw)) / yaw_rate_rps, 0.0)
        poses = np.tile(np.eye(4), (t.size, 1, 1))
        poses[:, :3, :3] = Rotation.from_euler('z', yaw[:, None]).as_matrix()
        poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = x, y, SENSOR_HEIGHT_M
        return poses
    return pose_at


@pytest.mark.parametrize('guess_deskew', [True, False])
def test_turned_guesses_are_matched_with_the_scan_deskewed_by_their_own_turn(
        orchard, guess_deskew):
    """turn_guess_deskew: at a turn's onset the prediction has no turn, and the scan deskewed
    with it is bent the wrong way; the turn check's turned guesses each match the scan deskewed
    by their own motion, which puts a guess close to the true turn closer to the true scene.
    The ICP here reports fitness 0.80 from the prediction (so the check runs)."""
    n_straight = 6
    pose_at = onset_of_turn(onset_s=n_straight * SCAN_PERIOD_S)
    scans = [scan_scene(orchard, pose_at, k * SCAN_PERIOD_S, seed=k)
             for k in range(n_straight + 1)]
    reg = registration(turn_guess_deskew=guess_deskew, **TURN_CHECK_SCENE)
    for scan in scans[:n_straight]:
        assert reg.register(scan['points'], scan['stamp_ns'], scan['time']).status in (
            'first', 'ok')
    real_register, calls = reg.icp.register, []

    def scripted(source, target, init, distance_m, **kwargs):
        result = real_register(source, target, init, distance_m, **kwargs)
        calls.append((np.asarray(source.points).copy(), np.asarray(init, dtype=float)))
        return IcpResult(calls[-1][1], 0.80 if len(calls) == 1 else 0.90, result.inlier_rmse,
                         np.asarray(result.correspondence_set), None, 1)

    reg.icp.register = scripted
    turning = scans[n_straight]
    reg.register(turning['points'], turning['stamp_ns'], turning['time'])
    assert reg.n_turn_checks == 1 and len(calls) == 5  # the prediction, then 4 turned guesses
    predicted_xyz, init_pred = calls[0]
    # The guess turned the most to the left (+2 rad/s): the true turn.
    yaw_of = [Rotation.from_matrix((invert_transform(init_pred) @ init)[:3, :3]).as_euler(
        'zyx')[0] for _, init in calls[1:]]
    turned_xyz = calls[1 + int(np.argmax(yaw_of))][0]
    if not guess_deskew:
        np.testing.assert_array_equal(turned_xyz, predicted_xyz)
        return
    keep = voxel_downsample_indices(turning['points'], RegistrationConfig().voxel_size_m)
    truth = turning['undistorted'][keep]
    error_predicted = np.median(np.linalg.norm(predicted_xyz - truth, axis=1))
    error_turned = np.median(np.linalg.norm(turned_xyz - truth, axis=1))
    # Deskew with half the turn (the mean of the recent twist and the guess's) halves the bend.
    assert error_turned < 0.7 * error_predicted


def test_rough_points_move_along_their_beams_into_the_map(static_pair):
    """`rough_beam_shift_m`: a rough point (nu 0) moves its full shift along its beam, a
    smooth one (nu >= smooth_nu) or one without frequencies not at all."""
    a, _, _ = static_pair
    n = len(a['points'])
    maps = {}
    for name, shift_m, nu in (('plain', 0.0, np.zeros(n)), ('rough', 0.2, np.zeros(n)),
                              ('smooth', 0.2, np.full(n, 0.4)), ('no frequency', 0.2, None)):
        reg = registration(rough_beam_shift_m=shift_m)
        assert reg.register(a['points'], a['stamp_ns'], nu=nu).status == 'first'
        maps[name] = np.linalg.norm(reg.local_map.points_xyz, axis=1)  # sensor at the origin
    for name in ('smooth', 'no frequency'):
        np.testing.assert_array_equal(maps[name], maps['plain'])
    assert np.median(maps['rough']) - np.median(maps['plain']) == pytest.approx(0.2, abs=0.05)


def test_rough_beam_shift_is_bounded():
    with pytest.raises(ConfigError, match='rough_beam_shift_m'):
        RegistrationConfig(rough_beam_shift_m=2.0).validate()
    RegistrationConfig(rough_beam_shift_m=-0.1).validate()


def _retried_with_scripted_fits(drive, move_first, first_fitness: float, other_fitness: float,
                                **overrides):
    """Scan 8 of `drive` after 8 matched ones: the match from the prediction fails (fitness
    0.3) and is retried; the retry's first fine fit stops at `move_first(init)` with
    `first_fitness`, every other one where it started with `other_fitness`. The result and the
    number of fine fits."""
    reg = _moving_registration(drive, n_scans=8, turn_check=False, **overrides)
    real_register, fine_fits = reg.icp.register, []

    def scripted(source, target, init, distance_m, **kwargs):
        result = real_register(source, target, init, distance_m, **kwargs)
        T, fitness = np.asarray(init, dtype=float).copy(), other_fitness
        if kwargs.get('prior'):
            fitness = 0.3  # the match from the prediction
        elif kwargs.get('recovery'):
            fine_fits.append(1)
            if len(fine_fits) == 1:
                T, fitness = move_first(T), first_fitness
        return IcpResult(T, fitness, result.inlier_rmse, np.asarray(result.correspondence_set),
                         None, 1)

    reg.icp.register = scripted
    scan = drive[8]
    return reg.register(scan['points'], scan['stamp_ns'], scan['time']), len(fine_fits)


def _moved_1_m_along_x(T: np.ndarray) -> np.ndarray:
    T[0, 3] += 1.0
    return T


def _turned_0_1_rad(T: np.ndarray) -> np.ndarray:
    T[:3, :3] = T[:3, :3] @ Rotation.from_euler('z', 0.1).as_matrix()
    return T


@pytest.mark.parametrize('beats_refused', [False, True])
def test_a_retry_gives_up_when_a_refused_fit_explains_the_scan_clearly_better(
        drive, beats_refused):
    """reacquisition_beats_refused: the match from the prediction fails; the retry's first
    guess fits 0.95 but 1 m off (beyond the bounds from the last trusted pose), every other
    guess fits 0.75 where it started. Off: the poor plausible fit is taken (`recovered`); on:
    a refused fit explains the scan clearly better, so the last trusted pose is the likelier
    error: a fallback."""
    result, n_fine = _retried_with_scripted_fits(drive, _moved_1_m_along_x, 0.95, 0.75,
                                                 reacquisition_beats_refused=beats_refused)
    assert n_fine >= 2  # the refused fit and at least one plausible one
    assert result.status == ('fallback_low_fitness' if beats_refused else 'recovered')


@pytest.mark.parametrize('by_share', [False, True])
def test_reacquisition_can_pick_its_fit_by_the_share_near_the_map(drive, by_share):
    """reacquisition_by_share: the match from the prediction fails; of the retry's fits the
    first reports fitness 0.95 at a pose turned 0.1 rad (few points within 0.3 m of the map),
    the others 0.85 where they started (near the truth). By ICP's fitness the turned one
    wins; by the share near the map the other."""
    result, _ = _retried_with_scripted_fits(drive, _turned_0_1_rad, 0.95, 0.85,
                                            reacquisition_by_share=by_share)
    assert result.status == 'recovered'
    assert result.fitness == pytest.approx(0.85 if by_share else 0.95)
    with pytest.raises(ConfigError, match='turn_check_gate_m'):
        RegistrationConfig(reacquisition_by_share=True, turn_check_gate_m=0.0).validate()


@pytest.mark.parametrize('min_rad, continued', [(0.0, False), (0.02, True), (0.2, False)])
def test_a_match_capped_while_still_turning_carries_on(static_pair, min_rad, continued):
    """turn_continue_min_rad: the prediction (standing still) misses b's 3 deg turn; ICP
    stopped by its iteration cap (here 2) has turned part of the way and is still turning;
    carried on, it gets there. A threshold above what it turned leaves it capped."""
    a, b, T_ab = static_pair
    reg = registration(max_iterations=2, deskew=False, turn_check=False,
                       turn_continue_min_rad=min_rad)
    reg.register(a['points'], a['stamp_ns'])
    result = reg.register(b['points'], b_stamp(a))
    assert result.status == 'ok'
    assert reg.n_turn_continued == int(continued)
    err_m, err_rad = pose_error(result.T_world_sensor, T_ab)
    if continued:
        assert err_m < 0.04 and err_rad < np.deg2rad(0.3), (err_m, np.rad2deg(err_rad))
    else:
        assert err_rad > np.deg2rad(0.6), np.rad2deg(err_rad)
    for other in ({'solver': 'open3d'}, {'mode': 'paper'}):  # their ICP does not say
        with pytest.raises(ConfigError, match='turn_continue_min_rad'):
            RegistrationConfig(turn_continue_min_rad=0.02, **other).validate()


# ---------------------------------------------------------------- adaptive kernel

def _kernel_scales(registration: ScanRegistration, scans: list[dict]) -> list[float]:
    scales = []
    for scan in scans:
        registration.register(scan['points'], scan['stamp_ns'], scan['time'])
        scales.append(registration.icp.kernel_scale_m)
    return scales


@pytest.mark.parametrize('solver', ['map_tree', 'gauss_newton', 'open3d'])
def test_the_kernel_follows_the_prediction_errors_and_starts_over_at_reset(drive, solver):
    scans = drive[:8]
    cfg = dataclasses.replace(RegistrationConfig(), solver=solver, adaptive_kernel_ratio=0.5,
                              adaptive_min_motion_m=0.001)
    registration = ScanRegistration(cfg)
    scales = _kernel_scales(registration, scans)
    # The first scan is not matched: the fixed scale; from the second match on, half the
    # RMS of the prediction errors at the map's range.
    assert scales[0] == cfg.robust_kernel_scale_m
    assert registration.threshold.n_samples >= 5
    assert scales[-1] == pytest.approx(0.5 * registration.threshold.sigma_m)
    assert scales[-1] != pytest.approx(cfg.robust_kernel_scale_m, abs=1e-3)
    # The solver that matches uses it (open3d: its Tukey loss object).
    icp = registration.icp
    assert icp.kernel.k == pytest.approx(scales[-1])
    if solver != 'open3d':
        assert (icp.map_tree or icp.solver).kernel_scale_m == scales[-1]
    registration.reset()
    assert registration.icp.kernel_scale_m == cfg.robust_kernel_scale_m
    assert registration.threshold.n_samples == 0
    # Off: the scale never moves.
    fixed = _kernel_scales(ScanRegistration(dataclasses.replace(cfg, adaptive_kernel_ratio=0.0)),
                           scans)
    assert set(fixed) == {cfg.robust_kernel_scale_m}
