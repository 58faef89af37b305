"""Scan registration: ICP on open3d, a constant-velocity motion prior, a local map, fallbacks.

Two modes share one backend so that filtered/unfiltered comparisons are fair:

- `paper`: the paper's baseline. Each scan is registered to the previous scan with
  point-to-point ICP started at identity; the per-scan transforms are chained. No deskew,
  no robust kernel, no map.
- `default`: constant-velocity prediction as the initial guess, scan-to-local-map ICP
  (point-to-plane with a Tukey kernel unless configured otherwise) against a keyframe local
  map, optional deskew (per-point `time`, or the azimuth when the bag has none; off by
  default, see the config). docs/registration.md has the measurements behind these choices.

Registration never raises for bad geometry: too few points, a low fitness, a jump far from
the prediction or a motion no Jackal can make return the prediction with a `fallback_*` status
and an inflated covariance, and the next scan goes on. RegistrationError is raised only for
malformed input.

Motion model: a velocity (rad/s, m/s) from the last trusted match, extrapolated over the real
stamp difference and capped by the physical bounds. Plausibility, the velocity and
re-acquisition are measured from the last trusted pose over the time since it, never from a
fallback's extrapolated one. After a gap (> `max_gap_s`) or
`max_consecutive_fallbacks` fallbacks in a row the velocity is dropped and the next scan is
re-acquired against the local map from a few initial guesses (status `recovered`), so one bad
patch of data cannot make every later prediction miss.

Frames: `T_world_sensor` is the sensor pose at the scan's stamp, world = the sensor frame at the
first registered scan. `covariance` is the (6, 6) uncertainty of this scan's registration
(x, y, z, rot_x, rot_y, rot_z; world axes, about the sensor origin), not accumulated drift.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from gft_odom.core.constants import SCAN_PERIOD_S
from gft_odom.core.deskew import (
    azimuth_time_offsets,
    deskew_points,
    planar_delta,
    twist_from_delta,
)
from gft_odom.core.gauss_newton import GaussNewtonICP, IcpResult
from gft_odom.core.geometry import invert_transform, make_transform, transform_points
from gft_odom.core.local_map import (
    KEYFRAME_EVICTIONS,
    VOXEL_KEEPS,
    LocalMap,
    to_cloud,
    voxel_downsample_indices,
)
from gft_odom.core.residuals import (
    RESIDUAL_MODELS,
    ROUGH_RESIDUALS,
    make_residual_model,
    smoothness_from_nu,
)
from gft_odom.errors import ConfigError, RegistrationError

log = logging.getLogger(__name__)
o3d_reg = o3d.pipelines.registration

MODES = ('default', 'paper')
# What a keyframe adds to the local map: the registration's downsampled points, or the whole
# scan downsampled at the map's voxel (denser, costs a downsample per keyframe).
MAP_POINTS_FROM = ('registration', 'scan')
ESTIMATIONS = ('auto', 'point_to_plane', 'point_to_point', 'gicp')
ROBUST_KERNELS = ('none', 'tukey', 'huber', 'cauchy')
SOLVERS = ('open3d', 'gauss_newton')
VOXEL_PRIORITIES = ('first', 'smoothest')
# Every status `register` / `advance_with_prediction` can return.
STATUSES = ('first', 'ok', 'recovered', 'fallback_too_few_points', 'fallback_low_fitness',
            'fallback_diverged', 'fallback_implausible', 'fallback_degenerate')
# Re-acquisition's fine ICP may iterate this many times longer than a normal match.
RECOVERY_ITERATIONS_FACTOR = 4
# Matches whose median fitness min_relative_fitness refers to (and the fewest it needs).
RECENT_FITNESS_WINDOW = 10
RECENT_FITNESS_MIN = 3
# Poses trusted enough to update the velocity and the reference (map or previous scan).
TRUSTED_STATUSES = ('first', 'ok', 'recovered')
# Failed matches from the prediction that `retry_failed_match` re-acquires at once.
RETRIED_STATUSES = ('fallback_low_fitness', 'fallback_diverged', 'fallback_implausible')


@dataclass(frozen=True)
class RegistrationConfig:
    """Parameters of ScanRegistration; defaults chosen by benchmarks/bench_registration.py."""

    # 'default' (our design) or 'paper' (scan-to-scan point-to-point ICP from identity).
    mode: str = 'default'
    # 'auto' = point_to_point in paper mode (as the paper), point_to_plane in default mode.
    estimation: str = 'auto'
    # Source voxel: ~3k of the ~26k points of a VLP-16 orchard scan, plenty for 6 DoF.
    voxel_size_m: float = 0.4
    # Largest point pair ICP accepts: a few voxels, above the worst prediction error at 2 m/s.
    max_correspondence_distance_m: float = 1.0
    max_iterations: int = 30
    # Stop when the relative fitness and rmse changes fall below this: 1e-4 gave the same ATE
    # as 1e-6 on the simulated drives at half the ICP time.
    convergence_relative: float = 1e-4
    # Robust kernel of point_to_plane and gicp in default mode (point_to_point has none).
    robust_kernel: str = 'tukey'
    # Tukey c: residuals beyond it get zero weight; ~4 sigma of canopy sway + range noise.
    robust_kernel_scale_m: float = 0.3
    # GICP covariance regulariser (open3d epsilon).
    gicp_epsilon: float = 1e-3
    # Local map (default mode): voxel, radius around the newest keyframe, hard point cap.
    # 60 keyframes, not 15: on the four long varied training drives (docs/benchmarks.md) a
    # 15 m memory drifted (mean ATE 0.222 m over ~230 m); 60 more than halved it (0.101 m).
    map_voxel_size_m: float = 0.3
    map_max_range_m: float = 40.0
    map_max_points: int = 80000
    map_keyframes: int = 60
    # Which keyframe a full map drops: 'oldest' (a window in time) or 'farthest' from the
    # newest keyframe (a window in space, as kiss-icp's range-cropped voxel map). 'farthest'
    # with 1 rad rotation keyframes helped on three training drives and lost track on the
    # fourth (1.38 m ATE, 49 fallbacks), so the default stays 'oldest'.
    map_keyframe_eviction: str = 'oldest'
    # What a keyframe adds: the registration's downsampled points, or the whole scan at the
    # map voxel ('scan': denser, a downsample per keyframe). Studied, not the default.
    map_points_from: str = 'registration'
    # Which point a voxel seen by several keyframes keeps. 'oldest': the map stays anchored
    # to what was seen first instead of following each new keyframe's small error (GenZ-ICP
    # and kiss-icp never replace a filled voxel either). With retry_failed_match: mean ATE
    # 0.097 -> 0.070 m on the seven training drives (docs/benchmarks.md, round 3).
    map_voxel_keeps: str = 'oldest'
    # Anchors: when a keyframe leaves the window, its points of smoothness >= this (the
    # graph frequency nu / smooth_nu: ground, trunks, posts) stay in the map while within
    # map_max_range_m; canopy, which looks different from another row, leaves with it.
    # Without frequencies (--no-filter) nothing is anchored.
    map_anchors: bool = False
    map_anchor_smoothness: float = 0.75
    keyframe_distance_m: float = 1.0
    keyframe_rotation_rad: float = 0.2
    normal_neighbours: int = 15
    # Below this many downsampled points ICP is not attempted.
    min_points: int = 100
    # open3d fitness = inlier pairs / source points; below it the result is not trusted.
    min_fitness: float = 0.3
    # Default mode: a fitness below this fraction of the median of the last matches is not
    # trusted either. Scan-to-map fitness is steady (0.8-0.97 on the simulated drives); a
    # copy of a scan rotated 90 deg still reached 0.48 near the prediction, enough for
    # min_fitness, and would have entered the map at a keyframe.
    min_relative_fitness: float = 0.7
    # Largest correction to the constant-velocity prediction per scan period: a Jackal
    # (2 m/s, ~2 rad/s top speed) cannot change its velocity by more within 0.1 s.
    max_translation_jump_m: float = 0.5
    max_rotation_jump_rad: float = 0.25
    # Physical bounds: a Clearpath Jackal tops out at 2.0 m/s. The rotation bound applies to
    # the whole rotation angle (yaw dominates on a ground robot; bumps add roll and pitch).
    # A registration implying faster motion over the real stamp difference is rejected
    # (`fallback_implausible`, never enters the map); predictions are capped by the same.
    max_speed_mps: float = 2.0
    max_yaw_rate_rps: float = 4.0
    # Relative slack on both bounds for stamp jitter and ICP noise over short steps; a copy
    # of a scan rotated 90 deg 30 ms later implies 52 rad/s, far beyond it.
    motion_margin: float = 0.5
    # A stamp step longer than this is a gap: the velocity is not extrapolated over it and the
    # scan is re-acquired against the map (zero motion and last velocity as initial guesses).
    max_gap_s: float = 1.0
    # This many fallbacks in a row drop the velocity and re-acquire the same way.
    max_consecutive_fallbacks: int = 3
    # A match from the prediction that fails (low fitness, diverged, implausible) is tried
    # again at once the way re-acquisition does (several guesses, coarse then fine ICP),
    # and kept as `recovered` if that passes the fitness checks and the bounds. At the start
    # of a pivot the yaw rate jumps within a scan and ICP from the prediction can slide
    # along the row (0.45 m at fitness 0.90 on training drive every_other_row-118).
    retry_failed_match: bool = True
    # Re-acquisition runs a coarse ICP with the correspondence distance widened by this
    # factor from each guess, then the normal ICP; the best plausible fit wins.
    recovery_correspondence_factor: float = 3.0
    # The solver of default mode: 'open3d' (its ICP: one residual type for every pair) or
    # 'gauss_newton' (core/gauss_newton.py: a residual type and weight per pair, set by
    # residual_model). Paper mode always uses open3d's point-to-point ICP.
    solver: str = 'open3d'
    # Gauss-Newton only (core/residuals.py): 'plane' (every pair point-to-plane, weight 1),
    # 'frequency' (the scan point's graph frequency decides: smooth -> plane, rough -> the
    # rough residual), 'planarity' (the map neighbourhood's covariance decides, GenZ-ICP-style).
    residual_model: str = 'plane'
    # What rough points contribute: 'beam_perpendicular' (point-to-point across the beam
    # only: canopy returns sit at random depths along it) or 'point' (GenZ-ICP's).
    rough_residual: str = 'beam_perpendicular'
    rough_weight: float = 1.0
    # 'frequency': smoothness = nu / smooth_nu clipped to [0, 1] (ground and trunks ~0.5,
    # canopy ~0 on the scan-line graph).
    smooth_nu: float = 0.4
    # 'planarity': smoothness = 1 - surface variation / this (a plane 0, a blob 1/3).
    rough_surface_variation: float = 0.1
    # Which point of a source voxel registration uses (and a keyframe adds to the map):
    # 'first' (in scan order) or 'smoothest' (the highest graph frequency nu: a ground or
    # trunk return is preferred to a canopy return of the same voxel; needs nu).
    voxel_priority: str = 'first'
    # Gauss-Newton stops when the update's norm (m, rad) falls below this.
    convergence_m: float = 1e-4
    # Gauss-Newton: match like with like. The map remembers each point's smoothness (its
    # scan point's nu / smooth_nu), and a scan point picks, among its nearest map points,
    # the one nearest once a smoothness mismatch d counts as affinity_m * d of distance:
    # canopy pairs with canopy, ground and trunks with their own surface. 0: distance alone
    # (also what --no-filter gives: no frequencies, nothing to compare).
    frequency_affinity_m: float = 0.0
    # Motion compensation (default mode only). An undeskewed sweep registers to about its
    # mid-sweep pose, ~50 ms after the stamp it is published with; the evaluation of before
    # (GPS paired by nearest stamp, 37 ms after the scan) hid that and deskew looked mixed.
    # With the GPS interpolated at the stamps, deskew took the training drives
    # lawnmower-111 / every_other_row-113 / every_other_row-118 from 0.080 / 0.082 / 0.124 m
    # to 0.056 / 0.031 / 0.158 m ATE, and let 5 of 9 mirrored copies of a row scan be trusted
    # (the fault suite allows 4), so it stays off by default (docs/registration.md).
    deskew: bool = False
    # Deskew with forward motion and yaw rate only (ground robot); false: full 6-DoF twist.
    deskew_planar: bool = True
    # Deskew velocity = mean twist of the last this many trusted scans (ICP noise averages out).
    deskew_velocity_window: int = 5
    scan_period_s: float = SCAN_PERIOD_S
    # Azimuth-derived times only: ROS velodyne drivers stamp with the last packet by default
    # (timestamp_first_packet: false); set true when the bag's header.stamp is the sweep end.
    azimuth_stamp_at_sweep_end: bool = False
    # Return the full-resolution deskewed scan in the result (costs ~2 ms for 30k points).
    output_deskewed_points: bool = False
    # 1-sigma floor of an accepted registration and the inflated values of a fallback.
    min_std_m: float = 0.005
    min_std_rad: float = 0.001
    fallback_std_m: float = 1.0
    fallback_std_rad: float = 0.3

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""
        if self.mode not in MODES:
            raise ConfigError(f'mode must be one of {MODES}, got {self.mode!r}')
        if self.estimation not in ESTIMATIONS:
            raise ConfigError(f'estimation must be one of {ESTIMATIONS}, got {self.estimation!r}')
        if self.map_keyframe_eviction not in KEYFRAME_EVICTIONS:
            raise ConfigError(f'map_keyframe_eviction must be one of {KEYFRAME_EVICTIONS}, '
                              f'got {self.map_keyframe_eviction!r}')
        if self.map_voxel_keeps not in VOXEL_KEEPS:
            raise ConfigError(f'map_voxel_keeps must be one of {VOXEL_KEEPS}, '
                              f'got {self.map_voxel_keeps!r}')
        if self.map_points_from not in MAP_POINTS_FROM:
            raise ConfigError(f'map_points_from must be one of {MAP_POINTS_FROM}, '
                              f'got {self.map_points_from!r}')
        if self.voxel_priority not in VOXEL_PRIORITIES:
            raise ConfigError(f'voxel_priority must be one of {VOXEL_PRIORITIES}, '
                              f'got {self.voxel_priority!r}')
        if self.solver not in SOLVERS:
            raise ConfigError(f'solver must be one of {SOLVERS}, got {self.solver!r}')
        if self.residual_model not in RESIDUAL_MODELS:
            raise ConfigError(f'residual_model must be one of {RESIDUAL_MODELS}, '
                              f'got {self.residual_model!r}')
        if self.rough_residual not in ROUGH_RESIDUALS:
            raise ConfigError(f'rough_residual must be one of {ROUGH_RESIDUALS}, '
                              f'got {self.rough_residual!r}')
        if self.residual_model != 'plane' and self.solver != 'gauss_newton':
            raise ConfigError(f"residual_model {self.residual_model!r} needs solver "
                              f"'gauss_newton' (open3d's ICP has one residual type)")
        if not (math.isfinite(self.frequency_affinity_m) and self.frequency_affinity_m >= 0.0):
            raise ConfigError(f'frequency_affinity_m must be a finite number >= 0, '
                              f'got {self.frequency_affinity_m}')
        if self.frequency_affinity_m > 0.0 and self.solver != 'gauss_newton':
            raise ConfigError("frequency_affinity_m needs solver 'gauss_newton' (open3d's "
                              "ICP pairs by distance alone)")
        if not (math.isfinite(self.rough_weight) and self.rough_weight >= 0.0):
            raise ConfigError(f'rough_weight must be a finite number >= 0, '
                              f'got {self.rough_weight}')
        if self.robust_kernel not in ROBUST_KERNELS:
            raise ConfigError(
                f'robust_kernel must be one of {ROBUST_KERNELS}, got {self.robust_kernel!r}')
        positive = ('voxel_size_m', 'max_correspondence_distance_m', 'robust_kernel_scale_m',
                    'gicp_epsilon', 'map_voxel_size_m', 'map_max_range_m',
                    'keyframe_distance_m', 'keyframe_rotation_rad', 'max_translation_jump_m',
                    'max_rotation_jump_rad', 'scan_period_s', 'convergence_relative',
                    'min_std_m', 'min_std_rad', 'fallback_std_m', 'fallback_std_rad',
                    'max_speed_mps', 'max_yaw_rate_rps', 'max_gap_s', 'smooth_nu',
                    'rough_surface_variation', 'convergence_m')
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f'{name} must be a finite number > 0, got {value}')
        minimum = {'max_iterations': 1, 'map_max_points': 100, 'map_keyframes': 1,
                   'normal_neighbours': 5, 'min_points': 3, 'max_consecutive_fallbacks': 1,
                   'deskew_velocity_window': 1}
        for name, lowest in minimum.items():
            if getattr(self, name) < lowest:
                raise ConfigError(f'{name} must be >= {lowest}, got {getattr(self, name)}')
        for name in ('min_fitness', 'min_relative_fitness', 'map_anchor_smoothness'):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f'{name} must be in [0, 1], got {getattr(self, name)}')
        if not (math.isfinite(self.motion_margin) and self.motion_margin >= 0.0):
            raise ConfigError(f'motion_margin must be a finite number >= 0, got '
                              f'{self.motion_margin}')
        if not (math.isfinite(self.recovery_correspondence_factor)
                and self.recovery_correspondence_factor >= 1.0):
            raise ConfigError(f'recovery_correspondence_factor must be >= 1, got '
                              f'{self.recovery_correspondence_factor}')
        if self.max_gap_s < self.scan_period_s:
            raise ConfigError(f'max_gap_s ({self.max_gap_s}) must be >= scan_period_s '
                              f'({self.scan_period_s})')
        if self.fallback_std_m < self.min_std_m or self.fallback_std_rad < self.min_std_rad:
            raise ConfigError('fallback_std_m/_rad must be >= min_std_m/_rad '
                              '(a fallback is never more certain than a match)')

    @property
    def resolved_estimation(self) -> str:
        """The estimator 'auto' stands for in this mode."""
        if self.estimation != 'auto':
            return self.estimation
        return 'point_to_point' if self.mode == 'paper' else 'point_to_plane'


@dataclass
class RegistrationResult:
    """Outcome of one scan: pose, increment, match quality, health, timings."""

    T_world_sensor: np.ndarray  # (4, 4) sensor pose at the stamp
    T_prev_curr: np.ndarray  # (4, 4) motion since the previous scan
    fitness: float  # inlier pairs / source points (open3d), 0 when not matched
    inlier_rmse_m: float
    n_points_used: int  # downsampled source points
    status: str  # one of STATUSES
    covariance: np.ndarray  # (6, 6), inflated on fallback
    timings_s: dict[str, float] = field(default_factory=dict)
    deskewed_points: np.ndarray | None = None  # (N, 3) sensor frame at the stamp
    # (rot_x, rot_y, rot_z, v_x, v_y, v_z) rad/s, m/s in the sensor frame at the stamp: the
    # motion model's velocity after this scan (zeros when unknown, e.g. after a loss).
    twist: np.ndarray = field(default_factory=lambda: np.zeros(6))
    # (6, 6) Gauss-Newton information of the match (x, y, z, rot_x, rot_y, rot_z; the same
    # axes as `covariance`), None on a fallback: its small eigenvalues are weak directions.
    information: np.ndarray | None = None
    # The speed (m/s) and rotation rate (rad/s) a match refused as implausible implied, since
    # the last trusted pose; None unless status is fallback_implausible from the match.
    refused_speed_mps: float | None = None
    refused_rate_rps: float | None = None

    @property
    def fell_back(self) -> bool:
        """True when ICP was not trusted and the prediction was used."""
        return self.status.startswith('fallback')


def scale_delta(T: np.ndarray, factor: float) -> np.ndarray:
    """The rigid motion `T` extrapolated to `factor` times its duration (constant twist)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(
        Rotation.from_matrix(T[:3, :3]).as_rotvec() * factor).as_matrix()
    out[:3, 3] = T[:3, 3] * factor
    return out


