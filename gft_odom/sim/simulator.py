"""One simulated VLP-16 sweep at a time: poses per firing, ray casting, noise, intensity.

Motion distortion: each firing's ray leaves from the sensor pose at its own time within the
sweep, and each return is reported in the sensor frame of that moment (range times the beam
direction), as a real spinning LiDAR does; the cloud's header stamp is the sweep start and
`time` is the firing's offset from it (0..0.1 s), as the ROS 2 velodyne driver writes. So a
point maps into the world with T_world_velodyne(stamp + time), and de-skewing means expressing
it in the stamp's sensor frame. With distortion off every ray uses the stamp pose and `time` is
0 for every point (the scan is truly instantaneous, so a de-skewing consumer leaves it as is).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from gft_odom.config import NodeConfig
from gft_odom.core.constants import NS_PER_S, SCAN_PERIOD_S
from gft_odom.core.geometry import make_transform, rpy_transform
from gft_odom.core.types import Scan
from gft_odom.errors import ConfigError
from gft_odom.io.ground_truth import GroundTruthConfig
from gft_odom.sim.lidar import SURFACE_REFLECTIVITY, Vlp16Model, cast_rays
from gft_odom.sim.motion import (
    ROUTES,
    RobotMotion,
    make_motion,
    make_route_motion,
    required_row_length_m,
    route_driving,
    route_headland_m,
    route_lane_count,
)
from gft_odom.sim.orchard import Orchard, generate_orchard
from gft_odom.sim.variation import OrchardVariation


@dataclass(frozen=True)
class SimConfig:
    """Knobs of the orchard simulator; defaults model a VLP-16 on a Jackal in a citrus grove."""

    # Orchard size: rows of trees either side of the driven lanes (row length is sized to the
    # requested drive by the scenario).
    n_rows: int = 10
    # Driving speed; ~1 m/s is what CitrusFarm's Jackal drove.
    speed_mps: float = 1.0
    # Skid-steer wander: lateral offset amplitude and yaw oscillation amplitude.
    lateral_wobble_m: float = 0.05
    yaw_wobble_rad: float = 0.02
    # VLP-16: 0.2 deg at 10 Hz (the real sensor; coarser steps only to make tests cheap).
    azimuth_step_deg: float = 0.2
    scan_rate_hz: float = 1.0 / SCAN_PERIOD_S
    min_range_m: float = 0.4
    max_range_m: float = 100.0
    # Datasheet: typical accuracy +-3 cm; a 1-sigma of 2.5 cm matches what people measure.
    range_noise_std_m: float = 0.025
    # Returns lost to dust, wet leaves and weak echoes.
    dropout_probability: float = 0.01
    # Std of multiplicative intensity noise.
    intensity_noise: float = 0.1
    # Crown sway amplitude in a light breeze (each tree gets 50-100 % of it).
    wind_amplitude_m: float = 0.04
    # Mean distance a beam travels inside a crown before a leaf stops it: dense citrus
    # canopies return mostly from their outer ~0.3 m, yet some beams cross thin crown edges.
    canopy_mean_free_path_m: float = 0.35
    motion_distortion: bool = True
    # CitrusFarm's ROS 1 PointXYZIR layout, without the per-point `time` field.
    legacy_fields: bool = False
    # Jackal: base_link -> velodyne, and the GPS antenna in the LiDAR frame (as CitrusFarm):
    # the package defaults, so a simulated bag matches what the node and the tools assume.
    base_to_sensor_xyz_m: tuple[float, ...] = NodeConfig.base_to_sensor_xyz_m
    base_to_sensor_rpy_rad: tuple[float, ...] = NodeConfig.base_to_sensor_rpy_rad
    sensor_to_gps_xyz_m: tuple[float, ...] = GroundTruthConfig.lidar_to_gps_xyz_m
    gps_rate_hz: float = 10.0
    # First sweep stamp (2023-07-22T00:00:00Z, an arbitrary realistic epoch).
    start_time_s: float = 1690000000.0

    def validate(self) -> None:
        """Raise ConfigError naming the first value that cannot work."""
        def positive(name):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f'sim.{name} must be > 0, got {value}')
        for name in ('speed_mps', 'azimuth_step_deg', 'scan_rate_hz', 'max_range_m',
                     'canopy_mean_free_path_m', 'gps_rate_hz'):
            positive(name)
        for name in ('lateral_wobble_m', 'yaw_wobble_rad', 'min_range_m', 'range_noise_std_m',
                     'intensity_noise', 'wind_amplitude_m', 'start_time_s'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ConfigError(f'sim.{name} must be >= 0, got {value}')
        if self.n_rows < 3:
            raise ConfigError(f'sim.n_rows must be >= 3 (the loop needs two lanes), '
                              f'got {self.n_rows}')
        if not self.max_range_m > self.min_range_m:
            raise ConfigError(f'sim.max_range_m ({self.max_range_m}) must be > min_range_m '
                              f'({self.min_range_m})')
        if not 0.0 <= self.dropout_probability < 1.0:
            raise ConfigError(f'sim.dropout_probability must be in [0, 1), '
                              f'got {self.dropout_probability}')
        steps = 360.0 / self.azimuth_step_deg
        if abs(steps - round(steps)) > 1e-6 or round(steps) < 8:
            raise ConfigError(f'sim.azimuth_step_deg must divide 360 into >= 8 columns, '
                              f'got {self.azimuth_step_deg}')
        if self.scan_rate_hz > 50.0 or self.scan_rate_hz < 1.0:
            raise ConfigError(f'sim.scan_rate_hz must be in [1, 50], got {self.scan_rate_hz}')
        for name in ('base_to_sensor_xyz_m', 'base_to_sensor_rpy_rad', 'sensor_to_gps_xyz_m'):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ConfigError(f'sim.{name} must be 3 finite numbers, got {list(value)}')

    def quiet(self) -> 'SimConfig':
        """The same with range noise, dropouts, intensity noise and wind off (exact geometry)."""
        return replace(self, range_noise_std_m=0.0, dropout_probability=0.0,
                       wind_amplitude_m=0.0, intensity_noise=0.0)


@dataclass
class SimScan:
    """A simulated sweep plus what only a simulator knows."""

    scan: Scan
    T_world_sensor: np.ndarray  # (4, 4) at scan.stamp_ns
    surface: np.ndarray  # (N,) int8 surface code per point (see orchard.SURFACE_NAMES)
    primitive: np.ndarray  # (N,) int32 index within its kind, -1 for ground
    seconds: float = 0.0  # wall time spent making it


class ScanSimulator:
    """Makes sweep `k` of a run: stamp = start + k / rate; deterministic per (seed, k)."""

    def __init__(self, orchard: Orchard, motion: RobotMotion, config: SimConfig,
                 seed: int) -> None:
        config.validate()
        self.orchard = orchard
        self.motion = motion
        self.config = config
        self.seed = int(seed)
        self.model = Vlp16Model(config.azimuth_step_deg, config.scan_rate_hz,
                                config.min_range_m, config.max_range_m)
        self.rays = self.model.ray_table()
        self.T_base_sensor = rpy_transform(config.base_to_sensor_xyz_m,
                                           config.base_to_sensor_rpy_rad)
        self.T_sensor_gps = make_transform(translation=np.asarray(config.sensor_to_gps_xyz_m))
        self.start_ns = int(round(config.start_time_s * NS_PER_S))
        self.period_ns = int(round(NS_PER_S / config.scan_rate_hz))

    @classmethod
    def from_config(cls, config: SimConfig, scenario: str = 'row', n_scans: int = 100,
                    seed: int = 0) -> 'ScanSimulator':
        """The orchard of `seed`, sized for `n_scans` sweeps of `scenario`, and its drive:
        exactly what `simulate_to_bag` simulates."""
        config.validate()
        duration_s = (int(n_scans) + 1) / config.scan_rate_hz
        orchard = generate_orchard(seed, n_rows=config.n_rows,
                                   row_length_m=required_row_length_m(
                                       scenario, duration_s * config.speed_mps))
        motion = make_motion(orchard, scenario, duration_s, config.speed_mps, seed,
                             config.lateral_wobble_m, config.yaw_wobble_rad)
        return cls(orchard, motion, config, seed)

    @classmethod
    def for_drive(cls, config: SimConfig, scenario: str, seed: int, n_scans: int | None = None,
                  distance_m: float = 300.0, vary: bool = False, family: str = 'varied'
                  ) -> tuple['ScanSimulator', OrchardVariation | None]:
        """The simulator of one drive, and the variation it was drawn with (None: fixed).

        `scenario` is one of the short scenarios (row, uturn, loop: `n_scans` sweeps) or one
        of the routes (lawnmower, every_other_row, spiral, out_and_back, edge_lawnmower:
        about `distance_m` of driving, the whole route unless `n_scans` cuts it short). `vary`
        draws orchard, terrain, driving, mount and wind from the seed (sim/variation.py); the
        edge route replaces the drawn speeds and turns with its own (motion.route_driving),
        and the variation returned is what was driven. `family` (with `vary`): 'varied', or
        'stress' for drives outside every range of the varied family
        (sim/variation.STRESS_RANGES).
        """
        variation = (route_driving(scenario, OrchardVariation.draw(seed, family)) if vary
                     else None)
        if variation is not None:
            if variation.lateral_wobble_m is not None:
                config = replace(config, lateral_wobble_m=variation.lateral_wobble_m,
                                 yaw_wobble_rad=variation.yaw_wobble_rad)
            config = replace(
                config, speed_mps=variation.cruise_speed_mps,
                canopy_mean_free_path_m=variation.canopy_mean_free_path_m,
                wind_amplitude_m=variation.wind_amplitude_m,
                base_to_sensor_xyz_m=(config.base_to_sensor_xyz_m[0],
                                      config.base_to_sensor_xyz_m[1],
                                      variation.mount_height_m),
                base_to_sensor_rpy_rad=(variation.mount_roll_rad, variation.mount_pitch_rad,
                                        config.base_to_sensor_rpy_rad[2]))
        config.validate()
        if scenario not in ROUTES:
            if n_scans is None:
                raise ConfigError(f'scenario {scenario!r} needs a number of scans')
            if variation is None:
                return cls.from_config(config, scenario, n_scans, seed), None
            duration_s = (int(n_scans) + 1) / config.scan_rate_hz
            row_length_m = required_row_length_m(scenario, duration_s * config.speed_mps)
            orchard = generate_orchard(seed, n_rows=config.n_rows, row_length_m=row_length_m,
                                       variation=variation)
            motion = make_motion(orchard, scenario, duration_s, config.speed_mps, seed,
                                 config.lateral_wobble_m, config.yaw_wobble_rad)
            return cls(orchard, motion, config, seed), variation
        route_variation = variation or route_driving(scenario, OrchardVariation.nominal())
        n_lanes = route_lane_count(scenario, distance_m, route_variation.row_length_m)
        orchard = generate_orchard(seed, n_rows=n_lanes + 2,
                                   row_length_m=route_variation.row_length_m,
                                   variation=variation, headland_m=route_headland_m(scenario))
        motion = make_route_motion(orchard, scenario, n_lanes, route_variation, seed,
                                   config.lateral_wobble_m, config.yaw_wobble_rad)
        return cls(orchard, motion, config, seed), variation

    @property
    def n_scans_in_drive(self) -> int:
        """Sweeps that fit in the drive (the last one ends before the motion does)."""
        return max(1, int(np.floor(self.motion.duration_s * self.config.scan_rate_hz)) - 1)

    def stamp_ns(self, index: int) -> int:
        """Header stamp of sweep `index` (the sweep start)."""
        return self.start_ns + index * self.period_ns

    def sensor_poses(self, t_s: np.ndarray) -> np.ndarray:
        """T_world_sensor (T, 4, 4) at run times `t_s` (seconds since the first stamp)."""
        return self.motion.poses(t_s) @ self.T_base_sensor

    def scan(self, index: int) -> SimScan:
        """Simulate sweep `index` (0-based)."""
        t_wall = time.perf_counter()
        cfg = self.config
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x5CA7, int(index)]))
        t0 = index * self.period_ns / NS_PER_S
        rays = self.rays
        n_col = self.model.n_columns
        T_stamp = self.sensor_poses(np.array([t0]))[0]
        if cfg.motion_distortion:
            col_t = t0 + np.arange(n_col) * (self.model.period_s / n_col)
            T_col = self.sensor_poses(col_t)  # pose per firing column (lasers 2.3 us apart)
            R = T_col[rays['column'], :3, :3]
            origins = T_col[rays['column'], :3, 3]
            directions = np.einsum('nij,nj->ni', R, rays['direction'])
            time_offset = rays['time_offset_s'].astype(np.float32)
        else:
            origins = np.broadcast_to(T_stamp[:3, 3], rays['direction'].shape)
            directions = rays['direction'] @ T_stamp[:3, :3].T
            time_offset = np.zeros(rays['direction'].shape[0], np.float32)
        times = t0 + time_offset.astype(float)  # drives the canopy sway

        hits = cast_rays(self.orchard, origins, directions, times, rng,
                         max_range_m=cfg.max_range_m, min_range_m=cfg.min_range_m,
                         canopy_mean_free_path_m=cfg.canopy_mean_free_path_m,
                         wind_amplitude_m=cfg.wind_amplitude_m)
        measured = hits.range_m + rng.normal(0.0, cfg.range_noise_std_m, hits.range_m.size) \
            if cfg.range_noise_std_m > 0.0 else hits.range_m
        keep = np.isfinite(measured) & (measured >= cfg.min_range_m) & \
            (measured <= cfg.max_range_m)
        if cfg.dropout_probability > 0.0:
            keep &= rng.random(measured.size) >= cfg.dropout_probability
        idx = np.nonzero(keep)[0]
        # The sensor reports each return in its own frame at firing time; labelling them all
        # with the sweep stamp is what makes the cloud motion-distorted.
        points = measured[idx, None] * rays['direction'][idx]

        surface = hits.surface[idx]
        intensity = SURFACE_REFLECTIVITY[surface] * (0.35 + 0.65 * hits.cos_incidence[idx])
        if cfg.intensity_noise > 0.0:
            intensity *= 1.0 + cfg.intensity_noise * rng.standard_normal(idx.size)
        intensity = np.clip(np.round(intensity), 0.0, 255.0).astype(np.float32)

        scan = Scan(stamp_ns=self.stamp_ns(index), points_xyz=points, intensity=intensity,
                    ring=rays['ring'][idx],
                    time_offset_s=None if cfg.legacy_fields else time_offset[idx],
                    frame_id='velodyne')
        return SimScan(scan, T_stamp, surface, hits.primitive[idx],
                       time.perf_counter() - t_wall)
