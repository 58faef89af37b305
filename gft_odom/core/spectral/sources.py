"""Where a scan's per-point frequencies come from: the scan itself, or the local map.

- `ScanSource` (`spectral.frequency_source: scan`, the default): the graph of the scan alone,
  computed on every scan.
- `LocalMapSource` (`local_map`): the paper computed its frequencies on the merged cloud, not
  on single scans. Here the merged cloud is a local map of the last keyframes (world frame,
  voxel grid); its frequencies are recomputed only when a keyframe is added (amortised), and
  each new scan's points take the frequency of their nearest map point, found with the pose
  guess (the previous scan's pose). The merged cloud has no single ring structure, so the map
  always uses the slice graph. Measured in benchmarks/bench_frequency_classes.py: the transfer
  carries far less information about the surface than the scan's own scan-line graph.
- `MapPlanaritySource` (`map_planarity`): no frequency at all, an ablation. The same local map,
  but each map point's value is the planarity of its neighbourhood (GenZ-ICP's surface
  variation), put on nu's scale; every use of nu downstream is unchanged.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from gft_odom.core.geometry import finite_rows
from gft_odom.core.local_map import to_cloud
from gft_odom.core.residuals import smoothness_from_covariances
from gft_odom.core.spectral.bands import band_of_nu
from gft_odom.core.spectral.filter import PointFrequencies, SpectralFilter
from gft_odom.core.types import Scan

log = logging.getLogger(__name__)

class ScanSource:
    """Frequencies of each scan from its own graph."""

    def __init__(self, spectral_filter: SpectralFilter) -> None:
        """`spectral_filter` computes the frequencies."""
        self.spectral_filter = spectral_filter

    def frequencies(self, scan: Scan, n_bands: int) -> PointFrequencies:
        """The scan's own frequencies."""
        return self.spectral_filter.scan_frequencies(scan, n_bands)

    def observe(self, scan: Scan, T_world_sensor: np.ndarray) -> None:
        """A registered scan and its pose (unused: no state)."""

    def reset(self) -> None:
        """Nothing to forget."""


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


