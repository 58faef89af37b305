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

The parts, one concern each (`ScanRegistration.register` runs them in turn: predict,
downsample, deskew, match or re-acquire, trust, update the map, the result):

- here: ScanRegistration (the steps, the match from the prediction, the reference update)
- core/recovery.py: Recovery (re-acquisition, the retry of a failed match, the turn check)
- core/registration_config.py: RegistrationConfig (every parameter)
- core/trust.py: TrustPolicy (fitness against the recent matches, the bounds and the jump a
  match must keep, the fallback run)
- core/motion_model.py: MotionModel (velocity, trusted pose, physical bounds, prediction,
  plausibility, jumps, loss of track, the twists deskew assumes)
- core/icp_backend.py: IcpBackend (one ICP call: map_tree, open3d or the Gauss-Newton solver)
- core/gauss_newton.py, core/residuals.py: the Gauss-Newton solver and its per-pair residuals
- core/map_tree_icp.py: open3d's point-to-plane ICP over the map's own KD-tree
- core/uncertainty.py: the information of the final pairs and the reported covariance
- core/local_map.py: the keyframe local map (voxel downsampling too)
- core/deskew.py: per-point times and motion compensation

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
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import open3d as o3d

from gft_odom.core.deferred import Deferred, resolved
from gft_odom.core.deskew import azimuth_time_offsets, deskew_points, sweep_middle_offset_s
from gft_odom.core.geometry import along_beams, finite_rows, invert_transform, transform_points
from gft_odom.core.icp_backend import RECOVERY_ITERATIONS_FACTOR as RECOVERY_ITERATIONS_FACTOR
from gft_odom.core.icp_backend import IcpBackend
from gft_odom.core.local_map import (
    LocalMap,
    to_cloud,
    voxel_downsample_indices,
)
from gft_odom.core.motion_model import MotionModel
from gft_odom.core.motion_model import delta_of_twist as delta_of_twist
from gft_odom.core.motion_model import scale_delta as scale_delta
from gft_odom.core.motion_model import transform_magnitude as transform_magnitude
from gft_odom.core.motion_model import twist_of as twist_of
from gft_odom.core.recovery import Match, Recovery, fitted_match
from gft_odom.core.registration_config import RegistrationConfig as RegistrationConfig
from gft_odom.core.residuals import smoothness_from_nu
from gft_odom.core.threshold import AdaptiveThreshold
from gft_odom.core.trust import TrustPolicy
from gft_odom.core.uncertainty import PoseUncertainty, world_information
from gft_odom.core.uncertainty import in_world_axes as in_world_axes
from gft_odom.errors import RegistrationError, SpectralError

log = logging.getLogger(__name__)

# Every status `register` / `advance_with_prediction` can return.
STATUSES = ('first', 'ok', 'recovered', 'fallback_too_few_points', 'fallback_low_fitness',
            'fallback_diverged', 'fallback_implausible', 'fallback_degenerate')
# Poses trusted enough to update the velocity and the reference (map or previous scan).
TRUSTED_STATUSES = ('first', 'ok', 'recovered')
# Failed matches from the prediction that `retry_failed_match` re-acquires at once.
RETRIED_STATUSES = ('fallback_low_fitness', 'fallback_diverged', 'fallback_implausible')


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


def local_map_from_config(cfg: RegistrationConfig) -> LocalMap:
    """The local map of default mode, from the `map_*` / keyframe fields."""
    return LocalMap(
        voxel_size_m=cfg.map_voxel_size_m, max_range_m=cfg.map_max_range_m,
        max_points=cfg.map_max_points, max_keyframes=cfg.map_keyframes,
        keyframe_distance_m=cfg.keyframe_distance_m,
        keyframe_rotation_rad=cfg.keyframe_rotation_rad,
        normal_neighbours=cfg.normal_neighbours, eviction=cfg.map_keyframe_eviction,
        voxel_keeps=cfg.map_voxel_keeps,
        anchor_smoothness=cfg.map_anchor_smoothness if cfg.map_anchors else None,
        anchor_max_points=cfg.map_anchor_max_points,
        rough_anchor_view_rad=(math.radians(cfg.map_anchor_rough_view_deg)
                               if cfg.map_anchor_rough_view_deg > 0.0 else None),
        rough_anchor_any_side_share=cfg.map_anchor_rough_any_side_share,
        rough_window_view_rad=(math.radians(cfg.map_window_rough_view_deg)
                               if cfg.map_window_rough_view_deg > 0.0 else None),
        smooth_view_rad=(math.radians(cfg.map_smooth_view_deg)
                         if cfg.map_smooth_view_deg < 180.0 else None))


