"""Degeneracy told: the weakest translation direction of a match, from its information.

A match constrains the sensor's translation through the surfaces it sees: ground fixes z,
trunks and canopies fix x and y. Where they leave a direction free (open ground: only the
terrain's slopes hold x and y; a row of uniform hedges: the direction along it), the estimate
along it leans on the motion prior. Measured on simulated drives (tests/core/test_degeneracy):
the weakest direction of an orchard row is along the row at ~0.3 of the strongest's
information, continuous hedges ~0.1, open ground ~0.002.

The strength is a ratio, independent of the number of points and the residual scale: the
smallest over the largest eigenvalue of the translation's information with the rotation free
(the Schur complement H_tt - H_tr H_rr^-1 H_rt of the (x, y, z, rot_x, rot_y, rot_z)
information; the rotation is about the sensor).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A cloud whose thinnest principal axis has a standard deviation below this is flat (ground
# only, a wall): ICP cannot observe the in-plane motion (x, y, yaw on ground) but converges
# with a confident covariance and drags the map along, so the motion prediction is used
# instead. Orchard scans measure >= 0.69 m on that axis whatever the band mask, bare sim
# ground 0.01-0.04 m (docs/robustness.md).
FLAT_CLOUD_STD_M = 0.05

AXES = ('x', 'y', 'z')
# A direction is named by one axis when that axis holds at least this much of it.
AXIS_ALIGNED = 0.9


@dataclass(frozen=True)
class WeakDirection:
    """The least constrained translation direction (unit, in the axes asked for)."""

    direction: np.ndarray  # (3,) unit, sign fixed so that its largest component is positive
    ratio: float  # its information over the strongest direction's, in [0, 1]
    axis: str  # the axis it is closest to

    @property
    def text(self) -> str:
        """'translation along x' or, off the axes, 'translation along (0.58, 0.81, 0.03)'."""
        if abs(self.direction[AXES.index(self.axis)]) >= AXIS_ALIGNED:
            return f'translation along {self.axis}'
        return 'translation along (' + ', '.join(f'{v:.2f}' for v in self.direction) + ')'


def translation_information(information: np.ndarray) -> np.ndarray:
    """(3, 3) information of the translation with the rotation free (Schur complement)."""
    H = 0.5 * (np.asarray(information, float) + np.asarray(information, float).T)
    H_tt, H_tr, H_rr = H[:3, :3], H[:3, 3:], H[3:, 3:]
    return H_tt - H_tr @ np.linalg.pinv(H_rr) @ H_tr.T


def weakest_translation(information: np.ndarray | None,
                        R_axes_info: np.ndarray | None = None) -> WeakDirection | None:
    """The weakest translation direction of a (6, 6) information (x, y, z, rot_x, rot_y, rot_z),
    expressed in other axes by `R_axes_info` (rotation from the information's axes to those,
    e.g. base_link's); None without information (a fallback)."""
    if information is None:
        return None
    H_t = translation_information(information)
    if R_axes_info is not None:
        H_t = R_axes_info @ H_t @ R_axes_info.T
    values, vectors = np.linalg.eigh(0.5 * (H_t + H_t.T))
    if not np.all(np.isfinite(values)) or values[-1] <= 0.0:
        return WeakDirection(np.array([1.0, 0.0, 0.0]), 0.0, 'x')
    direction = vectors[:, 0]
    direction = direction * np.sign(direction[np.argmax(np.abs(direction))])
    ratio = float(np.clip(values[0] / values[-1], 0.0, 1.0))
    return WeakDirection(direction, ratio, AXES[int(np.argmax(np.abs(direction)))])


def thinnest_axis_std_m(points_xyz: np.ndarray) -> float:
    """Standard deviation of the points along their thinnest principal axis (inf if < 10)."""
    if points_xyz.shape[0] < 10:
        return float('inf')  # too few to judge: registration's min_points decides
    # Axis-major (3, N): the mean and the 3 x 3 product run ~3x faster than on (N, 3) rows.
    axes = np.ascontiguousarray(points_xyz.T, dtype=np.float64)
    centred = axes - axes.mean(axis=1, keepdims=True)
    scatter = centred @ centred.T / points_xyz.shape[0]
    return float(np.sqrt(max(np.linalg.eigvalsh(scatter)[0], 0.0)))
