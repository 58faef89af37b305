"""The per-scan loop, the one place the node and every offline tool call.

`OdometryPipeline.register_frame(scan)` reads as the method: crop, graph-frequency filter,
register, update. Frames follow REP 105: `odom` is where `base_link` was at the first scan.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from gft_odom.config import GftOdomConfig
from gft_odom.core.geometry import rpy_transform, sensor_to_base_poses
from gft_odom.core.registration import ScanRegistration
from gft_odom.core.spectral.bands import BandMask
from gft_odom.core.spectral.filter import PointFrequencies, SpectralFilter
from gft_odom.core.spectral.sources import make_source
from gft_odom.core.trajectory import Trajectory
from gft_odom.core.types import Scan
from gft_odom.errors import ConfigError, SpectralError

log = logging.getLogger(__name__)

# A cloud whose thinnest principal axis has a standard deviation below this is flat (ground
# only, a wall): ICP cannot observe the in-plane motion (x, y, yaw on ground) but converges
# with a confident covariance and drags the map along, so the motion prediction is used
# instead. Orchard scans measure >= 0.69 m on that axis whatever the band mask, bare sim
# ground 0.01-0.04 m (docs/robustness.md).
FLAT_CLOUD_STD_M = 0.05
DEGENERATE_STATUS = 'fallback_degenerate'


@dataclass
class FrameResult:
    """What one scan produced: poses, the filtered cloud, health and per-stage timings."""

    stamp_ns: int
    T_world_sensor: np.ndarray  # world = sensor frame at the first scan
    T_odom_base: np.ndarray  # REP 105 odom -> base_link
    covariance: np.ndarray  # (6, 6) of the pose, inflated when registration fell back
    status: str
    n_points_in: int
    n_points_kept: int
    filtered: Scan  # the points registration used
    nu: np.ndarray | None  # per kept point, None when the filter is off
    band: np.ndarray | None
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def fell_back(self) -> bool:
        return self.status.startswith('fallback')


def thinnest_axis_std_m(points_xyz: np.ndarray) -> float:
    """Standard deviation of the points along their thinnest principal axis (inf if < 10)."""
    if points_xyz.shape[0] < 10:
        return float('inf')  # too few to judge: registration's min_points decides
    centred = points_xyz - points_xyz.mean(axis=0)
    scatter = centred.T @ centred / points_xyz.shape[0]
    return float(np.sqrt(max(np.linalg.eigvalsh(scatter)[0], 0.0)))


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
        self.band_mask = BandMask.parse(config.spectral.band_mask, config.spectral.n_bands)
        self.frequency_source = make_source(self.spectral_filter)
        self.registration = ScanRegistration.from_config(config.registration)
        self.T_base_sensor = base_to_sensor(config)
        self.status_counts: Counter[str] = Counter()
        self._stamps_ns: list[int] = []
        self._poses: list[np.ndarray] = []

    @property
    def use_filter(self) -> bool:
        """Whether every scan gets its per-point frequencies (`pipeline.use_spectral_filter`).

        With an all-pass mask nothing is dropped, but the frequencies are still computed and
        published (`~/filtered_points` `frequency` / `band`): the filter is always visible."""
        return self.config.pipeline.use_spectral_filter

    def register_frame(self, scan: Scan, freqs: PointFrequencies | None = None
                       ) -> FrameResult:
        """One scan through crop, filter, registration. `freqs`: frequencies of the
        cropped scan computed earlier (the band search re-filters them with many masks)."""
        t0 = time.perf_counter()
        # 1. Range crop: drop the robot's own body and far, sparse returns.
        cropped = self._crop(scan)
        t1 = time.perf_counter()
        # 2. Graph-frequency band-pass: per-point band, keep the bands of the mask.
        nu = band = None
        kept = cropped
        if self.use_filter and len(cropped):
            if freqs is None:
                freqs = self.frequency_source.frequencies(cropped, self.band_mask.n_bands)
            keep = self._precomputed_keep(cropped, freqs)
            if keep.all():  # all-pass: no copy of the scan
                kept, nu, band = cropped, freqs.nu, freqs.band
            else:
                kept = cropped.select(keep)
                nu, band = freqs.nu[keep], freqs.band[keep]
        t2 = time.perf_counter()
        # 3. Registration (falls back to the motion prediction when ICP cannot be trusted).
        flat_std_m = thinnest_axis_std_m(kept.points_xyz)
        if flat_std_m < FLAT_CLOUD_STD_M:
            # Registration with no points takes its own fallback path: prediction, inflated
            # covariance, the reference map untouched.
            log.debug('scan at %d ns is flat (thinnest axis std %.3f m): using the motion '
                      'prediction', scan.stamp_ns, flat_std_m)
            reg = self.registration.register(np.zeros((0, 3)), scan.stamp_ns)
            reg.status = DEGENERATE_STATUS
        else:
            reg = self.registration.register(kept.points_xyz, scan.stamp_ns,
                                             kept.time_offset_s)
        t3 = time.perf_counter()
        # 4. Update: odom -> base_link, trajectory, counters, the frequency source's map.
        if self.use_filter and not reg.status.startswith('fallback'):
            self.frequency_source.observe(cropped, reg.T_world_sensor)
        t4 = time.perf_counter()  # a local-map source's keyframe update is filter time
        T_odom_base = sensor_to_base_poses(reg.T_world_sensor, self.T_base_sensor)
        self.status_counts[reg.status] += 1
        if self.record_trajectory:
            self._stamps_ns.append(int(scan.stamp_ns))
            self._poses.append(reg.T_world_sensor)
        return FrameResult(
            stamp_ns=int(scan.stamp_ns), T_world_sensor=reg.T_world_sensor,
            T_odom_base=T_odom_base, covariance=reg.covariance, status=reg.status,
            n_points_in=len(scan), n_points_kept=len(kept), filtered=kept, nu=nu, band=band,
            timings_s={'crop': t1 - t0, 'filter': (t2 - t1) + (t4 - t3), 'register': t3 - t2,
                       'pipeline': t4 - t0})

    def _precomputed_keep(self, cropped: Scan, freqs: PointFrequencies) -> np.ndarray:
        if len(freqs) != len(cropped):
            raise SpectralError(f'precomputed frequencies cover {len(freqs)} points but the '
                                f'cropped scan at {cropped.stamp_ns} ns has {len(cropped)}')
        return self.spectral_filter.keep_mask(freqs, self.band_mask)

    def _crop(self, scan: Scan) -> Scan:
        cfg = self.config.pipeline
        r2 = np.einsum('ij,ij->i', scan.points_xyz, scan.points_xyz)
        keep = (r2 >= cfg.min_range_m ** 2) & (r2 <= cfg.max_range_m ** 2)
        index = np.flatnonzero(keep)
        if index.size > cfg.max_points_per_scan:
            stride = int(np.ceil(index.size / cfg.max_points_per_scan))
            log.warning('scan at %d ns has %d points; keeping every %d-th (max_points_per_scan='
                        '%d)', scan.stamp_ns, index.size, stride, cfg.max_points_per_scan)
            index = index[::stride]
        return scan if index.size == len(scan) else scan.select(index)

    def reconfigure(self, config: GftOdomConfig) -> None:
        """Take new spectral / crop parameters at run time; registration keeps its state."""
        config.validate()
        if config.registration != self.config.registration:
            raise ConfigError('registration parameters can only change before the first scan')
        self.spectral_filter = SpectralFilter.from_config(config.spectral)
        self.frequency_source = make_source(self.spectral_filter)
        self.band_mask = BandMask.parse(config.spectral.band_mask, config.spectral.n_bands)
        self.config = config

    def sensor_trajectory(self) -> Trajectory:
        """T_world_sensor of every registered scan (world = first sensor frame)."""
        return Trajectory(np.array(self._stamps_ns, dtype=np.int64),
                          np.array(self._poses).reshape(-1, 4, 4))

    def base_trajectory(self) -> Trajectory:
        """T_odom_base of every registered scan: what the node publishes."""
        traj = self.sensor_trajectory()
        return Trajectory(traj.stamps_ns, sensor_to_base_poses(traj.poses, self.T_base_sensor))
