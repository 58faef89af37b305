"""A trajectory: timestamps and poses, nothing else."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gft_odom.core.constants import NS_PER_S
from gft_odom.errors import GroundTruthError


@dataclass
class Trajectory:
    """Poses `T_world_body` at `stamps_ns` (int64 nanoseconds), sorted by time."""

    stamps_ns: np.ndarray  # (N,) int64
    poses: np.ndarray  # (N, 4, 4) float64

    def __post_init__(self) -> None:
        self.stamps_ns = np.asarray(self.stamps_ns, dtype=np.int64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=float).reshape(-1, 4, 4)
        if self.stamps_ns.shape[0] != self.poses.shape[0]:
            raise ValueError(f'{self.stamps_ns.shape[0]} stamps but {self.poses.shape[0]} poses')

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    @property
    def positions_xyz(self) -> np.ndarray:
        """(N, 3) positions of the body in the world frame."""
        return self.poses[:, :3, 3]

    @property
    def stamps_s(self) -> np.ndarray:
        """(N,) stamps in float seconds (for plots and evo; ns stay exact)."""
        return self.stamps_ns.astype(np.float64) * 1e-9

    def path_length_m(self) -> float:
        """Total distance travelled along the positions."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions_xyz, axis=0), axis=1).sum())

    def transformed(self, T_new_world: np.ndarray) -> 'Trajectory':
        """Express the trajectory in another world frame: T_new_body = T_new_world T_world_body."""
        return Trajectory(self.stamps_ns.copy(), T_new_world @ self.poses)

    def with_body_offset(self, T_body_other: np.ndarray) -> 'Trajectory':
        """Poses of a frame rigidly attached to the body: T_world_other = T_world_body T_b_o."""
        return Trajectory(self.stamps_ns.copy(), self.poses @ T_body_other)

    def pose_at(self, stamp_ns: int, max_extrapolation_s: float = 0.1) -> np.ndarray:
        """T_world_body at `stamp_ns`: linear in position, slerp in rotation.

        A stamp up to `max_extrapolation_s` outside the trajectory's span gets the end pose;
        further out raises GroundTruthError.
        """
        from scipy.spatial.transform import Rotation, Slerp

        stamps_ns, poses = self.stamps_ns, self.poses
        margin_ns = max_extrapolation_s * NS_PER_S
        if not stamps_ns[0] - margin_ns <= stamp_ns <= stamps_ns[-1] + margin_ns:
            raise GroundTruthError(
                f'scan stamp {stamp_ns * 1e-9:.3f} s is outside the ground truth '
                f'({stamps_ns[0] * 1e-9:.3f} .. {stamps_ns[-1] * 1e-9:.3f} s)')
        if len(stamps_ns) == 1:
            return poses[0]
        k = int(np.clip(np.searchsorted(stamps_ns, stamp_ns) - 1, 0, len(stamps_ns) - 2))
        t0, t1 = int(stamps_ns[k]), int(stamps_ns[k + 1])
        a = float(np.clip((stamp_ns - t0) / max(t1 - t0, 1), 0.0, 1.0))
        T = np.eye(4)
        T[:3, 3] = (1.0 - a) * poses[k, :3, 3] + a * poses[k + 1, :3, 3]
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(poses[k:k + 2, :3, :3]))
        T[:3, :3] = slerp([a]).as_matrix()[0]
        return T


class TrajectoryRecorder:
    """Poses appended one at a time into arrays that double as they fill: a day's drive keeps
    136 bytes a pose and no Python object per pose."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        """Forget every pose."""
        self._stamps_ns = np.empty(0, dtype=np.int64)
        self._poses = np.empty((0, 4, 4))
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, stamp_ns: int, pose: np.ndarray) -> None:
        """Add the pose `pose` (4x4) held at `stamp_ns`."""
        if self._n == self._stamps_ns.shape[0]:
            size = max(64, 2 * self._n)
            self._stamps_ns = np.resize(self._stamps_ns, size)
            self._poses = np.resize(self._poses, (size, 4, 4))
        self._stamps_ns[self._n] = stamp_ns
        self._poses[self._n] = pose
        self._n += 1

    def trajectory(self) -> Trajectory:
        """A copy of the poses so far."""
        return Trajectory(self._stamps_ns[:self._n].copy(), self._poses[:self._n].copy())
