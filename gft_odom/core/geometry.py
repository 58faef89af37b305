"""Rigid-body helpers: 4x4 homogeneous transforms and quaternions (x, y, z, w order, as TUM);
which points of a cloud are finite."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_transform(rotation: np.ndarray | None = None,
                   translation: np.ndarray | None = None) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation and a 3-vector (identity where omitted)."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = rotation
    if translation is not None:
        T[:3, 3] = translation
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Invert one (4, 4) or a stack (N, 4, 4) of rigid transforms without a general inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum('...ij,...j->...i', Rt, t)
    out[..., 3, 3] = 1.0
    return out


# Beyond this angle the axis of the skew part is ill-conditioned: scipy's general log map.
_NEAR_HALF_TURN_RAD = 3.0


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vector (axis x angle, rad) of one 3x3 rotation: the log map, in a few
    flops (scipy's Rotation.from_matrix checks and orthonormalises: ~0.3 ms a call, several
    calls a scan)."""
    skew = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    twice_sin = float(np.sqrt(skew @ skew))
    angle_rad = float(np.arctan2(0.5 * twice_sin, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    if angle_rad > _NEAR_HALF_TURN_RAD:
        return Rotation.from_matrix(R).as_rotvec()
    # angle / sin(angle) -> 1 at 0: the skew part is then 2 x the rotation vector.
    return skew * (0.5 if twice_sin < 1e-12 else angle_rad / twice_sin)


def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """The 3x3 rotation of a rotation vector (rad): the exp map (Rodrigues)."""
    angle_rad = float(np.linalg.norm(rotvec))
    if angle_rad < 1e-12:
        return np.eye(3)
    x, y, z = np.asarray(rotvec, dtype=float) / angle_rad
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1.0 - np.cos(angle_rad)) * (K @ K)


def rotate_about_axis(points_xyz: np.ndarray, axis: np.ndarray, angles_rad: np.ndarray
                      ) -> np.ndarray:
    """Each point (N, 3) turned by its own angle (N,) about one unit `axis` (Rodrigues on the
    vectors: deskew's rotations share the axis of the twist, so no (N, 3, 3) matrices)."""
    across = np.cross(axis, points_xyz)
    return (points_xyz + np.sin(angles_rad)[:, None] * across
            + (1.0 - np.cos(angles_rad))[:, None] * np.cross(axis, across))


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def poses_from_xyz_quat(xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """(N, 3) positions and (N, 4) quaternions (x, y, z, w) -> (N, 4, 4) poses."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    quat = np.asarray(quat_xyzw, dtype=float).reshape(-1, 4)
    poses = np.tile(np.eye(4), (xyz.shape[0], 1, 1))
    if xyz.shape[0]:
        poses[:, :3, :3] = Rotation.from_quat(quat).as_matrix()
        poses[:, :3, 3] = xyz
    return poses


def xyz_quat_from_poses(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) poses -> (N, 3) positions and (N, 4) quaternions (x, y, z, w)."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    if poses.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    return poses[:, :3, 3].copy(), Rotation.from_matrix(poses[:, :3, :3]).as_quat()


def rpy_transform(xyz=(0.0, 0.0, 0.0), rpy_rad=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Transform from a translation and roll/pitch/yaw (REP 103 fixed-axis x-y-z)."""
    return make_transform(Rotation.from_euler('xyz', rpy_rad).as_matrix(), np.asarray(xyz))


def sensor_to_base_poses(T_world_sensor: np.ndarray, T_base_sensor: np.ndarray) -> np.ndarray:
    """Sensor poses (world = first sensor frame) as base poses (odom = first base frame).

    T_odom_base = T_base_sensor @ T_world_sensor @ T_sensor_base, for one (4, 4) pose or a
    stack (N, 4, 4).
    """
    return T_base_sensor @ T_world_sensor @ invert_transform(T_base_sensor)


def base_to_sensor_poses(T_odom_base: np.ndarray, T_base_sensor: np.ndarray) -> np.ndarray:
    """The inverse of `sensor_to_base_poses`: T_sensor_base @ T_odom_base @ T_base_sensor."""
    return invert_transform(T_base_sensor) @ T_odom_base @ T_base_sensor


def least_variance_axis(covariance: np.ndarray) -> np.ndarray:
    """(m, 3) unit eigenvectors of the smallest eigenvalue of (m, 3, 3) symmetric PSD
    matrices: the eigenvalue in closed form (trigonometric), the vector as the longest cross
    product of two rows of C - lambda I; about 4x faster than `np.linalg.eigh` per matrix,
    which stays for the rare matrix whose two smallest eigenvalues coincide (a line)."""
    C = np.asarray(covariance, dtype=float)
    q = np.trace(C, axis1=1, axis2=2) / 3.0
    off = C[:, 0, 1] ** 2 + C[:, 0, 2] ** 2 + C[:, 1, 2] ** 2
    centred = C[:, [0, 1, 2], [0, 1, 2]] - q[:, None]
    p = np.sqrt((np.einsum('ij,ij->i', centred, centred) + 2.0 * off) / 6.0)
    B = (C - q[:, None, None] * np.eye(3)) / np.where(p > 0.0, p, 1.0)[:, None, None]
    r = np.clip(np.linalg.det(B) / 2.0, -1.0, 1.0)
    smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    M = C - smallest[:, None, None] * np.eye(3)
    crosses = np.stack([np.cross(M[:, 0], M[:, 1]), np.cross(M[:, 0], M[:, 2]),
                        np.cross(M[:, 1], M[:, 2])], axis=1)
    n2 = np.einsum('mcj,mcj->mc', crosses, crosses)
    at, best = np.arange(C.shape[0]), np.argmax(n2, axis=1)
    axis, length = crosses[at, best], np.sqrt(n2[at, best])
    # Relative to the scale of C squared (a cross product of two rows).
    degenerate = length <= 1e-12 * np.maximum(9.0 * q * q, np.finfo(float).tiny)
    axis = axis / np.where(degenerate, 1.0, length)[:, None]
    if degenerate.any():
        axis[degenerate] = np.linalg.eigh(C[degenerate])[1][:, :, 0]
    return axis


def finite_rows(points: np.ndarray) -> np.ndarray:
    """(N,) which rows of `points` (N, k) are finite in every column.

    `np.isfinite(points).all(axis=1)` costs ~0.5 ms on a 26 k-point scan, thirty times the
    flat `.all()`; a decoded scan is all finite (the decoder drops the rest), so that is
    checked first."""
    finite = np.isfinite(points)
    if finite.all():
        return np.ones(points.shape[0], dtype=bool)
    return finite.all(axis=1)


def along_beams(points_xyz: np.ndarray, distance_m: np.ndarray) -> np.ndarray:
    """Points (sensor frame) moved along their beams by `distance_m` each (positive: away
    from the sensor); a point never crosses to the sensor's other side (at most halved)."""
    range_m = np.sqrt(np.einsum('ij,ij->i', points_xyz, points_xyz))
    scale = np.maximum(1.0 + distance_m / np.maximum(range_m, 1e-9), 0.5)
    return points_xyz * scale[:, None]