class LocalMapSource:
    """Frequencies of a local map of keyframes, passed to each scan by nearest neighbour."""

    def __init__(self, spectral_filter: SpectralFilter) -> None:
        """Map settings from the filter's config (`local_map_*`)."""
        cfg = spectral_filter.config
        self.config = cfg
        # The map is a merged cloud: the slice graph (no ring order to follow).
        self.map_filter = SpectralFilter(dataclasses.replace(cfg, graph='slice'))
        self.reset()

    def reset(self) -> None:
        """Forget the map and the pose."""
        self._keyframes: list[np.ndarray] = []  # world-frame points per keyframe
        self._last_keyframe_xyz: np.ndarray | None = None
        self._T_last = np.eye(4)
        self._tree: cKDTree | None = None
        self._nu = self._band = self._n_bands = None
        self.keyframe_updates = 0

    def frequencies(self, scan: Scan, n_bands: int) -> PointFrequencies:
        """Each point's frequency = its nearest map point's, found with the last pose; band 0
        (no spectrum) beyond `local_map_max_distance_m` from the map."""
        points = np.asarray(scan.points_xyz, dtype=np.float64)
        finite = finite_rows(points)
        if not self._keyframes:  # first scan: it is the map
            self._add_keyframe(points[finite], self._T_last)
        if self._n_bands != n_bands or self._tree is None:
            self._recompute(n_bands)
        n = points.shape[0]
        nu = np.full(n, np.nan, dtype=np.float32)
        band = np.zeros(n, dtype=np.int16)
        if finite.any() and self._tree is not None:
            distance, index = self._tree.query(_transform(self._T_last, points[finite]), k=1,
                                               distance_upper_bound=self.config
                                               .local_map_max_distance_m)
            hit = np.isfinite(distance)
            rows = np.flatnonzero(finite)[hit]
            nu[rows] = self._nu[index[hit]]
            band[rows] = self._band[index[hit]]
        no_spectrum = finite & (band == 0)
        return PointFrequencies(nu=nu, band=band, n_bands=n_bands, isolated=no_spectrum,
                                in_range=np.ones(n, dtype=bool), finite=finite, n_slices=1)

    def observe(self, scan: Scan, T_world_sensor: np.ndarray) -> None:
        """Keep the pose; add the scan as a keyframe after enough motion."""
        self._T_last = np.asarray(T_world_sensor, dtype=np.float64)
        position = self._T_last[:3, 3]
        if (self._last_keyframe_xyz is not None and np.linalg.norm(
                position - self._last_keyframe_xyz) < self.config.local_map_keyframe_distance_m):
            return
        points = np.asarray(scan.points_xyz, dtype=np.float64)
        points = points[finite_rows(points)]
        self._add_keyframe(points, self._T_last)
        if self._n_bands is not None:
            self._recompute(self._n_bands)

    def _add_keyframe(self, points_sensor: np.ndarray, T_world_sensor: np.ndarray) -> None:
        self._keyframes.append(_transform(T_world_sensor, points_sensor))
        self._keyframes = self._keyframes[-self.config.local_map_keyframes:]
        self._last_keyframe_xyz = T_world_sensor[:3, 3].copy()
        self._tree = None

    def _recompute(self, n_bands: int) -> None:
        """Frequencies of the merged, voxelised keyframes, sliced in the last keyframe's
        sensor frame (its z is the sensor's vertical)."""
        merged = np.concatenate(self._keyframes) if self._keyframes else np.zeros((0, 3))
        voxel = self.config.local_map_voxel_m
        if merged.shape[0]:
            _, first = np.unique(np.floor(merged / voxel).astype(np.int64), axis=0,
                                 return_index=True)
            merged = merged[np.sort(first)]
        self._nu, self._band = self._map_values(merged, n_bands)
        self._tree = cKDTree(merged) if merged.shape[0] else None
        self._n_bands = n_bands
        self.keyframe_updates += 1

    def _map_values(self, merged: np.ndarray, n_bands: int) -> tuple[np.ndarray, np.ndarray]:
        """(nu, band) of every merged map point: its frequency on the slice graph."""
        T_sensor_world = np.linalg.inv(self._T_last)
        freqs = self.map_filter.frequencies(_transform(T_sensor_world, merged), n_bands)
        return freqs.nu, freqs.band


# nu of a perfectly planar neighbourhood: where the scan-line frequency puts a smooth surface.
PLANAR_NU = 0.5


class MapPlanaritySource(LocalMapSource):
    """The local map's planarity in place of the frequency (GenZ-ICP-style, an ablation):
    nu = PLANAR_NU (1 - v / planarity_rough_variation), v the surface variation of the map
    point's `planarity_neighbours` nearest map points. As GenZ-ICP's, it calls a line (a wire,
    one sparse ring) planar: v is 0 there too."""

    def _map_values(self, merged: np.ndarray, n_bands: int) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        if merged.shape[0] < cfg.planarity_neighbours:  # too few for a neighbourhood
            nu = np.full(merged.shape[0], np.nan, dtype=np.float32)
            return nu, band_of_nu(nu, n_bands)
        cloud = to_cloud(merged)
        cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(cfg.planarity_neighbours))
        planarity = smoothness_from_covariances(np.asarray(cloud.covariances),
                                                cfg.planarity_rough_variation)
        nu = (PLANAR_NU * planarity).astype(np.float32)
        return nu, band_of_nu(nu, n_bands)


def make_source(spectral_filter: SpectralFilter):
    """The source named by `spectral.frequency_source`."""
    if spectral_filter.config.frequency_source == 'local_map':
        return LocalMapSource(spectral_filter)
    if spectral_filter.config.frequency_source == 'map_planarity':
        return MapPlanaritySource(spectral_filter)
    return ScanSource(spectral_filter)
