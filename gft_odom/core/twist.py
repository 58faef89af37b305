"""The body twist the odometry publishes: the motion model's velocity in base_link.

Registration keeps the velocity (rot rad/s, lin m/s) of the motion since the last trusted pose,
expressed in that pose's sensor axes: `lin` is the chord of the path over the step. The twist
of nav_msgs/Odometry is in `child_frame_id` (base_link) at the scan's stamp, linear first:
- the chord of a constant-twist (planar) arc points along the heading half-way through it and
  is sin(a)/a of the arc (a = |omega| dt / 2), so the velocity at the end of the step, in the
  sensor axes of that moment, is R(omega dt / 2)^T lin a / sin(a);
- at base_link's origin (rigid body, lever arm t from base to sensor): v_b = R_bs v_s + t x w_b,
  w_b = R_bs w_s.
Covariance (a documented model, not a filter's): the velocity is an increment of two matches
over dt, each as uncertain as this scan's match, so Sigma_twist = 2 Sigma_pose / dt^2, taken to
base_link with the same linear map. A fallback (or the first scan) has no measured twist: zero
with a standard deviation of the platform's bounds (`max_speed_mps`, `max_yaw_rate_rps`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _sensor_to_base_map(T_base_sensor: np.ndarray) -> np.ndarray:
    """(6, 6) A with [v_b; w_b] = A [v_s; w_s] (linear first)."""
    R, t = T_base_sensor[:3, :3], T_base_sensor[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = _skew(t) @ R
    A[3:, 3:] = R
    return A


def base_twist(twist_sensor: np.ndarray, T_base_sensor: np.ndarray,
               step_s: float) -> np.ndarray:
    """(6,) [v_x, v_y, v_z, w_x, w_y, w_z] of base_link in its own axes (m/s, rad/s) from
    registration's (rot_x, rot_y, rot_z, v_x, v_y, v_z) over the previous sensor axes."""
    twist_sensor = np.asarray(twist_sensor, dtype=float)
    omega, chord = twist_sensor[:3], twist_sensor[3:]
    half_turn = 0.5 * omega * max(float(step_s), 0.0)
    # The chord of an arc is sin(a)/a (a: half the turn) of its length, at the mid heading.
    arc_factor = float(np.sinc(np.linalg.norm(half_turn) / np.pi))
    v_s = Rotation.from_rotvec(half_turn).as_matrix().T @ chord / arc_factor
    return _sensor_to_base_map(T_base_sensor) @ np.concatenate([v_s, omega])


def base_twist_covariance(pose_covariance: np.ndarray, R_axes_sensor: np.ndarray,
                          T_base_sensor: np.ndarray, step_s: float) -> np.ndarray:
    """(6, 6) covariance of `base_twist` (linear first) from the match's pose covariance
    (x, y, z, rot_x, rot_y, rot_z in the axes `R_axes_sensor` maps the sensor's into)."""
    rotate = np.zeros((6, 6))
    rotate[:3, :3] = rotate[3:, 3:] = R_axes_sensor.T
    cov_sensor = rotate @ np.asarray(pose_covariance, dtype=float) @ rotate.T
    A = _sensor_to_base_map(T_base_sensor)
    cov = A @ (2.0 * cov_sensor / max(float(step_s), 1e-3) ** 2) @ A.T
    return 0.5 * (cov + cov.T)


def unknown_twist_covariance(max_speed_mps: float, max_yaw_rate_rps: float) -> np.ndarray:
    """(6, 6) covariance of the zero twist sent when none was measured: the bounds as std."""
    return np.diag([max_speed_mps ** 2] * 3 + [max_yaw_rate_rps ** 2] * 3)
