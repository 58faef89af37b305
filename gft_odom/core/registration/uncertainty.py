"""How certain one registration is: the information of its final ICP pairs and its covariance.

The covariance says how well this scan's match pins the pose down (x, y, z, rot_x, rot_y,
rot_z; world axes, about the sensor origin), not the accumulated drift. The information comes
from the final pairs, so weak directions (ground only: x, y, yaw) show as large variances;
the inflated fallback prior keeps it finite, and a floor keeps a good match from claiming
more certainty than the sensor has. A fallback reports the inflated prior alone.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from gft_odom.core.registration.matching import MapTarget

if TYPE_CHECKING:
    from gft_odom.core.registration.config import RegistrationConfig


def in_world_axes(matrix_6x6: np.ndarray, R_world_target: np.ndarray) -> np.ndarray:
    """A (6, 6) covariance or information of (translation, rotation) moved to world axes."""
    rotate = np.zeros((6, 6))
    rotate[:3, :3] = rotate[3:, 3:] = R_world_target
    return rotate @ matrix_6x6 @ rotate.T


def icp_information(source_xyz: np.ndarray, target, result, rmse: float) -> np.ndarray | None:
    """Gauss-Newton information J^T J / rmse^2 of the final pairs, in the target's axes.

    Point-to-plane rows [n, a x n] (a = point relative to the sensor) expose degenerate
    directions (ground only: x, y, yaw) as small information, hence large variances.
    Point-to-point rows are [I, -[a]x].
    """
    pairs = np.asarray(result.correspondence_set)
    if pairs.shape[0] < 6:
        return None
    R_target_sensor = np.asarray(result.transformation)[:3, :3]
    a = source_xyz[pairs[:, 0]] @ R_target_sensor.T
    # The map's normals, or (paper mode) open3d's cloud of the previous scan (none).
    n = (target.normals_at(pairs[:, 1]) if isinstance(target, MapTarget)
         else np.asarray(target.normals)[pairs[:, 1]] if target.has_normals() else None)
    if n is not None:
        J = np.hstack([n, np.cross(a, n)])
        H = J.T @ J
    else:
        s = a.sum(axis=0)
        S = np.array([[0.0, -s[2], s[1]], [s[2], 0.0, -s[0]], [-s[1], s[0], 0.0]])
        H = np.zeros((6, 6))
        H[:3, :3] = pairs.shape[0] * np.eye(3)
        H[:3, 3:] = -S
        H[3:, :3] = S
        H[3:, 3:] = np.einsum('ij,ij->', a, a) * np.eye(3) - a.T @ a
    return H / max(rmse, 1e-3) ** 2


def world_information(status: str, information: np.ndarray | None,
                      R_world_target: np.ndarray) -> np.ndarray | None:
    """The match's information in the covariance's axes (None on a fallback)."""
    if status.startswith('fallback') or information is None:
        return None
    return in_world_axes(information, R_world_target)


class PoseUncertainty:
    """The covariance of a registered pose: its floor and the inflated prior of a fallback."""

    def __init__(self, min_std_m: float, min_std_rad: float, fallback_std_m: float,
                 fallback_std_rad: float):
        self.min_var = np.array([min_std_m ** 2] * 3 + [min_std_rad ** 2] * 3)
        self.fallback_var = np.array([fallback_std_m ** 2] * 3 + [fallback_std_rad ** 2] * 3)

    @classmethod
    def from_config(cls, cfg: RegistrationConfig) -> 'PoseUncertainty':
        """From the `min_std_*` / `fallback_std_*` fields."""
        return cls(cfg.min_std_m, cfg.min_std_rad, cfg.fallback_std_m, cfg.fallback_std_rad)

    def covariance(self, status: str, information: np.ndarray | None,
                   R_world_target: np.ndarray) -> np.ndarray:
        """Fallback: the inflated prior. Match: (information + prior^-1)^-1, floored."""
        if status.startswith('fallback') or information is None:
            return np.diag(self.fallback_var)
        cov = np.linalg.inv(information + np.diag(1.0 / self.fallback_var))
        cov = in_world_axes(cov, R_world_target)
        cov = 0.5 * (cov + cov.T)
        idx = np.arange(6)
        cov[idx, idx] = np.maximum(cov[idx, idx], self.min_var)
        return cov
