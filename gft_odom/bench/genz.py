"""GenZ-ICP (POSTECH, pip package `genz-icp`) behind the same per-scan interface as our pipeline.

Its Python API: `GenZICP(GenZConfig).register_frame(points, timestamps)`. GenZ-ICP ships with
deskew off in every configuration it provides; with it on, its deskew (core/Deskew.cpp) wants
per-point stamps normalised to [0, 1] and moves every point to the sweep's middle
(`mid_pose_timestamp = 0.5`): its ROS node normalises the `time` field as
(t - min) / (max - min), and so do we. Deskewed or not, its pose holds at the middle of the
sweep (a rigid fit of the whole sweep registers to about its mid-sweep pose), so the pose is
stamped `stamp_ns + (min + max) / 2` of the per-point times (half a period without them).

GenZ-ICP keeps its adaptive voxel size in a function-level static shared by every instance of
a process: a second run in one process starts from the first run's last voxel size (it adapts
again within a few scans).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gft_odom.bench.kiss import KissFrame
from gft_odom.config import PipelineConfig
from gft_odom.core.constants import NS_PER_S, SCAN_PERIOD_S
from gft_odom.core.deskew import sweep_middle_offset_s
from gft_odom.core.types import Scan
from gft_odom.errors import ConfigError


@dataclass(frozen=True)
class GenzIcpConfig:
    """GenZ-ICP's own defaults (its `GenZConfig()`), but the crop and the deskew switch."""

    max_range_m: float = 100.0
    # Same crop as our pipeline: the Jackal's body and a walking operator.
    min_range_m: float = PipelineConfig.min_range_m
    # Off in every configuration GenZ-ICP ships; on, with the stamps normalised as it wants.
    deskew: bool = True
    voxel_size_m: float = 0.3
    desired_num_voxelized_points: int = 2000
    planarity_threshold: float = 0.2
    max_points_per_voxel: int = 1
    max_num_iterations: int = 100
    convergence_criterion: float = 1e-4
    initial_threshold_m: float = 2.0
    min_motion_threshold_m: float = 0.1

    def validate(self) -> None:
        """Raise ConfigError naming the first value GenZ-ICP cannot use."""
        for name in ('max_range_m', 'voxel_size_m', 'planarity_threshold',
                     'convergence_criterion', 'initial_threshold_m', 'min_motion_threshold_m'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f'genz-icp {name} must be a finite number > 0, got {value}')
        if not (math.isfinite(self.min_range_m) and 0.0 <= self.min_range_m < self.max_range_m):
            raise ConfigError(f'genz-icp min_range_m must be in [0, max_range_m '
                              f'({self.max_range_m})), got {self.min_range_m}')
        for name in ('desired_num_voxelized_points', 'max_points_per_voxel',
                     'max_num_iterations'):
            if getattr(self, name) < 1:
                raise ConfigError(f'genz-icp {name} must be >= 1, got {getattr(self, name)}')


def genz_icp_version() -> str:
    """Installed genz-icp version, or raise ConfigError with the install line."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version('genz-icp')
    except PackageNotFoundError:
        raise ConfigError('genz-icp is not installed: pip install genz-icp==0.3.2 '
                          "(or pip install -e '.[peers]')") from None


def normalised_times(time_offset_s: np.ndarray) -> np.ndarray:
    """Per-point times mapped to [0, 1] over the sweep, as GenZ-ICP's ROS node does."""
    t = np.asarray(time_offset_s, dtype=np.float64)
    lo, hi = float(np.min(t)), float(np.max(t))
    return (t - lo) / (hi - lo)


class GenzIcpOdometry:
    """One GenZ-ICP odometry instance; `register_frame(scan)` like our pipeline's."""

    def __init__(self, config: GenzIcpConfig = GenzIcpConfig()):
        config.validate()
        self.version = genz_icp_version()
        from genz_icp.config import GenZConfig
        from genz_icp.config.config import (
            AdaptiveThresholdConfig,
            DataConfig,
            MappingConfig,
            RegistrationConfig,
        )
        from genz_icp.genz_icp import GenZICP
        self.config = config
        self.odometry = GenZICP(GenZConfig(
            out_dir='/dev/null',
            data=DataConfig(max_range=config.max_range_m, min_range=config.min_range_m,
                            deskew=config.deskew),
            registration=RegistrationConfig(max_num_iterations=config.max_num_iterations,
                                            convergence_criterion=config.convergence_criterion),
            mapping=MappingConfig(voxel_size=config.voxel_size_m,
                                  desired_num_voxelized_points=(
                                      config.desired_num_voxelized_points),
                                  planarity_threshold=config.planarity_threshold,
                                  max_points_per_voxel=config.max_points_per_voxel),
            adaptive_threshold=AdaptiveThresholdConfig(
                initial_threshold=config.initial_threshold_m,
                min_motion_th=config.min_motion_threshold_m)))

    def register_frame(self, scan: Scan) -> KissFrame:
        """Register one scan with GenZ-ICP; its pose is stamped at mid-sweep."""
        points = np.ascontiguousarray(scan.points_xyz, dtype=np.float64)
        finite = np.isfinite(points).all(axis=1)
        times = scan.time_offset_s
        if times is not None:
            times = np.asarray(times, dtype=np.float64)
            finite &= np.isfinite(times)
            times = times[finite]
        points = points[finite]
        use_times = (self.config.deskew and times is not None and times.size
                     and float(np.max(times)) > float(np.min(times)))
        self.odometry.register_frame(points, normalised_times(times) if use_times
                                     else np.zeros(0))
        mid_s = sweep_middle_offset_s(times, SCAN_PERIOD_S)
        return KissFrame(stamp_ns=int(scan.stamp_ns) + int(round(mid_s * NS_PER_S)),
                         T_world_sensor=np.array(self.odometry.last_pose, dtype=float),
                         n_points_kept=int(points.shape[0]))