@dataclass
class _Sweep:
    """One scan on its way through `register`: the whole scan and what the steps make of it."""

    points_xyz: np.ndarray  # (N, 3) the whole scan, sensor frame
    time_offset_s: np.ndarray | None  # (N,) per-point times from the bag, if any
    nu: np.ndarray | Deferred | None  # (N,) per-point graph frequency, if any
    keep: np.ndarray | None = None  # indices of the downsampled points
    source_xyz: np.ndarray | None = None  # the points ICP matches (downsampled, deskewed)
    point_smoothness: np.ndarray | Deferred | None = None  # theirs, as the map keeps it
    offsets_s: np.ndarray | None = None  # (N,) point times; set only when deskewed
    dt_s: float = 0.0  # since the previous scan
    scan_motion: np.ndarray | None = None  # its own motion, when re-deskewed with it
    map_motion: np.ndarray | None = None  # the motion the re-deskewed points assume

    @property
    def n_used(self) -> int:
        """How many points ICP matches."""
        return int(self.source_xyz.shape[0])

    def deskewed(self, motion: np.ndarray) -> np.ndarray:
        """The downsampled points deskewed with `motion` over the scan's `dt_s` (needs
        `offsets_s`)."""
        return deskew_points(self.points_xyz[self.keep], self.offsets_s[self.keep], motion,
                             self.dt_s)


def _delegated(part: str, name: str, settable: bool = False) -> property:
    """`name` of one of ScanRegistration's parts, readable where callers always found it."""
    def get(self):
        return getattr(getattr(self, part), name)

    def put(self, value) -> None:
        setattr(getattr(self, part), name, value)
    return property(get, put if settable else None, doc=f'`self.{part}.{name}`')


