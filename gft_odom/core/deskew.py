"""Motion compensation of one LiDAR sweep under a constant-velocity assumption.

A spinning LiDAR measures each point from a different pose while the robot moves; the sweep is
a smear of about 0.1 s of motion. We undo it by expressing every point in the sensor frame at
ONE instant, the sweep's `header.stamp` (time offset 0), so the pose that registration estimates
is the sensor pose at the stamp the pipeline publishes.

Time offsets come from the per-point time field when the bag has it (offsets relative to
`header.stamp`, negative when the driver stamps with the last packet, as the ROS velodyne
driver's [-0.1, 0] s; its unit is found from the values: s, ms, us, ns, or absolute times),
otherwise from the azimuth. VLP-16 convention assumed (velodyne manual and driver): the head
spins clockwise seen from above, i.e. in the ROS sensor frame (x forward, y left, z up) the
angle `atan2(y, x)` DECREASES with time; the driver emits points in firing order, so the first
point of the cloud is the start of the sweep.
"""

from __future__ import annotations

import numpy as np

from gft_odom.core.geometry import rotate_about_axis, rotation_matrix, rotation_vector

TWO_PI = 2.0 * np.pi
# Units a per-point time field comes in (velodyne float s, Ouster uint32 ns, some drivers us).
TIME_UNITS_S = (('s', 1.0), ('ms', 1e-3), ('us', 1e-6), ('ns', 1e-9))
# No offset within one sweep is this far from the stamp (a VLP-16 sweep lasts 0.05-0.2 s):
# the unit is the first that puts every offset inside it. Sweeps are 3 decades apart in the
# four units, so a full sweep is never ambiguous.
MAX_TIME_OFFSET_S = 1.0


def time_offsets_from_field(values: np.ndarray, stamp_ns: int) -> tuple[np.ndarray | None, str]:
    """Per-point offsets (s) from the stamp of a per-point time field, and the unit found.

    Relative offsets in s, ms, us or ns (either sign: [0, 0.1] s from a sweep-start stamp,
    [-0.1, 0] s from a sweep-end stamp); absolute times in s or ns since the epoch (Hesai,
    Livox) have the stamp subtracted. (None, 'unknown') when no reading fits.
    """
    raw = np.asarray(values)
    finite = raw[np.isfinite(raw)] if raw.dtype.kind == 'f' else raw
    if finite.size == 0:
        return np.zeros(raw.shape[0]), 's'
    peak = float(np.max(np.abs(finite.astype(np.float64))))
    for name, scale in TIME_UNITS_S:
        if peak * scale <= MAX_TIME_OFFSET_S:
            return raw.astype(np.float64) * scale, name
    median = float(np.median(finite.astype(np.float64)))
    if abs(median - stamp_ns * 1e-9) <= MAX_TIME_OFFSET_S:
        return raw.astype(np.float64) - stamp_ns * 1e-9, 'absolute_s'
    if abs(median * 1e-9 - stamp_ns * 1e-9) <= MAX_TIME_OFFSET_S:
        if raw.dtype.kind in 'iu':  # exact in integers before the float conversion
            return (raw.astype(np.int64) - int(stamp_ns)).astype(np.float64) * 1e-9, 'absolute_ns'
        return (raw.astype(np.float64) - float(stamp_ns)) * 1e-9, 'absolute_ns'
    return None, 'unknown'


def azimuth_time_offsets(points_xyz: np.ndarray, scan_period_s: float,
                         stamp_at_sweep_end: bool = False) -> np.ndarray:
    """Per-point time offsets (s) from the azimuth, for clouds without a `time` field.

    The fraction of the sweep is the clockwise angle from the first point's azimuth over 2 pi.
    A sweep a little longer than one turn (the driver cuts on packet boundaries) wraps: points
    in the second half of the cloud that land in the first quarter are moved to the end.
    With `stamp_at_sweep_end` (ROS velodyne driver default `timestamp_first_packet: false`)
    the offsets run from -period to 0, otherwise from 0 to period.
    """
    n = points_xyz.shape[0]
    if n == 0:
        return np.zeros(0)
    azimuth_rad = np.arctan2(points_xyz[:, 1], points_xyz[:, 0])
    fraction = np.mod(azimuth_rad[0] - azimuth_rad, TWO_PI) / TWO_PI
    # Points come in firing order: an early point just "after" the first one (rounding, or
    # azimuth -pi vs pi) is at the start, a late one just "before" it is past a full turn.
    late = np.arange(n) > n // 2
    fraction = np.where(late & (fraction < 0.25), fraction + 1.0, fraction)
    fraction = np.where(~late & (fraction > 0.75), 0.0, fraction)
    offsets_s = fraction * scan_period_s
    if stamp_at_sweep_end:
        offsets_s -= scan_period_s
    return offsets_s


def sweep_middle_offset_s(time_offset_s: np.ndarray | None, scan_period_s: float,
                          stamp_at_sweep_end: bool = False) -> float:
    """The middle of a sweep's time span, in s from its stamp: where the pose of a sweep
    registered as one rigid cloud (not deskewed) holds, since each half of the sweep pulls
    the fit towards its own pose. Without per-point times the sweep spans one period from
    the stamp (back from it with `stamp_at_sweep_end`)."""
    if time_offset_s is not None:
        offsets = np.asarray(time_offset_s, dtype=float)
        offsets = offsets[np.isfinite(offsets)]
        if offsets.size:
            return 0.5 * (float(offsets.min()) + float(offsets.max()))
    return -0.5 * scan_period_s if stamp_at_sweep_end else 0.5 * scan_period_s


def twist_from_delta(T_prev_curr: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Angular (rad/s) and linear (m/s) velocity, in the sensor frame, of a per-scan delta."""
    if not dt_s > 0.0:
        return np.zeros(3), np.zeros(3)
    omega = rotation_vector(T_prev_curr[:3, :3]) / dt_s
    return omega, T_prev_curr[:3, 3] / dt_s


def planar_delta(T_prev_curr: np.ndarray) -> np.ndarray:
    """Keep only the ground-robot part of a motion: x, y translation and yaw (sensor axes).

    On rough ground the roll, pitch and height rates measured over one scan are vibration
    that does not persist into the next scan; extrapolating them into a deskew adds error
    (0.01 rad of wrong pitch moves a point 0.6 m at 60 m).
    """
    out = np.eye(4)
    yaw_rad = rotation_vector(T_prev_curr[:3, :3])[2]
    out[:3, :3] = rotation_matrix(np.array([0.0, 0.0, yaw_rad]))
    out[:2, 3] = T_prev_curr[:2, 3]
    return out


def deskew_points(points_xyz: np.ndarray, time_offset_s: np.ndarray,
                  T_prev_curr: np.ndarray, dt_s: float) -> np.ndarray:
    """Express each point in the sensor frame at offset 0 (the stamp).

    The sensor moves with the constant twist of `T_prev_curr` over `dt_s`; a point measured at
    offset s from pose T_0_s = exp(s * twist) maps to T_0_s p. Rotation and translation are
    interpolated separately, which is exact for the straight-line-plus-yaw motion of a ground
    robot over 0.1 s to well below the range noise.
    """
    omega, velocity = twist_from_delta(T_prev_curr, dt_s)
    if not np.any(omega) and not np.any(velocity):
        return points_xyz.copy()
    s = np.asarray(time_offset_s, dtype=float).reshape(-1, 1)
    rate_rps = float(np.linalg.norm(omega))
    turned = (rotate_about_axis(points_xyz, omega / rate_rps, s[:, 0] * rate_rps)
              if rate_rps > 0.0 else points_xyz)
    return turned + s * velocity
