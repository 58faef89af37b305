"""The per-scan loop, the one place the node and every offline tool call.

`OdometryPipeline.register_frame(scan)` reads as the method: accept, crop, graph-frequency
filter, register, update. Frames follow REP 105: `odom` is where `base_link` was at the first
scan.

Acceptance is decided here, once, for the node and every offline tool alike: an empty or
all-identical scan, a stamp not after the last accepted one, and a jump of the stamps by more
than `registration.max_gap_s` are rejected and counted by reason. A jump is held as a candidate
for one scan: when the next scan continues from it the clock really stepped (forward: a gap,
the motion is re-acquired; backward, e.g. a bag played in a loop: the odometry starts over, as
tf2 does on a jump back in time); when the next scan continues the old clock it was a lone
outlier. So no stamp can lock the later valid scans out.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from gft_odom.config import GftOdomConfig
from gft_odom.core.bounds_watch import BoundsWatch
from gft_odom.core.constants import NS_PER_S
from gft_odom.core.deferred import Deferred, resolved
from gft_odom.core.degeneracy import FLAT_CLOUD_STD_M, thinnest_axis_std_m
from gft_odom.core.geometry import rpy_transform, sensor_to_base_poses, transform_points
from gft_odom.core.localisation import DriveMap
from gft_odom.core.memory import (
    TRIM_AFTER_POINTS,
    TRIMS_AFTER_A_LARGE_SCAN,
    release_free_memory,
)
from gft_odom.core.registration import ScanRegistration
from gft_odom.core.registration.scan_registration import TRUSTED_STATUSES
from gft_odom.core.spectral.bands import BandMask
from gft_odom.core.spectral.filter import PointFrequencies, SpectralConfig, SpectralFilter
from gft_odom.core.trajectory import Trajectory, TrajectoryRecorder
from gft_odom.core.types import Scan
from gft_odom.errors import ConfigError, SpectralError

log = logging.getLogger(__name__)

DEGENERATE_STATUS = 'fallback_degenerate'
# Scans the drive map takes: trusted and deskewed with a known motion (not the first scan).
DRIVE_MAP_STATUSES = tuple(s for s in TRUSTED_STATUSES if s != 'first')
# The scan-line weight of the frequency the map's anchors keep their points by.
ANCHOR_SCAN_LINE_WEIGHT = 'distance'
# Why a scan can be rejected before registration (FrameResult.status is 'rejected_<reason>').
REJECTION_REASONS = ('empty', 'degenerate', 'out_of_order', 'clock_jump')
# Accepted scans that restarted the clock: counted in status_counts beside the statuses.
CLOCK_RESET = 'clock_reset'
@dataclass(frozen=True)
class Rejection:
    """Why a scan was not registered: a reason from REJECTION_REASONS and a log line."""

    reason: str
    text: str


@dataclass
class FrameResult:
    """What one scan produced: poses, the filtered cloud, health and per-stage timings."""

    stamp_ns: int  # when the pose holds: the scan's stamp, or mid-sweep when not deskewed
    T_world_sensor: np.ndarray  # world = sensor frame at the first scan
    T_odom_base: np.ndarray  # REP 105 odom -> base_link
    covariance: np.ndarray  # (6, 6) of the pose, inflated when registration fell back
    status: str
    n_points_in: int
    n_points_kept: int
    filtered: Scan  # the points registration used
    # (nu, band) per kept point, None when the filter is off; computed after the pose when
    # nothing needs them before it (`frequencies_after_pose`), at the first read.
    frequencies: Deferred | None
    timings_s: dict[str, float] = field(default_factory=dict)
    rejection: Rejection | None = None  # set when the scan was not registered
    # Sensor-frame velocity (rot rad/s, lin m/s) and the match's information matrix
    # (RegistrationResult.twist / .information); zeros / None when not registered.
    twist: np.ndarray = field(default_factory=lambda: np.zeros(6))
    information: np.ndarray | None = None

    @property
    def nu(self) -> np.ndarray | None:
        """Each kept point's graph frequency; None when the filter is off or they failed
        after the pose (`update_map` says so)."""
        return self._frequencies_now()[0]

    @property
    def band(self) -> np.ndarray | None:
        """Each kept point's band (0: no spectrum); None as `nu`."""
        return self._frequencies_now()[1]

    def _frequencies_now(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        if self.frequencies is None:
            return None, None
        try:
            return self.frequencies.get()
        except SpectralError:
            return None, None

    @property
    def fell_back(self) -> bool:
        """Registration fell back to the motion prediction."""
        return self.status.startswith('fallback')

    @property
    def accepted(self) -> bool:
        """False for a scan rejected before registration (its pose is the last one)."""
        return not self.status.startswith('rejected')


def _nu_and_band(freqs: PointFrequencies) -> tuple[np.ndarray, np.ndarray]:
    return freqs.nu, freqs.band


def anchor_filter(spectral: SpectralConfig) -> SpectralFilter | None:
    """The filter of the frequency the map's anchors keep their points by, when it is not the
    published one: on the scan-line graph, distance weights (with range-slope weights the
    anchors lost a record drive, docs/method.md). None: the anchors read the published ones."""
    if spectral.graph != 'scan_line' or spectral.scan_line_weight == ANCHOR_SCAN_LINE_WEIGHT:
        return None
    return SpectralFilter.from_config(replace(spectral, scan_line_weight=ANCHOR_SCAN_LINE_WEIGHT))


def base_to_sensor(config: GftOdomConfig) -> np.ndarray:
    """T_base_sensor from the node section's extrinsic."""
    return rpy_transform(config.node.base_to_sensor_xyz_m, config.node.base_to_sensor_rpy_rad)


class OdometryPipeline:
    """Spectral filter + registration with their state; one call per scan."""

    def __init__(self, config: GftOdomConfig, record_trajectory: bool = True):
        config.validate()
        self.record_trajectory = record_trajectory
        self.config = config
        self.spectral_filter = SpectralFilter.from_config(config.spectral)
        self.anchor_filter = anchor_filter(config.spectral)
        self.band_mask = BandMask.parse(config.spectral.band_mask, config.spectral.n_bands)
        self.registration = ScanRegistration.from_config(config.registration)
        self.T_base_sensor = base_to_sensor(config)
        # Says once when the motion bounds keep refusing matches that agree (a fast platform).
        self.bounds_watch = BoundsWatch(config.registration.max_speed_mps,
                                        config.registration.max_yaw_rate_rps)
        self.status_counts: Counter[str] = Counter()
        self._recorded = TrajectoryRecorder()
        # Trajectories of the odometry runs ended by a clock reset (bag loop), oldest first.
        self.finished_segments: list[Trajectory] = []
        self._last_accepted_ns: int | None = None
        self._jump_candidate_ns: int | None = None  # a stamp jump waiting for confirmation
        self._trims_pending = 0
        # What the last scan left for `update_map`: (its deferred frequencies or None, its
        # timings).
        self._left_after_pose: tuple | None = None
        # Everything the drive saw (~/save_map writes it); what the last scan leaves for it.
        self.drive_map, self._left_for_drive_map = DriveMap(), None
        self.n_resets = 0  # odometry runs started over (reset(), clock reset)

    def reset(self) -> None:
        """Re-initialise the odometry: the next scan is the first again (pose identity,
        empty map, no velocity). The trajectory so far is kept in `finished_segments`."""
        self.update_map()  # the last scan's work, in the run it belongs to
        self.registration.reset()
        self.n_resets += 1
        self._last_accepted_ns = None
        self._jump_candidate_ns = None
        if len(self._recorded):
            self.finished_segments.append(self.sensor_trajectory())
        self._recorded.clear()
        self.drive_map = DriveMap()  # a new odom frame

    def screen(self, scan: Scan) -> Rejection | None:
        """Why `scan` would be rejected now, or None (no state changes)."""
        rejection, _ = self._screen(scan)
        return rejection

    def _screen(self, scan: Scan) -> tuple[Rejection | None, str]:
        """(rejection or None, 'normal' | 'first' | 'gap' | 'clock_reset')."""
        if len(scan) == 0:
            return Rejection('empty', f'skipping empty scan at {scan.stamp_ns} ns (no finite '
                             'point)'), ''
        if not np.any(scan.points_xyz != scan.points_xyz[0]):
            # Every point in one spot: a driver glitch, not geometry (ICP would see one voxel).
            return Rejection('degenerate', f'skipping scan at {scan.stamp_ns} ns: all '
                             f'{len(scan)} points are identical'), ''
        last = self._last_accepted_ns
        if last is None:
            return None, 'first'
        max_gap_ns = self.config.registration.max_gap_s * NS_PER_S
        stamp = int(scan.stamp_ns)
        if 0 < stamp - last <= max_gap_ns:
            return None, 'normal'
        candidate = self._jump_candidate_ns
        if candidate is not None and 0 < stamp - candidate <= max_gap_ns:
            return None, ('gap' if stamp > last else CLOCK_RESET)
        if stamp <= last:
            return Rejection('out_of_order', f'skipping scan stamped {stamp} ns, not after the '
                             f'previous one ({last} ns)'), ''
        return Rejection('clock_jump', f'holding back scan stamped {stamp} ns, '
                         f'{(stamp - last) / NS_PER_S:.1f} s after the previous one: accepted '
                         'only if the next scan continues from it'), ''

    def _admit(self, scan: Scan) -> Rejection | None:
        """Screen `scan` and commit the decision to the acceptance state."""
        rejection, kind = self._screen(scan)
        stamp = int(scan.stamp_ns)
        if rejection is not None:
            self.status_counts[f'rejected_{rejection.reason}'] += 1
            last = self._last_accepted_ns
            if (rejection.reason in ('out_of_order', 'clock_jump') and last is not None
                    and abs(stamp - last) > self.config.registration.max_gap_s * NS_PER_S):
                self._jump_candidate_ns = stamp
            return rejection
        if kind == CLOCK_RESET:
            log.warning('the clock went back from %d to %d ns and stayed (a bag played in a '
                        'loop?): the odometry starts over', self._last_accepted_ns, stamp)
            self.status_counts[CLOCK_RESET] += 1
            self.reset()
        elif kind == 'gap':
            log.warning('the stamps jumped by %.1f s and stayed: re-acquiring the motion',
                        (stamp - self._last_accepted_ns) / NS_PER_S)
        self._last_accepted_ns = stamp
        self._jump_candidate_ns = None
        return None

    @property
    def use_filter(self) -> bool:
        """Whether every scan gets its per-point frequencies (`pipeline.use_spectral_filter`).

        With an all-pass mask nothing is dropped, but the frequencies are still computed and
        published (`~/filtered_points` `frequency` / `band`): the filter is always visible."""
        return self.config.pipeline.use_spectral_filter

    def register_frame(self, scan: Scan, freqs: PointFrequencies | None = None
                       ) -> FrameResult:
        """One scan through acceptance, crop, filter, registration. `freqs`: frequencies of the
        cropped scan computed earlier (the band search re-filters them with many masks).
        A rejected scan gives a result with status 'rejected_<reason>' and the last pose."""
        self.update_map()  # the previous scan's, late
        t0 = time.perf_counter()
        if self._trims_pending:
            release_free_memory()
            self._trims_pending -= 1
        if len(scan) > TRIM_AFTER_POINTS:
            self._trims_pending = TRIMS_AFTER_A_LARGE_SCAN
        # 0. Acceptance: empty, degenerate, stamps out of order or jumping.
        rejection = self._admit(scan)
        if rejection is not None:
            return self._rejected(scan, rejection)
        # 1. Range crop: drop the robot's own body and far, sparse returns.
        cropped = self._crop(scan)
        t1 = time.perf_counter()
        # 2. Graph-frequency band-pass: per-point band, keep the bands of the mask. A mask
        # that keeps every point leaves the frequencies to after the pose.
        kept, kept_freqs, after_pose, keep = cropped, None, None, None
        if self.use_filter and len(cropped):
            if freqs is None and self.frequencies_after_pose:
                # The crop keeps only finite points, so the mask keeps them all.
                after_pose = Deferred(partial(self._frequencies_after_pose, cropped))
                kept_freqs = after_pose.then(_nu_and_band)
            else:
                if freqs is None:
                    freqs = self.spectral_filter.scan_frequencies(cropped, self.band_mask.n_bands)
                keep = self._precomputed_keep(cropped, freqs)
                if keep.all():  # all-pass: no copy of the scan
                    kept_freqs, keep = Deferred.of((freqs.nu, freqs.band)), None
                else:
                    kept = kept.select(keep)
                    kept_freqs = Deferred.of((freqs.nu[keep], freqs.band[keep]))
        t2 = time.perf_counter()
        # 3. Registration (falls back to the motion prediction when ICP cannot be trusted).
        flat_std_m = thinnest_axis_std_m(kept.points_xyz)
        if flat_std_m < FLAT_CLOUD_STD_M:
            log.debug('scan at %d ns is flat (thinnest axis std %.3f m): using the motion '
                      'prediction', scan.stamp_ns, flat_std_m)
            reg = self.registration.advance_with_prediction(scan.stamp_ns, DEGENERATE_STATUS)
        else:
            nu = None if kept_freqs is None else self._anchor_nu(cropped, keep, kept_freqs,
                                                                 scan.stamp_ns)
            reg = self.registration.register(kept.points_xyz, scan.stamp_ns,
                                             kept.time_offset_s,
                                             nu=nu if after_pose or self.anchor_filter
                                             else resolved(nu),
                                             defer_map_update=True)
        t3 = time.perf_counter()
        # 4. Update: odom -> base_link, trajectory, counters.
        T_odom_base = sensor_to_base_poses(reg.T_world_sensor, self.T_base_sensor)
        self.status_counts[reg.status] += 1
        self.bounds_watch.observe(reg.status, reg.refused_speed_mps, reg.refused_rate_rps)
        # The pose holds at the stamp when the sweep was deskewed to it, else mid-sweep.
        pose_stamp_ns = int(scan.stamp_ns) + int(round(
            self.registration.pose_time_offset_s(kept.time_offset_s) * NS_PER_S))
        if self.record_trajectory:
            self._recorded.append(pose_stamp_ns, reg.T_world_sensor)
        timings_s = {'crop': t1 - t0, 'filter': t2 - t1, 'register': t3 - t2,
                     'pipeline': time.perf_counter() - t0}
        self._left_after_pose = (after_pose, timings_s)
        self._left_for_drive_map = (reg.status, reg.T_world_sensor, kept, kept_freqs)
        return FrameResult(
            stamp_ns=pose_stamp_ns, T_world_sensor=reg.T_world_sensor,
            T_odom_base=T_odom_base, covariance=reg.covariance, status=reg.status,
            n_points_in=len(scan), n_points_kept=len(kept), filtered=kept,
            frequencies=kept_freqs, twist=reg.twist, information=reg.information,
            timings_s=timings_s)

    @property
    def frequencies_after_pose(self) -> bool:
        """Whether a scan's frequencies are computed after its pose: the mask keeps every
        point whatever its frequency, so the pose does not need them (the registration reads
        them only for its next keyframe's map)."""
        return self.spectral_filter.keeps_every_finite_point(self.band_mask)

    def _frequencies_after_pose(self, cropped: Scan) -> PointFrequencies:
        """The frequencies of a scan whose pose is out: whatever fails in them is a
        SpectralError, which costs the scan its frequencies, nothing else."""
        try:
            return self.spectral_filter.scan_frequencies(cropped, self.band_mask.n_bands)
        except Exception as exc:
            raise SpectralError(f'the frequencies of the scan at {cropped.stamp_ns} ns failed '
                                f'after its pose: {exc!r}') from exc

    def _anchor_nu(self, cropped: Scan, keep: np.ndarray | None, kept_freqs: Deferred,
                   stamp_ns: int) -> Deferred:
        """The frequencies the map's anchors keep the kept points by: the published ones, or
        (`anchor_filter`) their own, computed only if a keyframe reads them."""
        if self.anchor_filter is None:
            return kept_freqs.then(lambda nu_band: self._registration_nu(nu_band[0], stamp_ns))

        def compute() -> np.ndarray:
            try:
                nu = self.anchor_filter.scan_frequencies(cropped, self.band_mask.n_bands).nu
            except Exception as exc:
                raise SpectralError(f'the anchor frequencies of the scan at {stamp_ns} ns '
                                    f'failed: {exc!r}') from exc
            return self._registration_nu(nu if keep is None else nu[keep], stamp_ns)
        return Deferred(compute)

    def _registration_nu(self, nu: np.ndarray | None, stamp_ns: int) -> np.ndarray | None:
        """The frequencies registration sees: the scan's, or (the ablation control
        `pipeline.shuffle_frequencies`) the same values permuted, seeded by the stamp."""
        if nu is None or not self.config.pipeline.shuffle_frequencies:
            return nu
        seed = self.config.pipeline.shuffle_seed
        stamp = int(stamp_ns) % (1 << 32)
        return np.random.default_rng(stamp if seed == 0 else [stamp, seed]).permutation(nu)

    def _rejected(self, scan: Scan, rejection: Rejection) -> FrameResult:
        T_world_sensor = self.registration.T_world_sensor.copy()
        return FrameResult(
            stamp_ns=int(scan.stamp_ns), T_world_sensor=T_world_sensor,
            T_odom_base=sensor_to_base_poses(T_world_sensor, self.T_base_sensor),
            covariance=np.diag(self.registration.fallback_var),
            status=f'rejected_{rejection.reason}', n_points_in=len(scan), n_points_kept=0,
            filtered=scan.select(np.zeros(0, dtype=np.int64)), frequencies=None,
            rejection=rejection)

    def _precomputed_keep(self, cropped: Scan, freqs: PointFrequencies) -> np.ndarray:
        if len(freqs) != len(cropped):
            raise SpectralError(f'precomputed frequencies cover {len(freqs)} points but the '
                                f'cropped scan at {cropped.stamp_ns} ns has {len(cropped)}')
        return self.spectral_filter.keep_mask(freqs, self.band_mask)

    def _crop(self, scan: Scan) -> Scan:
        index = self._crop_index(scan)
        return scan if index.size == len(scan) else scan.select(index)

    def _crop_index(self, scan: Scan) -> np.ndarray:
        """The points the range crop keeps, in scan order (a study can follow its own
        per-point data, e.g. the simulator's labels, through the crop)."""
        cfg = self.config.pipeline
        r2 = np.einsum('ij,ij->i', scan.points_xyz, scan.points_xyz)
        # A non-finite point fails the test (NaN), or is dropped (inf, max_range_m inf).
        keep = (r2 >= cfg.min_range_m ** 2) & (r2 <= cfg.max_range_m ** 2) & np.isfinite(r2)
        index = np.flatnonzero(keep)
        if index.size > cfg.max_points_per_scan:
            stride = int(np.ceil(index.size / cfg.max_points_per_scan))
            log.warning('scan at %d ns has %d points; keeping every %d-th (max_points_per_scan='
                        '%d)', scan.stamp_ns, index.size, stride, cfg.max_points_per_scan)
            index = index[::stride]
        return index

    def reconfigure(self, config: GftOdomConfig) -> None:
        """Take new spectral / crop parameters at run time; registration keeps its state."""
        config.validate()
        self.update_map()  # the last scan's work, with the settings it was registered with
        if config.registration != self.config.registration:
            raise ConfigError('registration parameters can only change before the first scan')
        self.spectral_filter = SpectralFilter.from_config(config.spectral)
        self.anchor_filter = anchor_filter(config.spectral)
        self.band_mask = BandMask.parse(config.spectral.band_mask, config.spectral.n_bands)
        self.config = config

    def update_map(self) -> float:
        """The work the last `register_frame` left after its pose: its frequencies (when
        they come after the pose, and nobody read them yet) and a keyframe's map rebuild
        (its normals and search index); the seconds it took.

        `register_frame` returns the pose first, so that a caller can publish it and then
        call this; the next `register_frame` does it when the caller did not. Either way
        the poses are the same. The scan's `timings_s` get 'filter' (the frequencies,
        wherever they were computed) and 'map_update'."""
        t0 = time.perf_counter()
        left, self._left_after_pose = self._left_after_pose, None
        after_pose, timings_s = left or (None, {})
        if after_pose is not None:
            try:
                after_pose.get()  # the keyframe's smoothness needs them
            except SpectralError as exc:  # the pose is out: the scan is not lost for this
                log.warning('%s; its keyframe, if any, is mapped without them', exc)
            timings_s['filter'] = after_pose.seconds
        self._add_to_drive_map()
        timings_s['map_update'] = self.registration.update_map()
        return time.perf_counter() - t0

    def _add_to_drive_map(self) -> None:
        """The last scan into the drive map (deskewed as the odometry's map got it), when due."""
        left, self._left_for_drive_map = self._left_for_drive_map, None
        status, T_world_sensor, kept, kept_freqs = left or ('none', None, (), None)
        if status not in DRIVE_MAP_STATUSES or not len(kept) or not self.drive_map.due(
                T_world_sensor, self.config.registration.keyframe_distance_m):
            return
        try:
            nu = None if kept_freqs is None else kept_freqs.get()[0]
        except SpectralError:  # they failed after the pose: the points still go in
            nu = None
        points = self.registration.deskewed_like_last(kept.points_xyz)
        self.drive_map.add_scan(T_world_sensor, points, nu)

    def map_snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        """Everything this run saw (the drive map: a scan every keyframe distance or turn,
        deskewed, one point per map voxel) in the odom frame (REP 105, as the trajectory):
        (points_xyz (N, 3) float64, nu (N,) float32, NaN where a point has none)."""
        self.update_map()
        return (transform_points(self.T_base_sensor, self.drive_map.points_xyz),
                self.drive_map.nu.copy())

    def sensor_trajectory(self) -> Trajectory:
        """T_world_sensor of every registered scan (world = first sensor frame)."""
        return self._recorded.trajectory()

    def base_trajectory(self) -> Trajectory:
        """T_odom_base of every registered scan: what the node publishes."""
        traj = self.sensor_trajectory()
        return Trajectory(traj.stamps_ns, sensor_to_base_poses(traj.poses, self.T_base_sensor))