class ScanRegistration:
    """Registers consecutive scans and keeps the odometry state (pose, velocity, local map)."""

    # The parts' state and checks, where callers and tests have always found them.
    T_world_sensor = _delegated('motion', 'T_world_sensor')
    T_world_trusted = _delegated('motion', 'T_world_trusted')
    trusted_stamp_ns = _delegated('motion', 'trusted_stamp_ns')
    last_stamp_ns = _delegated('motion', 'last_stamp_ns')
    velocity = _delegated('motion', 'velocity', settable=True)
    recovering = _delegated('motion', 'recovering')
    last_implied_rates = _delegated('motion', 'last_implied_rates')
    capped = _delegated('motion', 'capped')
    predicted_delta = _delegated('motion', 'predicted_delta')
    is_plausible = _delegated('motion', 'is_plausible')
    n_fallbacks = _delegated('trust', 'n_fallbacks')
    n_turn_checks = _delegated('recovery', 'n_turn_checks')
    n_turns_found = _delegated('recovery', 'n_turns_found')
    consecutive_fallbacks = _delegated('trust', 'consecutive_fallbacks')
    min_var = _delegated('uncertainty', 'min_var')
    fallback_var = _delegated('uncertainty', 'fallback_var')

    def __init__(self, config: RegistrationConfig = RegistrationConfig()):
        config.validate()
        self.config = config
        self.mode = config.mode
        self.local_map = local_map_from_config(config)
        self.icp = IcpBackend(config, self.local_map)  # also sets what the map computes
        self.estimation = self.icp.estimation
        # Paper mode has no map to re-acquire against: it never drops the velocity.
        self.motion = MotionModel(config, track_loss=config.mode == 'default')
        self.trust = TrustPolicy(config, self.motion)
        self.uncertainty = PoseUncertainty.from_config(config)
        self.recovery = Recovery(config, self.icp, self.motion, self.trust, self.local_map)
        # adaptive_kernel_ratio: the kernel's scale follows the prediction errors, and
        # starts at the fixed one.
        self.threshold = (AdaptiveThreshold(
            config.robust_kernel_scale_m / config.adaptive_kernel_ratio,
            config.adaptive_min_motion_m, config.map_max_range_m, config.adaptive_window_scans)
            if config.adaptive_kernel_ratio > 0.0 else None)
        self.deskew = config.deskew and config.mode == 'default'
        self._background_map = (config.resolved_map_update == 'background'
                                and self.icp.solves_on_map_target)
        self.reset()

    @classmethod
    def from_config(cls, cfg: RegistrationConfig) -> 'ScanRegistration':
        """Same as the constructor (kept for the callers that name it)."""
        return cls(cfg)

    def reset(self) -> None:
        """Forget everything: the next scan is the first again."""
        self.motion.reset()
        self.trust.reset()
        self.recovery.reset()
        if self.threshold is not None:
            self.threshold.reset()
            self.icp.use_kernel_scale(self.config.robust_kernel_scale_m)
        self.n_registered = 0
        self.n_turn_continued = 0  # matches turn_continue_min_rad carried on
        self._prev_scan: o3d.geometry.PointCloud | None = None  # paper mode's target
        self.local_map.clear()
        self._map_provisional = False
        # A keyframe a deferred `register` left for `update_map`: (world points, pose,
        # smoothness, perhaps still Deferred, or None).
        self._pending_keyframe: tuple | None = None
        self._adopt_at_scan = 0
        # The last registered scan's (time offsets, motion, dt) when it was deskewed.
        self._last_deskew: tuple | None = None

    @property
    def has_reference(self) -> bool:
        """A map (default) or a previous scan (paper) to register against."""
        if self.mode == 'paper':
            return self._prev_scan is not None
        return len(self.local_map) > 0 or self._pending_keyframe is not None

    @property
    def map_update_pending(self) -> bool:
        """A deferred `register` left a keyframe for `update_map`."""
        return self._pending_keyframe is not None

    def update_map(self, next_scan_due_s: float | None = None) -> float:
        """Add the keyframe the last `register` left pending, and build the solvers' target
        (its KD-tree) for the next match; the seconds it took (0 when nothing was pending).
        `next_scan_due_s` (`time.perf_counter` seconds): when the next scan is due
        (map_normals 'in_time'; None: no deadline).

        The next `register` does it first when the caller did not, so deferring changes no
        pose: it only lets a caller publish the pose before the map work (a keyframe's
        rebuild and normals, most of the p95 latency)."""
        pending, self._pending_keyframe = self._pending_keyframe, None
        if pending is None:
            return 0.0
        t0 = time.perf_counter()
        points_world, T_world_sensor, smoothness = pending
        # The first keyframe is built at once: the next scan has no other map.
        background = self._background_map and len(self.local_map) > 0
        self.local_map.add_keyframe(points_world, T_world_sensor,
                                    _smoothness_or_unknown(smoothness, points_world.shape[0]),
                                    background=background, normals_due_s=next_scan_due_s)
        if background:
            self._adopt_at_scan = self.n_registered + 1  # served from the scan after next
        elif self.icp.solves_on_map_target and len(self.local_map):
            self.local_map.target()
        return time.perf_counter() - t0

    def _serve_map(self, timings: dict[str, float]) -> None:
        """map_update 'background': the rebuild a keyframe started is served from the second
        scan after it (the next one is matched against the map before it), whenever the
        thread finished; the wait is this scan's."""
        if self.local_map.rebuild_in_flight and self.n_registered >= self._adopt_at_scan:
            timings['map_wait'] = self.local_map.adopt()

    def advance_with_prediction(self, stamp_ns: int,
                                status: str = 'fallback_degenerate') -> RegistrationResult:
        """Take the motion prediction as the pose at `stamp_ns` without matching anything:
        for scans the caller knows ICP cannot observe (a flat cloud). Counted as a fallback."""
        if status not in STATUSES or not status.startswith('fallback'):
            raise RegistrationError(f'advance_with_prediction needs a fallback status from '
                                    f'{STATUSES}, got {status!r}')
        t_start = time.perf_counter()
        self.update_map(next_scan_due_s=t_start)
        timings: dict[str, float] = {}
        self._serve_map(timings)
        _, T_pred = self.motion.predict(stamp_ns)
        return self._finish(stamp_ns, status, T_pred, t_start, timings)

    def register(self, points_xyz: np.ndarray, stamp_ns: int,
                 time_offset_s: np.ndarray | None = None,
                 nu: np.ndarray | None = None,
                 defer_map_update: bool = False) -> RegistrationResult:
        """Register one scan (sensor frame, any number of points) and update the state.

        `nu` (N,): every point's graph frequency (NaN: none), read by residual_model
        'frequency'; without it every pair is weighted alike. A `Deferred` nu is computed
        only when something reads it: the default reads it for the keyframe's map, in
        `update_map`, after the pose. `defer_map_update`: a keyframe
        this scan makes waits for `update_map` (or the next `register`), so the pose is
        returned before the map's rebuild."""
        sweep = _Sweep(*self._check_input(points_xyz, time_offset_s, nu))
        timings: dict[str, float] = {}
        # A keyframe a deferred call left, when its caller did not: this scan is waiting.
        self.update_map(next_scan_due_s=time.perf_counter())
        t_start = time.perf_counter()
        self._serve_map(timings)
        # 1. Predict: the velocity over the real stamp difference, capped (a gap drops it).
        sweep.dt_s, T_pred = self.motion.predict(stamp_ns)
        # 2. Downsample: one point per voxel, which keeps its time and frequency.
        self._downsample(sweep, timings)
        # 3. Deskew those points with the recent velocity.
        self._deskew(sweep, timings)
        # 4. Match against the reference or re-acquire (the first scan and too few points
        # are not matched).
        status, T_new, match, refused = self._match_or_reacquire(sweep, T_pred, stamp_ns,
                                                                 timings)
        if self.threshold is not None and status == 'ok':
            self.threshold.observe(T_pred, T_new)
            self.icp.use_kernel_scale(self.config.adaptive_kernel_ratio
                                      * self.threshold.sigma_m)
        # 5. A trusted scan is deskewed again with its own motion: the map gets that cloud.
        self._redeskew(sweep, stamp_ns, status, T_new)
        # 6-8. Trust the pose or count a fallback, update the map, the result.
        result = self._finish(stamp_ns, status, T_new, t_start, timings, sweep, match)
        if not defer_map_update:
            timings['map_update'] = self.update_map()
        return self._with_extras(result, sweep, refused)

    # ------------------------------------------------------------ the steps

    def _downsample(self, sweep: _Sweep, timings: dict[str, float]) -> None:
        """The source points (one per voxel: the first in scan order, or the smoothest) and
        their smoothness for the solver and the map."""
        t0 = time.perf_counter()
        # A deferred nu is computed here only for the options that read it before the pose.
        cfg, nu = self.config, sweep.nu
        priority = resolved(nu) if cfg.voxel_priority == 'smoothest' else None
        on_grid = (sweep.points_xyz if cfg.voxel_grid_offset_m == 0.0
                   else sweep.points_xyz + cfg.voxel_grid_offset_m)
        sweep.keep = voxel_downsample_indices(on_grid, cfg.voxel_size_m, priority)
        if cfg.rough_voxel_size_m > 0.0 and nu is not None:
            sweep.keep = thinned_rough(sweep.points_xyz, sweep.keep, resolved(nu), cfg)
        sweep.source_xyz = sweep.points_xyz[sweep.keep]
        source_smoothness = (smoothness_from_nu(resolved(nu)[sweep.keep], cfg.smooth_nu)
                             if nu is not None and cfg.residual_model == 'frequency' else None)
        # The map remembers the smoothness of its points (unknown kept NaN) when it is read.
        remembered = nu is not None and (cfg.map_anchors or (
            self.icp.solver is not None and cfg.frequency_affinity_m > 0.0))
        sweep.point_smoothness = (_map_smoothness(nu, sweep.keep, cfg.smooth_nu)
                                  if remembered else None)
        self.icp.use_smoothness(source_smoothness, sweep.point_smoothness)
        if cfg.rough_beam_shift_m != 0.0 and nu is not None:
            self._shift_rough_points(sweep)
        timings['downsample'] = time.perf_counter() - t0

    def _shift_rough_points(self, sweep: _Sweep) -> None:
        """`rough_beam_shift_m`: the kept points moved along their beams by their roughness
        (in the scan itself, so that the deskew after the match carries it into the map)."""
        cfg = self.config
        roughness = 1.0 - smoothness_from_nu(resolved(sweep.nu)[sweep.keep], cfg.smooth_nu,
                                             unknown=1.0)
        points = sweep.points_xyz.copy()
        points[sweep.keep] = along_beams(points[sweep.keep], cfg.rough_beam_shift_m * roughness)
        sweep.points_xyz = points
        sweep.source_xyz = points[sweep.keep]

    def _deskew(self, sweep: _Sweep, timings: dict[str, float]) -> None:
        """Deskew the source points with the mean twist of the recent trusted scans."""
        t0 = time.perf_counter()
        if self.deskew and sweep.source_xyz.shape[0]:
            sweep.offsets_s = self._time_offsets(sweep.points_xyz, sweep.time_offset_s)
            sweep.source_xyz = sweep.deskewed(self.motion.deskew_motion(sweep.dt_s))
        timings['deskew'] = time.perf_counter() - t0

    def _match_or_reacquire(self, sweep: _Sweep, T_pred: np.ndarray, stamp_ns: int,
                            timings: dict[str, float]):
        """(status, pose, match or None, refused rates): the first scan, too few points,
        re-acquisition after a loss, or ICP against the reference (retried the way
        re-acquisition does when it fails and `retry_failed_match`)."""
        n_used = sweep.n_used
        refused = (None, None)  # the rates a match refused as implausible implied
        if n_used < self.config.min_points:
            if not self.has_reference:
                log.warning('scan %d has %d points after downsampling (< min_points %d) and '
                            'there is no reference yet', stamp_ns, n_used,
                            self.config.min_points)
            return 'fallback_too_few_points', T_pred, None, refused
        if not self.has_reference:
            return 'first', (T_pred if self.n_registered else np.eye(4)), None, refused
        t0 = time.perf_counter()
        if self.motion.recovering and self.mode == 'default':
            match = self.recovery.reacquire(sweep.source_xyz, T_pred, stamp_ns)
        else:
            self.motion.last_implied_rates = (None, None)  # set by is_plausible in the match
            match = Match(*self._match(sweep.source_xyz, T_pred, stamp_ns))
            if match.status == 'fallback_implausible':
                refused = self.motion.last_implied_rates
            if (match.status in RETRIED_STATUSES and self.mode == 'default'
                    and self.config.retry_failed_match):
                retried = self.recovery.reacquire(sweep.source_xyz, T_pred, stamp_ns, retry=True)
                match = retried if retried.status == 'recovered' else match
            if self.recovery.turn_check_due(match, sweep.source_xyz):
                match = self.recovery.turn_check(sweep.source_xyz,
                                                 partial(self._deskewed_as, sweep), T_pred,
                                                 stamp_ns, match)
        timings['icp'] = time.perf_counter() - t0
        return match.status, match.T_world_sensor, match, refused

    def _redeskew(self, sweep: _Sweep, stamp_ns: int, status: str, T_new: np.ndarray) -> None:
        """Deskew a trusted scan again with its own motion (only when it was deskewed)."""
        if sweep.offsets_s is None or status not in ('ok', 'recovered') or not sweep.dt_s > 0.0:
            return
        # This scan's motion as deskew assumes it, worked out before the trusted pose moves.
        sweep.scan_motion = self.motion.scan_motion(stamp_ns, T_new, sweep.dt_s)
        sweep.map_motion = self.motion.deskew_motion(sweep.dt_s, sweep.scan_motion)
        sweep.source_xyz = sweep.deskewed(sweep.map_motion)

    def _finish(self, stamp_ns: int, status: str, T_new: np.ndarray, t_start: float,
                timings: dict[str, float], sweep: _Sweep | None = None,
                match: Match | None = None) -> RegistrationResult:
        """Trust the pose (motion model, fitness) or count a fallback, update the reference,
        move the pose; the result."""
        t0 = time.perf_counter()
        fitness, rmse, information = (match[2], match[3], match[4]) if match else (0.0, 0.0, None)
        # Axes the ICP information is expressed in: world (map) or the previous scan (paper).
        R_world_target = self.T_world_trusted[:3, :3] if self.mode == 'paper' else np.eye(3)
        T_prev_curr = invert_transform(self.T_world_sensor) @ T_new
        n_used = 0 if sweep is None else sweep.n_used
        if status in TRUSTED_STATUSES:
            # The velocity spans the motion since the last trusted pose: after fallbacks the
            # previous pose was extrapolated, and its error is not this scan's motion.
            self.motion.trust(stamp_ns, T_new, status, None if match is None else match[5])
            self.trust.trusted(None if match is None else fitness)
            self._update_reference(sweep, T_new, status)
        else:
            log.debug('scan %d: %s (fitness %.3f, %d points)', stamp_ns, status, fitness, n_used)
            if self.trust.fell_back():
                self.motion.lose_track(f'{self.trust.consecutive_fallbacks} fallbacks in a row')
        self.motion.advance(stamp_ns, T_new)
        self.n_registered += 1
        timings['update'] = time.perf_counter() - t0
        timings['total'] = time.perf_counter() - t_start
        return RegistrationResult(
            T_world_sensor=T_new.copy(), T_prev_curr=T_prev_curr, fitness=fitness,
            inlier_rmse_m=rmse, n_points_used=n_used, status=status,
            covariance=self.uncertainty.covariance(status, information, R_world_target),
            timings_s=timings, twist=self.velocity.copy(),
            information=world_information(status, information, R_world_target))

    def _with_extras(self, result: RegistrationResult, sweep: _Sweep,
                     refused: tuple) -> RegistrationResult:
        """The rates a refused match implied; the deskewed scan when asked for (with the
        twists as this scan left them)."""
        if result.status == 'fallback_implausible':
            result.refused_speed_mps, result.refused_rate_rps = refused
        # What deskewing this scan takes, for `deskewed_like_last` (the map's snapshot).
        self._last_deskew = None if sweep.offsets_s is None else (
            sweep.offsets_s, self.motion.deskew_motion(sweep.dt_s, sweep.scan_motion),
            sweep.dt_s)
        if self.config.output_deskewed_points:
            result.deskewed_points = (sweep.points_xyz.copy() if self._last_deskew is None
                                      else deskew_points(sweep.points_xyz, *self._last_deskew))
        return result

    def deskewed_like_last(self, points_xyz: np.ndarray) -> np.ndarray:
        """The last registered scan's points (as it was given, after the crop) deskewed as
        the map got them; as they are when that scan was not deskewed or they do not match."""
        last = self._last_deskew
        if last is None or last[0].shape[0] != points_xyz.shape[0]:
            return points_xyz
        offsets_s, motion, dt_s = last
        return deskew_points(points_xyz, offsets_s, motion, dt_s)

    # ------------------------------------------------------------ matching

    def _match(self, source_xyz: np.ndarray, T_pred: np.ndarray, stamp_ns: int) -> Match:
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
        result = self.icp.register(source, target, init, cfg.max_correspondence_distance_m,
                                   prior=self.mode == 'default')
        wide = result = self._continued_if_turning(source, target, init, result)
        if cfg.refine_correspondence_distance_m > 0.0 and self.mode == 'default':
            result = self.icp.register(source, target, np.asarray(wide.transformation),
                                       cfg.refine_correspondence_distance_m)
        # `result` gives the pose; `wide` (the same without a refine), what trust reads.
        T_est = np.asarray(result.transformation)
        if self.mode == 'paper':
            T_est = self.T_world_trusted @ T_est
        refusal = self.trust.refusal(T_est, float(wide.fitness), T_pred, stamp_ns)
        if refusal in ('fallback_implausible', 'fallback_diverged') and np.all(np.isfinite(T_est)):
            self.motion.remember_refused(stamp_ns, T_est)  # it fitted: the bounds refused it
        if refusal is not None:
            return Match(refusal, T_pred, float(wide.fitness), float(wide.inlier_rmse), None)
        return fitted_match('ok', result, T_est, source_xyz, self.icp, target, wide=wide)

    def _continued_if_turning(self, source, target, init: np.ndarray, result):
        """`turn_continue_min_rad`: a match the iteration cap stopped while it was still
        turning away from `init` carries on from where it stopped."""
        cfg = self.config
        if (cfg.turn_continue_min_rad <= 0.0
                or getattr(result, 'n_iterations', 0) < cfg.max_iterations):
            return result  # off, converged, or open3d's ICP (which does not say)
        T = np.asarray(result.transformation)
        _, turned_rad = transform_magnitude(invert_transform(init) @ T)
        if not turned_rad > cfg.turn_continue_min_rad:
            return result
        self.n_turn_continued += 1
        return self.icp.register(source, target, T, cfg.max_correspondence_distance_m,
                                 max_iterations=cfg.turn_continue_iterations)

    def _deskewed_as(self, sweep: _Sweep, velocity: np.ndarray) -> np.ndarray:
        """The source points deskewed as they would be were `velocity` the scan's motion
        (`turn_guess_deskew`); the sweep's own (deskewed with the prediction's) otherwise."""
        if not self.config.turn_guess_deskew or sweep.offsets_s is None or not sweep.dt_s > 0.0:
            return sweep.source_xyz
        return sweep.deskewed(self.motion.deskew_motion(sweep.dt_s,
                                                        delta_of_twist(velocity, sweep.dt_s)))

    # ------------------------------------------------------------ the reference

    def _update_reference(self, sweep: _Sweep | None, T_world_sensor: np.ndarray,
                          status: str) -> None:
        """Paper: the scan becomes the target. Default: a keyframe when due, its points from
        `_keyframe_points` (only built then, with their smoothness)."""
        if sweep is None:
            return
        if self.mode == 'paper':
            self._prev_scan = to_cloud(sweep.source_xyz)
            return
        if status == 'first':
            # Its motion is unknown, so it could not be deskewed: replaced by the first match.
            self._map_provisional = self.deskew
        elif self._map_provisional:
            self.local_map.clear()
            self._map_provisional = False
        if self.local_map.needs_keyframe(T_world_sensor) or len(self.local_map) == 0:
            points, smoothness = self._keyframe_points(sweep)
            self._pending_keyframe = (transform_points(T_world_sensor, points),
                                      T_world_sensor.copy(), smoothness)

    def _keyframe_points(self, sweep: _Sweep) -> tuple[np.ndarray, np.ndarray | None]:
        """The points a keyframe adds, and their smoothness when the map keeps it: the
        registration's, or (map_points_from 'scan') the whole scan at the map voxel,
        deskewed as the registration's were."""
        cfg = self.config
        if cfg.map_points_from == 'registration' or sweep.source_xyz.shape[0] == 0:
            return sweep.source_xyz, sweep.point_smoothness
        dense = voxel_downsample_indices(sweep.points_xyz, cfg.map_voxel_size_m)
        smooth = (None if sweep.point_smoothness is None
                  else _map_smoothness(sweep.nu, dense, cfg.smooth_nu))
        if sweep.map_motion is None:
            return sweep.points_xyz[dense], smooth
        return deskew_points(sweep.points_xyz[dense], sweep.offsets_s[dense], sweep.map_motion,
                             sweep.dt_s), smooth

    # ------------------------------------------------------------ input

    def _check_input(self, points_xyz, time_offset_s, nu=None):
        points = np.asarray(points_xyz, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3:
            raise RegistrationError(f'points_xyz must have shape (N, 3), got {points.shape}')
        if isinstance(nu, Deferred):
            nu = nu.then(partial(_checked_nu, n_points=points.shape[0]))
        elif nu is not None:
            nu = _checked_nu(nu, points.shape[0])
        if time_offset_s is not None:
            time_offset_s = np.asarray(time_offset_s, dtype=float).reshape(-1)
            if time_offset_s.shape[0] != points.shape[0]:
                raise RegistrationError(
                    f'time_offset_s has {time_offset_s.shape[0]} values for '
                    f'{points.shape[0]} points')
        finite = finite_rows(points)
        if time_offset_s is not None:
            finite &= np.isfinite(time_offset_s)
        if not finite.all():
            points = points[finite]
            time_offset_s = None if time_offset_s is None else time_offset_s[finite]
            if isinstance(nu, Deferred):
                nu = nu.then(lambda values: values[finite])
            elif nu is not None:
                nu = nu[finite]
        return points, time_offset_s, nu

    def pose_time_offset_s(self, time_offset_s: np.ndarray | None) -> float:
        """Where in its sweep a scan's pose holds, in s after its stamp: the stamp when the
        sweep is deskewed to it, else the middle of the sweep (a rigid fit of the whole
        sweep: paper mode, deskew off)."""
        if self.deskew:
            return 0.0
        return sweep_middle_offset_s(time_offset_s, self.config.scan_period_s,
                                     self.config.azimuth_stamp_at_sweep_end)

    def _time_offsets(self, points_xyz: np.ndarray, time_offset_s: np.ndarray | None):
        if time_offset_s is not None:
            return time_offset_s
        return azimuth_time_offsets(points_xyz, self.config.scan_period_s,
                                    self.config.azimuth_stamp_at_sweep_end)


def _checked_nu(values, n_points: int) -> np.ndarray:
    """`values` as the (n_points,) float frequencies of a scan."""
    nu = np.asarray(values, dtype=float).reshape(-1)
    if nu.shape[0] != n_points:
        raise RegistrationError(f'nu has {nu.shape[0]} values for {n_points} points')
    return nu


def _smoothness_or_unknown(smoothness: np.ndarray | Deferred | None, n_points: int
                           ) -> np.ndarray | None:
    """A keyframe's smoothness; unknown (NaN) when its deferred frequencies failed: the
    keyframe still goes into the map, as it would without frequencies."""
    try:
        return resolved(smoothness)
    except SpectralError:  # its caller said so (OdometryPipeline.update_map)
        return np.full(n_points, np.nan)


def thinned_rough(points_xyz: np.ndarray, keep: np.ndarray, nu: np.ndarray,
                  cfg: RegistrationConfig) -> np.ndarray:
    """`keep` with its rough points (smoothness below `map_anchor_smoothness`, no spectrum
    counted rough) thinned to one per `rough_voxel_size_m` voxel; the smooth ones all kept."""
    smooth = smoothness_from_nu(nu[keep], cfg.smooth_nu) >= cfg.map_anchor_smoothness
    rough = keep[~smooth]
    kept_rough = rough[voxel_downsample_indices(points_xyz[rough], cfg.rough_voxel_size_m)]
    return np.sort(np.concatenate([keep[smooth], kept_rough]))


def _map_smoothness(nu: np.ndarray | Deferred, index: np.ndarray,
                    smooth_nu: float) -> np.ndarray | Deferred:
    """The smoothness the map remembers for the points `index` (NaN: unknown); deferred
    with `nu`."""
    if isinstance(nu, Deferred):
        return nu.then(lambda values: smoothness_from_nu(values[index], smooth_nu,
                                                         unknown=np.nan))
    return smoothness_from_nu(nu[index], smooth_nu, unknown=np.nan)
