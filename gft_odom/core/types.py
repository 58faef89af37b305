"""Plain data types shared by every layer."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Scan:
    """One LiDAR sweep in the sensor frame.

    `time_offset_s` is the per-point offset within the sweep (velodyne `time` field), None when
    the recording has no such field (CitrusFarm's ROS 1 PointXYZIR layout).
    """

    stamp_ns: int
    points_xyz: np.ndarray  # (N, 3) float64
    intensity: np.ndarray | None = None  # (N,) float32
    ring: np.ndarray | None = None  # (N,) uint16
    time_offset_s: np.ndarray | None = None  # (N,) float32
    frame_id: str = 'velodyne'

    def __len__(self) -> int:
        return int(self.points_xyz.shape[0])

    def select(self, keep: np.ndarray) -> 'Scan':
        """Return the scan restricted to `keep` (boolean mask or index array)."""
        def pick(a):
            return None if a is None else a[keep]
        return Scan(self.stamp_ns, self.points_xyz[keep], pick(self.intensity), pick(self.ring),
                    pick(self.time_offset_s), self.frame_id)
