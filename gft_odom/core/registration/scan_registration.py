"""`ScanRegistration`: one scan at a time against the local map (or, in paper mode, the
previous scan); `register` reads as its steps.

Registration never raises for bad geometry: too few points, a low fitness, a jump far from the
prediction or a motion the platform cannot make return the prediction with a `fallback_*`
status and an inflated covariance, and the next scan goes on. RegistrationError is raised only
for malformed input.

Frames: `T_world_sensor` is the sensor pose where the sweep holds (at the scan's stamp when it
was deskewed to it; mid-sweep otherwise: `pose_time_offset_s`), world = the sensor frame at
the first registered scan. `covariance` is the (6, 6) uncertainty of this scan's
registration (x, y, z, rot_x, rot_y, rot_z; world axes, about the sensor origin), not the
accumulated drift.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import open3d as o3d

from gft_odom.core.deferred import Deferred
from gft_odom.core.deskew import azimuth_time_offsets, deskew_points, sweep_middle_offset_s
from gft_odom.core.geometry import invert_transform, transform_points
from gft_odom.core.registration.config import RegistrationConfig
from gft_odom.core.registration.local_map import LocalMap
from gft_odom.core.registration.matching import MapMatcher, point_to_point_icp, to_cloud
from gft_odom.core.registration.motion import MotionModel, delta_of_twist
from gft_odom.core.registration.recovery import Match, Recovery, fitted_match
from gft_odom.core.registration.sweep import (
    Sweep,
    checked_input,
    map_smoothness,
    smoothness_or_unknown,
)
from gft_odom.core.registration.trust import TrustPolicy
from gft_odom.core.registration.uncertainty import PoseUncertainty, world_information
from gft_odom.core.registration.voxels import voxel_downsample_indices
from gft_odom.errors import RegistrationError

log = logging.getLogger(__name__)

# Every status `register` / `advance_with_prediction` can return.
STATUSES = ('first', 'ok', 'recovered', 'fallback_too_few_points', 'fallback_low_fitness',
            'fallback_diverged', 'fallback_implausible', 'fallback_degenerate')
# Poses trusted enough to update the velocity and the reference (map or previous scan).
TRUSTED_STATUSES = ('first', 'ok', 'recovered')
# Failed matches from the prediction that are re-acquired at once (a second chance: at the
# start of a pivot the yaw rate jumps within a scan and ICP from the prediction can slide).
RETRIED_STATUSES = ('fallback_low_fitness', 'fallback_diverged', 'fallback_implausible')
# Below this many downsampled points ICP is not attempted.
MIN_POINTS = 100


@dataclass
class RegistrationResult:
    """Outcome of one scan: pose, increment, match quality, health, timings."""

    T_world_sensor: np.ndarray  # (4, 4) sensor pose where the sweep holds
    T_prev_curr: np.ndarray  # (4, 4) motion since the previous scan
    fitness: float  # inlier pairs / source points, 0 when not matched
    inlier_rmse_m: float
    n_points_used: int  # downsampled source points
    status: str  # one of STATUSES
    covariance: np.ndarray  # (6, 6), inflated on fallback
    timings_s: dict[str, float] = field(default_factory=dict)
    # (rot_x, rot_y, rot_z, v_x, v_y, v_z) rad/s, m/s in the sensor frame: the motion model's
    # velocity after this scan (zeros when unknown, e.g. after a loss).
    twist: np.ndarray = field(default_factory=lambda: np.zeros(6))
    # (6, 6) information of the match (x, y, z, rot_x, rot_y, rot_z; the covariance's axes),
    # None on a fallback: its small eigenvalues are weak directions.
    information: np.ndarray | None = None
    # The speed (m/s) and rotation rate (rad/s) a match refused as implausible implied, since
    # the last trusted pose; None unless status is fallback_implausible from the match.
    refused_speed_mps: float | None = None
    refused_rate_rps: float | None = None

    @property
    def fell_back(self) -> bool:
        """True when ICP was not trusted and the prediction was used."""
        return self.status.startswith('fallback')


def _delegated(part: str, name: str, settable: bool = False) -> property:
    """`name` of one of ScanRegistration's parts, readable on the facade."""
    def get(self):
        return getattr(getattr(self, part), name)

    def put(self, value) -> None:
        setattr(getattr(self, part), name, value)
    return property(get, put if settable else None, doc=f'`self.{part}.{name}`')