def twist_of(T_prev_curr: np.ndarray, dt_s: float) -> np.ndarray:
    """(rot_x, rot_y, rot_z, v_x, v_y, v_z) in rad/s and m/s of a motion lasting `dt_s`."""
    omega, velocity = twist_from_delta(T_prev_curr, dt_s)
    return np.r_[omega, velocity]


def transform_magnitude(T: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation angle rad) of a rigid transform."""
    cos_angle = np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(T[:3, 3])), float(np.arccos(cos_angle))


def _kernel(name: str, scale_m: float):
    if name == 'tukey':
        return o3d_reg.TukeyLoss(scale_m)
    if name == 'huber':
        return o3d_reg.HuberLoss(scale_m)
    if name == 'cauchy':
        return o3d_reg.CauchyLoss(scale_m)
    return o3d_reg.L2Loss()


def local_map_from_config(cfg: RegistrationConfig) -> LocalMap:
    """The local map of default mode, from the `map_*` / keyframe fields."""
    return LocalMap(
        voxel_size_m=cfg.map_voxel_size_m, max_range_m=cfg.map_max_range_m,
        max_points=cfg.map_max_points, max_keyframes=cfg.map_keyframes,
        keyframe_distance_m=cfg.keyframe_distance_m,
        keyframe_rotation_rad=cfg.keyframe_rotation_rad,
        normal_neighbours=cfg.normal_neighbours, eviction=cfg.map_keyframe_eviction,
        voxel_keeps=cfg.map_voxel_keeps,
        anchor_smoothness=cfg.map_anchor_smoothness if cfg.map_anchors else None)


def in_world_axes(matrix_6x6: np.ndarray, R_world_target: np.ndarray) -> np.ndarray:
    """A (6, 6) covariance or information of (translation, rotation) moved to world axes."""
    rotate = np.zeros((6, 6))
    rotate[:3, :3] = rotate[3:, 3:] = R_world_target
    return rotate @ matrix_6x6 @ rotate.T


def delta_of_twist(twist: np.ndarray, dt_s: float) -> np.ndarray:
    """The rigid motion of a constant twist (rot rad/s, lin m/s) lasting `dt_s`."""
    return make_transform(Rotation.from_rotvec(twist[:3] * dt_s).as_matrix(), twist[3:] * dt_s)


class ScanRegistration:
    """Registers consecutive scans and keeps the odometry state (pose, velocity, local map)."""

    def __init__(self, config: RegistrationConfig = RegistrationConfig()):
        config.validate()
        self.config = config
        self.mode = config.mode
        self.estimation = config.resolved_estimation
        self.criteria = o3d_reg.ICPConvergenceCriteria(
            relative_fitness=config.convergence_relative,
            relative_rmse=config.convergence_relative, max_iteration=config.max_iterations)
        # Re-acquisition starts further away: more iterations to converge.
        self._recovery_criteria = o3d_reg.ICPConvergenceCriteria(
            relative_fitness=config.convergence_relative,
            relative_rmse=config.convergence_relative,
            max_iteration=RECOVERY_ITERATIONS_FACTOR * config.max_iterations)
        # The paper's ICP is plain least squares; ours is robust.
        kernel_name = 'none' if config.mode == 'paper' else config.robust_kernel
        self.kernel = _kernel(kernel_name, config.robust_kernel_scale_m)
        self.local_map = local_map_from_config(config)
        self.local_map.with_normals = self.estimation == 'point_to_plane'
        self.local_map.with_covariances = self.estimation == 'gicp'
        # Gauss-Newton (default mode): per-pair residual types and weights.
        self.solver = None
        if config.solver == 'gauss_newton' and config.mode == 'default':
            self.solver = GaussNewtonICP(
                make_residual_model(config.residual_model, config.rough_residual,
                                    config.rough_weight),
                config.robust_kernel, config.robust_kernel_scale_m, config.max_iterations,
                config.convergence_m, config.frequency_affinity_m)
            self.local_map.with_normals = True
            if config.residual_model == 'planarity':
                self.local_map.smoothness_variation = config.rough_surface_variation
                self.local_map.with_covariances = True  # computed once per map rebuild
        # Smoothness of this scan's downsampled points (residual_model 'frequency'), and the
        # same with unknown kept NaN, what the map remembers (frequency_affinity_m, anchors).
        self._source_smoothness: np.ndarray | None = None
        self._point_smoothness: np.ndarray | None = None
        self.deskew = config.deskew and config.mode == 'default'
        self.min_var = np.array([config.min_std_m ** 2] * 3 + [config.min_std_rad ** 2] * 3)
        self.fallback_var = np.array(
            [config.fallback_std_m ** 2] * 3 + [config.fallback_std_rad ** 2] * 3)
        self.reset()

    @classmethod
    def from_config(cls, cfg: RegistrationConfig) -> 'ScanRegistration':
        """Same as the constructor (kept for the callers that name it)."""
        return cls(cfg)

    def reset(self) -> None:
        """Forget everything: the next scan is the first again."""
        self.T_world_sensor = np.eye(4)
        # The last trusted pose and its stamp: fallbacks only extrapolate, so plausibility
        # and re-acquisition are measured from here, over the time since it.
        self.T_world_trusted = np.eye(4)
        self.trusted_stamp_ns: int | None = None
        # (rot_x, rot_y, rot_z, v_x, v_y, v_z) in rad/s, m/s, previous sensor axes.
        self.velocity = np.zeros(6)
        self._twists: deque[np.ndarray] = deque(maxlen=self.config.deskew_velocity_window)
        self._fitness: deque[float] = deque(maxlen=RECENT_FITNESS_WINDOW)  # trusted matches
        self.last_stamp_ns: int | None = None
        self.n_registered = 0
        self.n_fallbacks = 0
        self.consecutive_fallbacks = 0
        # Re-acquiring after a gap or a run of fallbacks; the velocity before the loss.
        self.recovering = False
        self._velocity_before_loss = np.zeros(6)
        self._prev_scan: o3d.geometry.PointCloud | None = None  # paper mode's target
        self.local_map.clear()
        self._map_provisional = False

    @property
    def has_reference(self) -> bool:
        """A map (default) or a previous scan (paper) to register against."""
        if self.mode == 'paper':
            return self._prev_scan is not None
        return len(self.local_map) > 0

    def capped(self, twist: np.ndarray) -> np.ndarray:
        """`twist` scaled down (direction kept) to the speed and rotation-rate bounds."""
        cfg = self.config
        out = np.array(twist, dtype=float)
        for part, bound in ((slice(0, 3), cfg.max_yaw_rate_rps), (slice(3, 6), cfg.max_speed_mps)):
            norm = float(np.linalg.norm(out[part]))
            if norm > bound:
                out[part] *= bound / norm
        return out

    def predicted_delta(self, dt_s: float) -> np.ndarray:
        """T_prev_curr the motion model expects `dt_s` after the last scan (none if <= 0)."""
        return delta_of_twist(self.velocity, dt_s) if dt_s > 0.0 else np.eye(4)

    def is_plausible(self, T_prev_curr: np.ndarray, dt_s: float) -> bool:
        """Could the robot have made this motion in `dt_s` (bounds times 1 + margin)?"""
        cfg = self.config
        distance_m, angle_rad = transform_magnitude(T_prev_curr)
        slack = (1.0 + cfg.motion_margin) * max(dt_s, 0.0)
        # What the motion implies, for a caller that reports a refusal (the bounds watch).
        self.last_implied_rates = ((distance_m / dt_s, angle_rad / dt_s) if dt_s > 0.0
                                   else (float('inf'), float('inf')))
        return (distance_m <= cfg.max_speed_mps * slack
                and angle_rad <= cfg.max_yaw_rate_rps * slack)

    def _since_trusted(self, stamp_ns: int, T_world_est: np.ndarray) -> tuple[np.ndarray, float]:
        """The motion from the last trusted pose to `T_world_est` and the time it took (the
        previous scan's unless registrations fell back since). A stamp not after the trusted
        one (the API tolerates it, the pipeline refuses it) is measured from the previous pose
        over the stamp step, as before the trusted pose existed."""
        if self.trusted_stamp_ns is None or int(stamp_ns) <= self.trusted_stamp_ns:
            dt_s = (self.config.scan_period_s if self.last_stamp_ns is None
                    else (int(stamp_ns) - self.last_stamp_ns) * 1e-9)
            return invert_transform(self.T_world_sensor) @ T_world_est, dt_s
        return (invert_transform(self.T_world_trusted) @ T_world_est,
                (int(stamp_ns) - self.trusted_stamp_ns) * 1e-9)

    def _scan_motion(self, stamp_ns: int, T_world_new: np.ndarray, dt_s: float) -> np.ndarray:
        """The motion over this scan's `dt_s` that deskew assumes: the mean motion since the
        last trusted pose, so a pose recovered after fallbacks is not read as one jump."""
        motion, elapsed_s = self._since_trusted(stamp_ns, T_world_new)
        if not elapsed_s > 0.0:
            return invert_transform(self.T_world_sensor) @ T_world_new
        return delta_of_twist(twist_of(motion, elapsed_s), dt_s)

    def _step_s(self, stamp_ns: int) -> float:
        if self.last_stamp_ns is None:
            return self.config.scan_period_s
        dt_s = (int(stamp_ns) - self.last_stamp_ns) * 1e-9
        if not dt_s > 0.0:
            log.warning('scan stamp %d is not after the previous one (%d): predicting no motion',
                        stamp_ns, self.last_stamp_ns)
        return dt_s

    def _lose_track(self, why: str) -> None:
        """Stop extrapolating the velocity; re-acquire the next scan against the map."""
        if not self.recovering:
            log.info('re-acquiring against the map: %s', why)
            self._velocity_before_loss = self.velocity.copy()
        self.recovering = True
        self.velocity = np.zeros(6)
        self._twists.clear()

    def _begin(self, stamp_ns: int) -> tuple[float, np.ndarray]:
        """Time step since the last scan and the predicted pose (a gap drops the velocity)."""
        dt_s = self._step_s(stamp_ns)
        if self.n_registered and dt_s > self.config.max_gap_s and self.mode == 'default':
            self._lose_track(f'gap of {dt_s:.2f} s in the scan stamps')
        return dt_s, self.T_world_sensor @ self.predicted_delta(dt_s)

    def advance_with_prediction(self, stamp_ns: int,
                                status: str = 'fallback_degenerate') -> RegistrationResult:
        """Take the motion prediction as the pose at `stamp_ns` without matching anything:
        for scans the caller knows ICP cannot observe (a flat cloud). Counted as a fallback."""
        if status not in STATUSES or not status.startswith('fallback'):
            raise RegistrationError(f'advance_with_prediction needs a fallback status from '
                                    f'{STATUSES}, got {status!r}')
        t_start = time.perf_counter()
        dt_s, T_pred = self._begin(stamp_ns)
        return self._finish(stamp_ns, dt_s, status, T_pred, 0, t_start, {})

    def register(self, points_xyz: np.ndarray, stamp_ns: int,
                 time_offset_s: np.ndarray | None = None,
                 nu: np.ndarray | None = None) -> RegistrationResult:
        """Register one scan (sensor frame, any number of points) and update the state.

        `nu` (N,): every point's graph frequency (NaN: none), read by residual_model
        'frequency'; without it every pair is weighted alike."""
        points_xyz, time_offset_s, nu = self._check_input(points_xyz, time_offset_s, nu)
        timings: dict[str, float] = {}
        t_start = time.perf_counter()

        # 1. Velocity prediction over the real stamp difference, capped by the bounds.
        dt_s, T_pred = self._begin(stamp_ns)

        # 2. Downsample (first point per voxel keeps its time), then deskew those points.
        t0 = time.perf_counter()
        priority = nu if self.config.voxel_priority == 'smoothest' else None
        keep = voxel_downsample_indices(points_xyz, self.config.voxel_size_m, priority)
        source_xyz = points_xyz[keep]
        self._source_smoothness = (
            smoothness_from_nu(nu[keep], self.config.smooth_nu)
            if nu is not None and self.config.residual_model == 'frequency' else None)
        remembered = nu is not None and (self.config.map_anchors or (
            self.solver is not None and self.config.frequency_affinity_m > 0.0))
        self._point_smoothness = (smoothness_from_nu(nu[keep], self.config.smooth_nu,
                                                     unknown=np.nan) if remembered else None)
        timings['downsample'] = time.perf_counter() - t0
        t0 = time.perf_counter()
        offsets_s = None
        if self.deskew and source_xyz.shape[0]:
            offsets_s = self._time_offsets(points_xyz, time_offset_s)
            source_xyz = deskew_points(source_xyz, offsets_s[keep], self._deskew_motion(dt_s),
                                       dt_s)
        timings['deskew'] = time.perf_counter() - t0

        # 3. Decide: first scan, too few points, re-acquisition or ICP against the reference.
        n_used = int(source_xyz.shape[0])
        match = None
        refused = (None, None)  # the rates a match refused as implausible implied
        if n_used < self.config.min_points:
            status, T_new = 'fallback_too_few_points', T_pred
            if not self.has_reference:
                log.warning('scan %d has %d points after downsampling (< min_points %d) and '
                            'there is no reference yet', stamp_ns, n_used,
                            self.config.min_points)
        elif not self.has_reference:
            status, T_new = 'first', (T_pred if self.n_registered else np.eye(4))
        else:
            t0 = time.perf_counter()
            if self.recovering and self.mode == 'default':
                match = self._reacquire(source_xyz, T_pred, stamp_ns)
            else:
                self.last_implied_rates = (None, None)  # set by is_plausible in the match
                match = self._match(source_xyz, T_pred, stamp_ns)
                refused = (self.last_implied_rates if match[0] == 'fallback_implausible'
                           else (None, None))
                if (match[0] in RETRIED_STATUSES and self.mode == 'default'
                        and self.config.retry_failed_match):
                    retried = self._reacquire(source_xyz, T_pred, stamp_ns, retry=True)
                    match = retried if retried[0] == 'recovered' else match
            status, T_new = match[0], match[1]
            timings['icp'] = time.perf_counter() - t0

        # 4. Re-deskew a trusted scan with its own motion: the map gets the better cloud.
        # This scan's motion, as deskew assumes it (before _finish moves the trusted pose);
        # only worked out when the scan is deskewed (offsets_s is set only then).
        T_prev_curr = (self._scan_motion(stamp_ns, T_new, dt_s)
                       if offsets_s is not None and status in ('ok', 'recovered')
                       and dt_s > 0.0 else None)
        redeskew = T_prev_curr is not None
        if redeskew:
            source_xyz = deskew_points(points_xyz[keep], offsets_s[keep],
                                       self._deskew_motion(dt_s, T_prev_curr), dt_s)

        def keyframe_xyz() -> tuple[np.ndarray, np.ndarray | None]:
            """The points a keyframe adds, and their smoothness when the map keeps it."""
            if self.config.map_points_from == 'registration' or source_xyz.shape[0] == 0:
                return source_xyz, self._point_smoothness
            dense = voxel_downsample_indices(points_xyz, self.config.map_voxel_size_m)
            smooth = (None if self._point_smoothness is None else smoothness_from_nu(
                nu[dense], self.config.smooth_nu, unknown=np.nan))
            if not redeskew:
                return points_xyz[dense], smooth
            return deskew_points(points_xyz[dense], offsets_s[dense],
                                 self._deskew_motion(dt_s, T_prev_curr), dt_s), smooth
        result = self._finish(stamp_ns, dt_s, status, T_new, n_used, t_start, timings,
                              source_xyz, match, keyframe_xyz)
        if status == 'fallback_implausible':
            result.refused_speed_mps, result.refused_rate_rps = refused
        if self.config.output_deskewed_points:
            result.deskewed_points = points_xyz.copy() if offsets_s is None else deskew_points(
                points_xyz, offsets_s,
                self._deskew_motion(dt_s, T_prev_curr), dt_s)
        return result

    def _finish(self, stamp_ns: int, dt_s: float, status: str, T_new: np.ndarray, n_used: int,
                t_start: float, timings: dict[str, float],
                source_xyz: np.ndarray | None = None, match=None,
                keyframe_xyz=None) -> RegistrationResult:
        """Update pose, velocity, fallback run and reference; build the result."""
        t0 = time.perf_counter()
        fitness, rmse, information = (match[2], match[3], match[4]) if match else (0.0, 0.0, None)
        # Axes the ICP information is expressed in: world (map) or the previous scan (paper).
        R_world_target = self.T_world_trusted[:3, :3] if self.mode == 'paper' else np.eye(3)
        T_prev_curr = invert_transform(self.T_world_sensor) @ T_new
        if status in TRUSTED_STATUSES:
            # The velocity spans the motion since the last trusted pose: after fallbacks the
            # previous pose was extrapolated, and its error is not this scan's motion.
            motion, elapsed_s = self._since_trusted(stamp_ns, T_new)
            self.T_world_trusted = T_new.copy()
            self.trusted_stamp_ns = int(stamp_ns)
            self._update_reference(source_xyz, T_new, status, keyframe_xyz)
            if match is not None:
                self._fitness.append(fitness)
            self.consecutive_fallbacks = 0
            if status == 'ok' and 0.0 < elapsed_s <= self.config.max_gap_s:
                self.velocity = self.capped(twist_of(motion, elapsed_s))
                self._twists.append(self.velocity)
            elif status == 'recovered':
                self.velocity = match[5]  # the velocity of the guess that won
            self.recovering = False
        else:
            self.n_fallbacks += 1
            self.consecutive_fallbacks += 1
            log.debug('scan %d: %s (fitness %.3f, %d points)', stamp_ns, status, fitness, n_used)
            if (self.consecutive_fallbacks >= self.config.max_consecutive_fallbacks
                    and self.mode == 'default'):
                self._lose_track(f'{self.consecutive_fallbacks} fallbacks in a row')
        self.T_world_sensor = T_new
        self.last_stamp_ns = int(stamp_ns)
        self.n_registered += 1
        timings['update'] = time.perf_counter() - t0
        timings['total'] = time.perf_counter() - t_start
        return RegistrationResult(
            T_world_sensor=T_new.copy(), T_prev_curr=T_prev_curr, fitness=fitness,
            inlier_rmse_m=rmse, n_points_used=n_used, status=status,
            covariance=self._covariance(status, information, R_world_target),
            timings_s=timings, twist=self.velocity.copy(),
            information=self._rotated_information(status, information, R_world_target))

    def _deskew_motion(self, dt_s: float, latest: np.ndarray | None = None) -> np.ndarray:
        """The motion over `dt_s` that deskew assumes: the mean twist of the recent trusted
        scans (with `latest`, this scan's own estimate, as the newest), planar by default."""
        window = self.config.deskew_velocity_window
        twists = list(self._twists)
        if latest is not None and dt_s > 0.0:
            twists = twists[len(twists) - window + 1:] + [twist_of(latest, dt_s)]
        if not twists or not dt_s > 0.0:
            return np.eye(4)
        motion = delta_of_twist(np.mean(twists[-window:], axis=0), dt_s)
        return planar_delta(motion) if self.config.deskew_planar else motion

    def _check_input(self, points_xyz, time_offset_s, nu=None):
        points = np.asarray(points_xyz, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3:
            raise RegistrationError(f'points_xyz must have shape (N, 3), got {points.shape}')
        if nu is not None:
            nu = np.asarray(nu, dtype=float).reshape(-1)
            if nu.shape[0] != points.shape[0]:
                raise RegistrationError(f'nu has {nu.shape[0]} values for {points.shape[0]} '
                                        'points')
        if time_offset_s is not None:
            time_offset_s = np.asarray(time_offset_s, dtype=float).reshape(-1)
            if time_offset_s.shape[0] != points.shape[0]:
                raise RegistrationError(
                    f'time_offset_s has {time_offset_s.shape[0]} values for '
                    f'{points.shape[0]} points')
        finite = np.isfinite(points).all(axis=1)
        if time_offset_s is not None:
            finite &= np.isfinite(time_offset_s)
        if not finite.all():
            points = points[finite]
            time_offset_s = None if time_offset_s is None else time_offset_s[finite]
            nu = None if nu is None else nu[finite]
        return points, time_offset_s, nu

    def _time_offsets(self, points_xyz: np.ndarray, time_offset_s: np.ndarray | None):
        if time_offset_s is not None:
            return time_offset_s
        return azimuth_time_offsets(points_xyz, self.config.scan_period_s,
                                    self.config.azimuth_stamp_at_sweep_end)

    def _match(self, source_xyz: np.ndarray, T_pred: np.ndarray, stamp_ns: int):
        """ICP from the prediction (default) or from identity (paper); then sanity checks:
        finite, fitness, physically possible and close to the prediction, both measured from
        the last trusted pose (after fallbacks the previous pose is only a prediction)."""
        cfg = self.config
        source = to_cloud(source_xyz)
        if self.mode == 'paper':
            target = self._prev_scan
            init = np.eye(4)  # scan-to-scan, relative to the last trusted scan (the target)
        else:
            target = self.local_map.cloud
            init = T_pred
        result = self._icp(source, target, init, cfg.max_correspondence_distance_m)
        T_est = np.asarray(result.transformation)
        if self.mode == 'paper':
            T_est = self.T_world_trusted @ T_est
        fitness, rmse = float(result.fitness), float(result.inlier_rmse)
        if not np.all(np.isfinite(T_est)):
            return 'fallback_diverged', T_pred, fitness, rmse, None
        if fitness < cfg.min_fitness or (self.mode == 'default'
                                         and self._relatively_unfit(fitness)):
            return 'fallback_low_fitness', T_pred, fitness, rmse, None
        motion, elapsed_s = self._since_trusted(stamp_ns, T_est)
        if not self.is_plausible(motion, elapsed_s):
            log.debug('ICP implies motion beyond the bounds over %.3f s', elapsed_s)
            return 'fallback_implausible', T_pred, fitness, rmse, None
        if self._jumped(T_pred, T_est, stamp_ns):
            return 'fallback_diverged', T_pred, fitness, rmse, None
        return 'ok', T_est, fitness, rmse, self._icp_information(source_xyz, target, result, rmse)

    def _jumped(self, T_pred: np.ndarray, T_est: np.ndarray, stamp_ns: int) -> bool:
        """Farther from the prediction than the jump bounds, which grow with the time the
        prediction has been extrapolated over (since the last trusted pose)."""
        cfg = self.config
        jump_m, jump_rad = transform_magnitude(invert_transform(T_pred) @ T_est)
        allowance = max(1.0, self._since_trusted(stamp_ns, T_est)[1] / cfg.scan_period_s)
        if (jump_m > cfg.max_translation_jump_m * allowance
                or jump_rad > cfg.max_rotation_jump_rad * allowance):
            log.debug('ICP moved %.3f m / %.3f rad away from the prediction', jump_m, jump_rad)
            return True
        return False

    def _relatively_unfit(self, fitness: float) -> bool:
        """Below `min_relative_fitness` x the median fitness of the recent trusted matches."""
        return (len(self._fitness) >= RECENT_FITNESS_MIN and fitness
                < self.config.min_relative_fitness * float(np.median(self._fitness)))

    def _reacquire(self, source_xyz: np.ndarray, T_pred: np.ndarray, stamp_ns: int,
                   retry: bool = False):
        """Re-acquire against the map from a few initial guesses, all from the last trusted
        pose over the time since it: zero motion, the velocity before the loss (capped), and
        its straight-line part (a turn rate extrapolated over a long gap throws the guess
        sideways). From each: a coarse ICP with a widened correspondence distance, then the
        normal one with more iterations. The plausible fit with the best fitness wins; no
        jump check (the guesses are rough).

        `retry`: a second chance for a scan whose match from the prediction failed, with the
        current velocity as the one before the loss; the fit must pass every check a match
        does (relative fitness, the jump from the prediction too), and the velocity becomes
        the motion it implies."""
        cfg = self.config
        source, target = to_cloud(source_xyz), self.local_map.cloud
        guesses = [np.zeros(6)]
        before = self.capped(self.velocity if retry else self._velocity_before_loss)
        if np.any(before):
            guesses.append(before)
        if np.any(before[:3]) and np.any(before[3:]):
            guesses.append(np.r_[0.0, 0.0, 0.0, before[3:]])
        wide_m = cfg.max_correspondence_distance_m * cfg.recovery_correspondence_factor
        _, elapsed_s = self._since_trusted(stamp_ns, self.T_world_trusted)
        best, status = None, 'fallback_low_fitness'
        for velocity in guesses:
            init = self.T_world_trusted @ delta_of_twist(velocity, max(elapsed_s, 0.0))
            coarse = self._icp(source, target, init, wide_m)
            result = self._icp(source, target, np.asarray(coarse.transformation),
                               cfg.max_correspondence_distance_m, self._recovery_criteria)
            T_est = np.asarray(result.transformation)
            if not np.all(np.isfinite(T_est)) or result.fitness < cfg.min_fitness:
                continue
            if retry and (self._relatively_unfit(float(result.fitness))
                          or self._jumped(T_pred, T_est, stamp_ns)):
                continue
            if not self.is_plausible(*self._since_trusted(stamp_ns, T_est)):
                status = 'fallback_implausible'
                continue
            if best is None or result.fitness > best[0].fitness:
                best = (result, T_est, velocity)
        if best is None:
            return status, T_pred, 0.0, 0.0, None
        result, T_est, velocity = best
        if retry:
            motion, elapsed_s = self._since_trusted(stamp_ns, T_est)
            if 0.0 < elapsed_s <= cfg.max_gap_s:
                velocity = self.capped(twist_of(motion, elapsed_s))
        rmse = float(result.inlier_rmse)
        return ('recovered', T_est, float(result.fitness), rmse,
                self._icp_information(source_xyz, target, result, rmse), velocity)

    def _icp(self, source, target, init, distance_m: float, criteria=None):
        criteria = self.criteria if criteria is None else criteria
        if self.solver is not None and target is self.local_map.cloud:
            return self.solver.register(np.asarray(source.points), self.local_map.target(),
                                        init, distance_m, self._source_smoothness,
                                        criteria.max_iteration, self._point_smoothness)
        if self.estimation == 'gicp':
            estimation = o3d_reg.TransformationEstimationForGeneralizedICP(
                self.config.gicp_epsilon, self.kernel)
            return o3d_reg.registration_generalized_icp(source, target, distance_m, init,
                                                        estimation, criteria)
        if self.estimation == 'point_to_plane':
            if not target.has_normals():
                target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(
                    self.local_map.normal_neighbours))
            estimation = o3d_reg.TransformationEstimationPointToPlane(self.kernel)
        else:
            estimation = o3d_reg.TransformationEstimationPointToPoint()
        return o3d_reg.registration_icp(source, target, distance_m, init, estimation, criteria)

    def _icp_information(self, source_xyz, target, result, rmse) -> np.ndarray | None:
        """Gauss-Newton information J^T J / rmse^2 of the final pairs, in the target's axes.

        Point-to-plane rows [n, a x n] (a = point relative to the sensor) expose degenerate
        directions (ground only: x, y, yaw) as small information, hence large variances.
        Point-to-point rows are [I, -[a]x].
        """
        if isinstance(result, IcpResult):  # Gauss-Newton: its own weighted normal matrix
            return result.information
        pairs = np.asarray(result.correspondence_set)
        if pairs.shape[0] < 6:
            return None
        R_target_sensor = np.asarray(result.transformation)[:3, :3]
        a = source_xyz[pairs[:, 0]] @ R_target_sensor.T
        if target.has_normals():
            n = np.asarray(target.normals)[pairs[:, 1]]
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

    def _rotated_information(self, status: str, information: np.ndarray | None,
                             R_world_target: np.ndarray) -> np.ndarray | None:
        """The match's information in the covariance's axes (None on a fallback)."""
        if status.startswith('fallback') or information is None:
            return None
        return in_world_axes(information, R_world_target)

    def _covariance(self, status: str, information: np.ndarray | None,
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

    def _update_reference(self, source_xyz: np.ndarray | None, T_world_sensor: np.ndarray,
                          status: str, keyframe_xyz=None) -> None:
        """Paper: the scan becomes the target. Default: a keyframe when due, its points from
        `keyframe_xyz()` (only built then, with their smoothness) or the registration's."""
        if source_xyz is None:
            return
        if self.mode == 'paper':
            self._prev_scan = to_cloud(source_xyz)
            return
        if status == 'first':
            # Its motion is unknown, so it could not be deskewed: replaced by the first match.
            self._map_provisional = self.deskew
        elif self._map_provisional:
            self.local_map.clear()
            self._map_provisional = False
        if self.local_map.needs_keyframe(T_world_sensor) or len(self.local_map) == 0:
            points, smoothness = ((source_xyz, None) if keyframe_xyz is None
                                  else keyframe_xyz())
            self.local_map.add_keyframe(transform_points(T_world_sensor, points), T_world_sensor,
                                        smoothness)
