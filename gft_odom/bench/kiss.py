"""kiss-icp (PRBonn, pip package `kiss-icp`) behind the same per-scan interface as our pipeline.

Only its Python API is used: `KissICP(KISSConfig).register_frame(points, timestamps)`. kiss-icp
normalises the per-point timestamps itself ((t - min) / (max - min)) and deskews every point to
the time of the LATEST point of the sweep, so its pose is the sensor pose at the sweep end; the
scan's header stamp (velodyne driver, our simulator) is the sweep start. The pose is therefore
stamped `stamp_ns + max(time)` so that the ground truth is matched at the right time. Without
deskew (or without per-point times) it fits the sweep as one rigid cloud, which holds at the
sweep's middle: stamped there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gft_odom.config import PipelineConfig
from gft_odom.core.constants import NS_PER_S, SCAN_PERIOD_S
from gft_odom.core.deskew import sweep_middle_offset_s
from gft_odom.core.types import Scan
from gft_odom.errors import ConfigError


@dataclass(frozen=True)
class KissIcpConfig:
    """kiss-icp settings for a VLP-16 on a Jackal; each default says where it comes from."""

    # VLP-16 rated range (kiss-icp's own default, too).
    max_range_m: float = 100.0
    # Same crop as our pipeline: the Jackal's body and a walking operator.
    min_range_m: float = PipelineConfig.min_range_m
    # kiss-icp's rule is max_range / 100 (1.0 m at 100 m); the bench's tuning seeds decide.
    voxel_size_m: float = 1.0
    max_points_per_voxel: int = 20
    # VLP-16 clouds carry a per-point `time` field: deskew with it (kiss-icp's default).
    deskew: bool = True
    # 0 = all cores (kiss-icp's default, TBB); our pipeline's open3d uses all cores too.
    max_num_threads: int = 0
    max_num_iterations: int = 500
    convergence_criterion: float = 1e-4
    initial_threshold_m: float = 2.0
    min_motion_threshold_m: float = 0.1

    def validate(self) -> None:
        """Raise ConfigError naming the first value kiss-icp cannot use."""
        for name in ('max_range_m', 'voxel_size_m', 'convergence_criterion',
                     'initial_threshold_m', 'min_motion_threshold_m'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f'kiss-icp {name} must be a finite number > 0, got {value}')
        if not (math.isfinite(self.min_range_m) and 0.0 <= self.min_range_m < self.max_range_m):
            raise ConfigError(f'kiss-icp min_range_m must be in [0, max_range_m '
                              f'({self.max_range_m})), got {self.min_range_m}')
        for name, lowest in (('max_points_per_voxel', 1), ('max_num_iterations', 1),
                             ('max_num_threads', 0)):
            if getattr(self, name) < lowest:
                raise ConfigError(f'kiss-icp {name} must be >= {lowest}, '
                                  f'got {getattr(self, name)}')


def kiss_icp_version() -> str:
    """Installed kiss-icp version, or raise ConfigError with the install line."""
    try:
        from importlib.metadata import PackageNotFoundError, version
        return version('kiss-icp')
    except PackageNotFoundError:
        raise ConfigError('kiss-icp is not installed: pip install kiss-icp') from None


@dataclass
class KissFrame:
    """What one kiss-icp call produced, in the terms the bench records."""

    stamp_ns: int
    T_world_sensor: np.ndarray
    n_points_kept: int


class KissIcpOdometry:
    """One kiss-icp odometry instance; `register_frame(scan)` like our pipeline's."""

    def __init__(self, config: KissIcpConfig = KissIcpConfig()):
        config.validate()
        kiss_icp_version()
        from kiss_icp.config import KISSConfig
        from kiss_icp.config.config import (
            AdaptiveThresholdConfig,
            DataConfig,
            MappingConfig,
            RegistrationConfig,
        )
        from kiss_icp.kiss_icp import KissICP
        self.config = config
        kiss_config = KISSConfig(
            out_dir='/dev/null',
            data=DataConfig(max_range=config.max_range_m, min_range=config.min_range_m,
                            deskew=config.deskew),
            registration=RegistrationConfig(max_num_iterations=config.max_num_iterations,
                                            convergence_criterion=config.convergence_criterion,
                                            max_num_threads=config.max_num_threads),
            mapping=MappingConfig(voxel_size=config.voxel_size_m,
                                  max_points_per_voxel=config.max_points_per_voxel),
            adaptive_threshold=AdaptiveThresholdConfig(
                initial_threshold=config.initial_threshold_m,
                min_motion_th=config.min_motion_threshold_m))
        self.odometry = KissICP(kiss_config)

    def register_frame(self, scan: Scan) -> KissFrame:
        """Register one scan with kiss-icp; its pose is stamped at the sweep end."""
        points = np.ascontiguousarray(scan.points_xyz, dtype=np.float64)
        times = scan.time_offset_s
        use_times = (self.config.deskew and times is not None and len(times)
                     and float(np.max(times)) > float(np.min(times)))
        timestamps = np.asarray(times, dtype=np.float64) if use_times else np.zeros(0)
        frame, _ = self.odometry.register_frame(points, timestamps)
        # Deskewed to the latest point of the sweep: that is when this pose holds; a sweep
        # fitted as one rigid cloud holds at its middle.
        offset_s = (float(np.max(times)) if use_times
                    else sweep_middle_offset_s(times, SCAN_PERIOD_S))
        return KissFrame(stamp_ns=int(scan.stamp_ns) + int(round(offset_s * NS_PER_S)),
                         T_world_sensor=np.array(self.odometry.last_pose, dtype=float),
                         n_points_kept=int(len(frame)))
