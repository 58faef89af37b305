"""Synthetic orchards and a fake VLP-16 for the registration's tests.

The scenes are small orchards (trunks as vertical cylinders, canopies as ellipsoids, a wavy
ground) seen by a fake 16-ring scanner that spins clockwise (seen from above) like a VLP-16 and
fires each column at its own time from its own pose, so scans carry real motion distortion.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import invert_transform
from gft_odom.core.registration import RegistrationConfig, ScanRegistration
from gft_odom.core.registration.motion import transform_magnitude

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




def run_drive(reg: ScanRegistration, scans: list[dict], use_time: bool = True):
    """(per-scan (position m, rotation rad) errors, statuses) of `scans` through `reg`."""
    T_world0 = invert_transform(scans[0]['T_world_sensor'])
    errors, statuses = [], []
    for scan in scans:
        result = reg.register(scan['points'], scan['stamp_ns'],
                              scan['time'] if use_time else None)
        statuses.append(result.status)
        errors.append(pose_error(result.T_world_sensor, T_world0 @ scan['T_world_sensor']))
    return np.array(errors), statuses


def yaw_errors(scans: list[dict], **overrides) -> list[float]:
    """Each scan's heading error [rad] through a registration with `overrides`."""
    return list(run_drive(registration(**overrides), scans, use_time=False)[0][:, 1])


def later_stamp(scan: dict) -> int:
    """A stamp one scan period after `scan`'s."""
    return scan['stamp_ns'] + 100_000_000
