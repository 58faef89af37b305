"""The registration's parameters: what a user sets (the mode, voxel sizes, the map's extent,
the platform's bounds, the sensor's timing, the covariance's floor); the design's constants
live with the part that uses them.

One source of truth: the node declares its ROS parameters from these fields and the params
files are generated from them (`gft_odom/ros/parameters.py`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gft_odom.core.constants import SCAN_PERIOD_S
from gft_odom.errors import ConfigError

# 'default': our odometry (scan-to-map, deskewed); 'paper': the paper's baseline (each scan
# to the previous one, point-to-point ICP from identity, the transforms chained).
MODES = ('default', 'paper')


@dataclass(frozen=True)
class RegistrationConfig:
    """Parameters of `ScanRegistration`."""

    mode: str = 'default'
    # Source voxel: ~3k of the ~26k points of a VLP-16 orchard scan, plenty for 6 DoF.
    voxel_size_m: float = 0.4
    # Largest point pair ICP accepts: a few voxels, above the worst prediction error at
    # 2 m/s; also the gate of a match's fitness (the share of points with a pair).
    max_correspondence_distance_m: float = 1.0
    max_iterations: int = 30
    # Tukey c of the point-to-plane match: ~4 sigma of canopy sway and range noise.
    robust_kernel_scale_m: float = 0.3
    # The local map: its voxel, its radius around the newest keyframe, its point cap and
    # how many keyframes its window holds (60, 1 m apart: a lane's worth of memory).
    map_voxel_size_m: float = 0.3
    map_max_range_m: float = 40.0
    map_max_points: int = 80000
    map_keyframes: int = 60
    keyframe_distance_m: float = 1.0
    # The platform's bounds (a Clearpath Jackal tops out at 2 m/s): a match implying faster
    # motion is refused, a prediction is capped. Set them to your robot's.
    max_speed_mps: float = 2.0
    max_yaw_rate_rps: float = 4.0
    # A stamp step longer than this is a gap: the velocity is dropped and the next scan is
    # re-acquired against the map.
    max_gap_s: float = 1.0
    # Motion compensation of each sweep (per-point `time`, or the azimuth when the cloud has
    # none). Off for clouds whose sweep is already compensated (config/no_deskew.yaml).
    deskew: bool = True
    scan_period_s: float = SCAN_PERIOD_S
    # Azimuth-derived times only: ROS velodyne drivers stamp with the last packet by default
    # (timestamp_first_packet: false); set true when the bag's header.stamp is the sweep end.
    azimuth_stamp_at_sweep_end: bool = False
    # 1-sigma floor of a match's covariance, and the inflated values of a fallback.
    min_std_m: float = 0.005
    min_std_rad: float = 0.001
    fallback_std_m: float = 1.0
    fallback_std_rad: float = 0.3

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""
        if self.mode not in MODES:
            raise ConfigError(f'mode must be one of {MODES}, got {self.mode!r}')
        for name in ('voxel_size_m', 'max_correspondence_distance_m', 'robust_kernel_scale_m',
                     'map_voxel_size_m', 'map_max_range_m', 'keyframe_distance_m',
                     'max_speed_mps', 'max_yaw_rate_rps', 'max_gap_s', 'scan_period_s',
                     'min_std_m', 'min_std_rad', 'fallback_std_m', 'fallback_std_rad'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f'{name} must be a finite number > 0, got {value}')
        for name, lowest in (('max_iterations', 1), ('map_max_points', 100),
                             ('map_keyframes', 1)):
            if getattr(self, name) < lowest:
                raise ConfigError(f'{name} must be >= {lowest}, got {getattr(self, name)}')
        if self.max_gap_s < self.scan_period_s:
            raise ConfigError(f'max_gap_s ({self.max_gap_s}) must be >= scan_period_s '
                              f'({self.scan_period_s})')
        if self.fallback_std_m < self.min_std_m or self.fallback_std_rad < self.min_std_rad:
            raise ConfigError('fallback_std_m/_rad must be >= min_std_m/_rad '
                              '(a fallback is never more certain than a match)')