class ScanRegistration:
    """Registers consecutive scans and keeps the odometry state (pose, velocity, local map)."""

    T_world_sensor = _delegated('motion', 'T_world_sensor')
    T_world_trusted = _delegated('motion', 'T_world_trusted')
    velocity = _delegated('motion', 'velocity', settable=True)
    recovering = _delegated('motion', 'recovering')
    n_fallbacks = _delegated('trust', 'n_fallbacks')
    consecutive_fallbacks = _delegated('trust', 'consecutive_fallbacks')
    n_turn_checks = _delegated('recovery', 'n_turn_checks')
    n_turns_found = _delegated('recovery', 'n_turns_found')
    fallback_var = _delegated('uncertainty', 'fallback_var')

    def __init__(self, config: RegistrationConfig = RegistrationConfig()):
        config.validate()
        self.config = config
        self.mode = config.mode
        self.local_map = LocalMap(config.map_voxel_size_m, config.map_max_range_m,
                                  config.map_max_points, config.map_keyframes,
                                  config.keyframe_distance_m)
        self.matcher = MapMatcher(self.local_map, config.max_iterations,
                                  config.robust_kernel_scale_m)
        # Paper mode has no map to re-acquire against: it never drops the velocity, and its
        # fitness is judged against the absolute bound only.
        self.motion = MotionModel(config, track_loss=config.mode == 'default')
        self.trust = TrustPolicy(self.motion, relative_fitness=config.mode == 'default')
        self.uncertainty = PoseUncertainty.from_config(config)
        self.recovery = Recovery(self.matcher, self.motion, self.trust, self.local_map,
                                 config.max_correspondence_distance_m)
        self.deskew = config.deskew and config.mode == 'default'
        self.reset()

    @classmethod
    def from_config(cls, cfg: RegistrationConfig) -> 'ScanRegistration':
        """Same as the constructor."""
        return cls(cfg)

    def reset(self) -> None:
        """Forget everything: the next scan is the first again."""
        self.motion.reset()
        self.trust.reset()
        self.recovery.reset()
        self.n_registered = 0
        self._prev_scan: o3d.geometry.PointCloud | None = None  # paper mode's target
        self.local_map.clear()
        self._map_provisional = False
        # A keyframe a deferred `register` left for `update_map`: (world points, pose,
        # smoothness, perhaps still Deferred, or None).
        self._pending_keyframe: tuple | None = None
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

    def update_map(self) -> float:
        """Add the keyframe the last `register` left pending and build the map's search
        index for the next match; the seconds it took (0 when nothing was pending). The next
        `register` does it first when the caller did not, so deferring changes no pose: it
        only lets a caller publish the pose before the map work (most of the p95 latency)."""
        pending, self._pending_keyframe = self._pending_keyframe, None
        if pending is None:
            return 0.0
        t0 = time.perf_counter()
        points_world, T_world_sensor, smoothness = pending
        self.local_map.add_keyframe(points_world, T_world_sensor,
                                    smoothness_or_unknown(smoothness, points_world.shape[0]))
        if len(self.local_map):
            self.local_map.target()
        return time.perf_counter() - t0

    def reference_points_world(self) -> np.ndarray:
        """The points a scan is matched against (world frame): the map's, or in paper mode
        the previous scan's."""
        self.update_map()
        if self.mode == 'paper' and self._prev_scan is not None:
            return transform_points(self.T_world_trusted, np.asarray(self._prev_scan.points))
        return self.local_map.points_xyz

    def advance_with_prediction(self, stamp_ns: int,
                                status: str = 'fallback_degenerate') -> RegistrationResult:
        """Take the motion prediction as the pose at `stamp_ns` without matching anything:
        for scans the caller knows ICP cannot observe (a flat cloud). Counted as a fallback."""
        if status not in STATUSES or not status.startswith('fallback'):
            raise RegistrationError(f'advance_with_prediction needs a fallback status from '
                                    f'{STATUSES}, got {status!r}')
        t_start = time.perf_counter()
        self.update_map()
        _, T_pred = self.motion.predict(stamp_ns)
        return self._finish(stamp_ns, status, T_pred, t_start, {})

    def register(self, points_xyz: np.ndarray, stamp_ns: int,
                 time_offset_s: np.ndarray | None = None,
                 nu: np.ndarray | Deferred | None = None,
                 defer_map_update: bool = False) -> RegistrationResult:
        """Register one scan (sensor frame, any number of points) and update the state.

        `nu` (N,): every point's graph frequency (NaN: none); the map keeps each keyframe
        point's smoothness from it (its anchors: a smooth point takes over a rough one's
        voxel). A `Deferred` nu is computed only when the keyframe is added, in `update_map`,
        after the pose. `defer_map_update`: a keyframe this scan makes waits for `update_map`
        (or the next `register`), so the pose is returned before the map's rebuild."""
        sweep = Sweep(*checked_input(points_xyz, time_offset_s, nu))
        timings: dict[str, float] = {}
        # A keyframe a deferred call left, when its caller did not: this scan is waiting.
        self.update_map()
        t_start = time.perf_counter()
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
        # 5. A trusted scan is deskewed again with its own motion: the map gets that cloud.
        self._redeskew(sweep, stamp_ns, status, T_new)
        # 6-8. Trust the pose or count a fallback, update the map, the result.
        result = self._finish(stamp_ns, status, T_new, t_start, timings, sweep, match)
        if not defer_map_update:
            timings['map_update'] = self.update_map()
        return self._with_extras(result, sweep, refused)

    def pose_time_offset_s(self, time_offset_s: np.ndarray | None) -> float:
        """Where in its sweep a scan's pose holds, in s after its stamp: the stamp when the
        sweep is deskewed to it, else the middle of the sweep (a rigid fit of the whole
        sweep: paper mode, deskew off)."""
        if self.deskew:
            return 0.0
        return sweep_middle_offset_s(time_offset_s, self.config.scan_period_s,
                                     self.config.azimuth_stamp_at_sweep_end)

    def deskewed_like_last(self, points_xyz: np.ndarray) -> np.ndarray:
        """The last registered scan's points (as it was given, after the crop) deskewed as
        the map got them; as they are when that scan was not deskewed or they do not match."""
        last = self._last_deskew
        if last is None or last[0].shape[0] != points_xyz.shape[0]:
            return points_xyz
        offsets_s, motion, dt_s = last
        return deskew_points(points_xyz, offsets_s, motion, dt_s)

    # ------------------------------------------------------------ the steps

    def _downsample(self, sweep: Sweep, timings: dict[str, float]) -> None:
        """The source points (the first in scan order of each voxel) and their smoothness as
        the map keeps it."""
        t0 = time.perf_counter()
        sweep.keep = voxel_downsample_indices(sweep.points_xyz, self.config.voxel_size_m)
        sweep.source_xyz = sweep.points_xyz[sweep.keep]
        if sweep.nu is not None:
            sweep.point_smoothness = map_smoothness(sweep.nu, sweep.keep)
        timings['downsample'] = time.perf_counter() - t0

    def _deskew(self, sweep: Sweep, timings: dict[str, float]) -> None:
        """Deskew the source points with the mean twist of the recent trusted scans."""
        t0 = time.perf_counter()
        if self.deskew and sweep.source_xyz.shape[0]:
            sweep.offsets_s = self._time_offsets(sweep.points_xyz, sweep.time_offset_s)
            sweep.source_xyz = sweep.deskewed(self.motion.deskew_motion(sweep.dt_s))
        timings['deskew'] = time.perf_counter() - t0

    def _match_or_reacquire(self, sweep: Sweep, T_pred: np.ndarray, stamp_ns: int,
                            timings: dict[str, float]):
        """(status, pose, match or None, refused rates): the first scan, too few points,
        re-acquisition after a loss, or ICP against the reference (retried the way
        re-acquisition does when it fails, then checked from turned guesses when it fits
        poorly for the recent matches)."""
        refused = (None, None)  # the rates a match refused as implausible implied
        if sweep.n_used < MIN_POINTS:
            if not self.has_reference:
                log.warning('scan %d has %d points after downsampling (< %d) and there is no '
                            'reference yet', stamp_ns, sweep.n_used, MIN_POINTS)
            return 'fallback_too_few_points', T_pred, None, refused
        if not self.has_reference:
            return 'first', (T_pred if self.n_registered else np.eye(4)), None, refused
        t0 = time.perf_counter()
        if self.motion.recovering and self.mode == 'default':
            match = self.recovery.reacquire(sweep.source_xyz, T_pred, stamp_ns)
        else:
            self.motion.last_implied_rates = (None, None)  # set by is_plausible in the match
            match = self._match(sweep.source_xyz, T_pred, stamp_ns)
            if match.status == 'fallback_implausible':
                refused = self.motion.last_implied_rates
            if self.mode == 'default':
                if match.status in RETRIED_STATUSES:
                    retried = self.recovery.reacquire(sweep.source_xyz, T_pred, stamp_ns,
                                                      retry=True)
                    match = retried if retried.status == 'recovered' else match
                if self.recovery.turn_check_due(match):
                    match = self.recovery.turn_check(sweep.source_xyz,
                                                     partial(self._deskewed_as, sweep), T_pred,
                                                     stamp_ns, match)
        timings['icp'] = time.perf_counter() - t0
        return match.status, match.T_world_sensor, match, refused

    def _match(self, source_xyz: np.ndarray, T_pred: np.ndarray, stamp_ns: int) -> Match:
        """ICP from the prediction (default) or from identity (paper); then sanity checks:
        finite, fitness, physically possible and close to the prediction, both measured from
        the last trusted pose (after fallbacks the previous pose is only a prediction)."""
        cfg = self.config
        if self.mode == 'paper':
            # Scan-to-scan, relative to the last trusted scan (the target).
            target = self._prev_scan
            result = point_to_point_icp(source_xyz, target, np.eye(4),
                                        cfg.max_correspondence_distance_m, cfg.max_iterations)
            T_est = self.T_world_trusted @ np.asarray(result.transformation)
        else:
            target = self.local_map.target()
            result = self.matcher.match(source_xyz, T_pred, cfg.max_correspondence_distance_m)
            T_est = np.asarray(result.transformation)
        refusal = self.trust.refusal(T_est, float(result.fitness), T_pred, stamp_ns)
        if refusal is not None:
            return Match(refusal, T_pred, float(result.fitness), float(result.inlier_rmse), None)
        return fitted_match('ok', result, T_est, source_xyz, target)

    def _deskewed_as(self, sweep: Sweep, velocity: np.ndarray) -> np.ndarray:
        """The source points deskewed as they would be were `velocity` the scan's motion (the
        turn check's guesses); the sweep's own when it was not deskewed."""
        if sweep.offsets_s is None or not sweep.dt_s > 0.0:
            return sweep.source_xyz
        return sweep.deskewed(self.motion.deskew_motion(sweep.dt_s,
                                                        delta_of_twist(velocity, sweep.dt_s)))

    def _redeskew(self, sweep: Sweep, stamp_ns: int, status: str, T_new: np.ndarray) -> None:
        """Deskew a trusted scan again with its own motion (only when it was deskewed)."""
        if sweep.offsets_s is None or status not in ('ok', 'recovered') or not sweep.dt_s > 0.0:
            return
        # This scan's motion as deskew assumes it, worked out before the trusted pose moves.
        sweep.scan_motion = self.motion.scan_motion(stamp_ns, T_new, sweep.dt_s)
        sweep.source_xyz = sweep.deskewed(self.motion.deskew_motion(sweep.dt_s,
                                                                    sweep.scan_motion))

    def _finish(self, stamp_ns: int, status: str, T_new: np.ndarray, t_start: float,
                timings: dict[str, float], sweep: Sweep | None = None,
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

    def _with_extras(self, result: RegistrationResult, sweep: Sweep,
                     refused: tuple) -> RegistrationResult:
        """The rates a refused match implied, and what deskewing this scan took (for
        `deskewed_like_last`: the map's snapshot)."""
        if result.status == 'fallback_implausible':
            result.refused_speed_mps, result.refused_rate_rps = refused
        self._last_deskew = None if sweep.offsets_s is None else (
            sweep.offsets_s, self.motion.deskew_motion(sweep.dt_s, sweep.scan_motion),
            sweep.dt_s)
        return result

    # ------------------------------------------------------------ the reference

    def _update_reference(self, sweep: Sweep | None, T_world_sensor: np.ndarray,
                          status: str) -> None:
        """Paper: the scan becomes the target. Default: a keyframe when due (its points and
        their smoothness, added in `update_map`)."""
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
            self._pending_keyframe = (transform_points(T_world_sensor, sweep.source_xyz),
                                      T_world_sensor.copy(), sweep.point_smoothness)

    def _time_offsets(self, points_xyz: np.ndarray, time_offset_s: np.ndarray | None):
        if time_offset_s is not None:
            return time_offset_s
        return azimuth_time_offsets(points_xyz, self.config.scan_period_s,
                                    self.config.azimuth_stamp_at_sweep_end)


