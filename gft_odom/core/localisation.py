"""Localisation in a map of an earlier day: the map a drive leaves, and each scan matched to it.

Odometry drifts with distance; a map saved on an earlier drive of the same block does not.
`DriveMap` keeps what a drive saw, voxel by voxel (the first point of each voxel, as the
odometry's map keeps the oldest view), with each point's graph frequency and any per-point
attribute a caller adds (the simulator's surface class, for the oracle). `PriorMap` is such a
map loaded for matching (normals and a search index, built once). `Localiser` registers every
scan against it from the odometry's prediction: the pose in the map frame is
`T_map_odom @ T_odom_sensor`, and a trusted match moves `T_map_odom` (REP 105: localisation
owns map -> odom, the odometry odom -> base_link). A scan that does not fit leaves
`T_map_odom` as it was: the odometry carries the pose until the map fits again.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from gft_odom.core.geometry import invert_transform, rotation_vector, transform_points
from gft_odom.core.registration.config import RegistrationConfig
from gft_odom.core.registration.local_map import KEYFRAME_ROTATION_RAD, NORMAL_NEIGHBOURS
from gft_odom.core.registration.matching import MapTarget, point_to_plane_icp
from gft_odom.core.registration.sweep import smoothness_from_nu
from gft_odom.core.registration.uncertainty import PoseUncertainty, icp_information
from gft_odom.core.registration.voxels import voxel_downsample_indices, voxel_keys
from gft_odom.errors import RegistrationError

# The map's voxel, as the odometry's map (registration.map_voxel_size_m's default).
MAP_VOXEL_M = 0.3
# The scan's source voxel, as the odometry's (registration.voxel_size_m's default).
SOURCE_VOXEL_M = 0.4
# Match: pairs within this gate, Tukey scale, iterations (the odometry's defaults).
GATE_M = 1.0
KERNEL_M = 0.3
ITERATIONS = 30
# A match is trusted when this share of the scan has a map point within the gate and it moves
# the prediction by no more than this (the odometry's drift between scans is millimetres).
MIN_FITNESS = 0.3
MAX_CORRECTION_M = 0.5
MAX_CORRECTION_RAD = 0.1
MIN_POINTS = 100
# A rough point's weight in localisation (a smooth one's is 1).
ROUGH_WEIGHT = 0.25
# A drive map stops growing here (36 bytes a point with its key, 180 MB).
MAX_DRIVE_MAP_POINTS = 5_000_000
# A fit's covariance: the odometry's floor and prior (registration.min_std_*, fallback_std_*).
UNCERTAINTY = PoseUncertainty.from_config(RegistrationConfig())


class DriveMap:
    """The points a drive saw, one per voxel (the first to arrive), in the odometry's world
    frame, with their frequency (NaN: none) and optional named per-point attributes.

    Buffers double as they fill and the voxel keys stay sorted, so adding a keyframe costs a
    copy of the keys, not of the map: about 20 ms a keyframe at 2.8 M points (measured on a
    loaded 2-core machine; a 150 m drive leaves about 150 000).
    """

    def __init__(self, voxel_m: float = MAP_VOXEL_M, max_points: int = MAX_DRIVE_MAP_POINTS
                 ) -> None:
        self.voxel_m = float(voxel_m)
        self.max_points = int(max_points)
        self._keys = np.zeros(0, dtype=np.int64)  # sorted
        self._points = np.zeros((0, 3))
        self._nu = np.zeros(0, dtype=np.float32)
        self._attributes: dict[str, np.ndarray] = {}
        self._n = 0
        self.full = False  # max_points reached: later points are not kept
        self._last_scan_pose: np.ndarray | None = None

    def __len__(self) -> int:
        return self._n

    @property
    def points_xyz(self) -> np.ndarray:
        """(N, 3) world."""
        return self._points[:self._n]

    @property
    def nu(self) -> np.ndarray:
        """(N,) float32 graph frequency, NaN where none."""
        return self._nu[:self._n]

    @property
    def attributes(self) -> dict[str, np.ndarray]:
        """name -> (N,) values."""
        return {name: values[:self._n] for name, values in self._attributes.items()}

    def due(self, T_world_sensor: np.ndarray, every_m: float) -> bool:
        """Whether a scan at `T_world_sensor` is `every_m` or a keyframe's turn from the last
        scan added (`add_scan`): the map takes a scan where the odometry takes a keyframe."""
        if self._last_scan_pose is None:
            return True
        step = invert_transform(self._last_scan_pose) @ T_world_sensor
        return bool(np.linalg.norm(step[:3, 3]) >= every_m or np.linalg.norm(
            rotation_vector(step[:3, :3])) >= KEYFRAME_ROTATION_RAD)

    def add_scan(self, T_world_sensor: np.ndarray, points_sensor: np.ndarray,
                 nu: np.ndarray | None = None, **attributes: np.ndarray) -> int:
        """Add a scan (deskewed, sensor frame) seen from `T_world_sensor`."""
        self._last_scan_pose = np.array(T_world_sensor, dtype=float)
        return self.add(transform_points(T_world_sensor, points_sensor), nu, **attributes)

    def add(self, points_world: np.ndarray, nu: np.ndarray | None = None,
            **attributes: np.ndarray) -> int:
        """Add the points of voxels not yet seen; returns how many were new."""
        points = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if self._n and set(attributes) != set(self._attributes):
            raise RegistrationError(f'a drive map with attributes {sorted(self._attributes)} '
                                    f'was given {sorted(attributes)}')
        first = voxel_downsample_indices(points, self.voxel_m)
        keys = voxel_keys(points[first], self.voxel_m)
        at = np.searchsorted(self._keys, keys)
        seen = np.zeros(keys.size, dtype=bool)
        if self._keys.size:
            seen = self._keys[np.minimum(at, self._keys.size - 1)] == keys
        room = self.max_points - self._n
        new = first[~seen][:max(room, 0)]
        self.full = self.full or new.size < int((~seen).sum())
        if not new.size:
            return 0
        self._grow(self._n + new.size, attributes)
        end = self._n + new.size
        self._points[self._n:end] = points[new]
        self._nu[self._n:end] = np.nan if nu is None else np.asarray(nu, np.float32)[new]
        for name, values in attributes.items():
            self._attributes[name][self._n:end] = np.asarray(values)[new]
        self._n = end
        new_keys = np.sort(keys[~seen][:new.size])
        self._keys = np.insert(self._keys, np.searchsorted(self._keys, new_keys), new_keys)
        return int(new.size)

    def _grow(self, size: int, attributes: dict[str, np.ndarray]) -> None:
        if size <= self._points.shape[0]:
            return
        capacity = max(size, 2 * self._points.shape[0], 4096)
        self._points = np.resize(self._points, (capacity, 3))
        self._nu = np.resize(self._nu, capacity)
        for name, values in attributes.items():
            old = self._attributes.get(name, np.zeros(0, dtype=np.asarray(values).dtype))
            self._attributes[name] = np.resize(old, capacity)


@dataclass
class PriorMap:
    """A map of an earlier day, ready to match against: points (map frame), normals, index."""

    points_xyz: np.ndarray
    nu: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    target: MapTarget | None = None

    def __post_init__(self) -> None:
        self.points_xyz = np.ascontiguousarray(self.points_xyz, dtype=np.float64)
        if self.points_xyz.shape[0] < MIN_POINTS:
            raise RegistrationError(f'a prior map needs at least {MIN_POINTS} points, it has '
                                    f'{self.points_xyz.shape[0]}')
        if self.target is None:
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points_xyz))
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
            self.target = MapTarget(self.points_xyz, np.asarray(cloud.normals))

    @classmethod
    def from_drive_map(cls, drive_map: DriveMap) -> 'PriorMap':
        """The map a drive left, as it is."""
        return cls(drive_map.points_xyz, drive_map.nu, dict(drive_map.attributes))

    def weighted(self, weights: np.ndarray) -> 'PriorMap':
        """The same map, each point's residuals weighed by `weights`."""
        target = MapTarget(self.points_xyz, self.target.normals, self.target.tree,
                           np.asarray(weights, dtype=float))
        return PriorMap(self.points_xyz, self.nu, self.attributes, target)

    def selected(self, keep: np.ndarray) -> 'PriorMap':
        """The map of the points `keep` (bool mask), normals kept as the whole map gave them."""
        keep = np.asarray(keep, dtype=bool)
        target = MapTarget(self.points_xyz[keep], self.target.normals[keep])
        return PriorMap(self.points_xyz[keep], self.nu[keep],
                        {k: v[keep] for k, v in self.attributes.items()}, target)


@dataclass
class LocalisationResult:
    """One scan localised: its pose in the map frame, the map -> odom transform, the fit."""

    T_map_sensor: np.ndarray
    T_map_odom: np.ndarray
    fitness: float
    inlier_rmse_m: float
    status: str  # 'localised', 'not_fitted' (odometry carried the pose), 'too_few_points'
    correction_m: float = 0.0  # how far the match moved the prediction
    # (6, 6) of the pose (x, y, z, rot_x, rot_y, rot_z; map axes, about the sensor), from the
    # final pairs as the odometry's; the inflated prior when the map did not fit.
    covariance: np.ndarray = field(default_factory=lambda: np.diag(UNCERTAINTY.fallback_var))


class Localiser:
    """Each scan matched to a prior map from the odometry's prediction."""

    def __init__(self, prior: PriorMap, T_map_odom: np.ndarray) -> None:
        self.prior = prior
        self.T_map_odom = np.array(T_map_odom, dtype=float)
        self.n_localised = 0
        self.n_not_fitted = 0

    def localise(self, points_sensor: np.ndarray, T_odom_sensor: np.ndarray,
                 keep: np.ndarray | None = None, weights: np.ndarray | None = None
                 ) -> LocalisationResult:
        """Match the scan `points_sensor` (deskewed to its stamp) whose odometry pose is
        `T_odom_sensor`; `keep` (bool per point) restricts the points matched, `weights` (per
        point) weighs their residuals."""
        points = np.asarray(points_sensor, dtype=np.float64).reshape(-1, 3)
        source_index = voxel_downsample_indices(points, SOURCE_VOXEL_M)
        if keep is not None:
            source_index = source_index[np.asarray(keep, dtype=bool)[source_index]]
        T_pred = self.T_map_odom @ T_odom_sensor
        if source_index.size < MIN_POINTS:
            self.n_not_fitted += 1
            return LocalisationResult(T_pred, self.T_map_odom.copy(), 0.0, 0.0,
                                      'too_few_points')
        fit = point_to_plane_icp(np.ascontiguousarray(points[source_index]), self.prior.target,
                                 T_pred, GATE_M, ITERATIONS, KERNEL_M,
                                 None if weights is None else np.asarray(weights)[source_index])
        delta = invert_transform(T_pred) @ fit.transformation
        moved_m = float(np.linalg.norm(delta[:3, 3]))
        turned_rad = float(np.arccos(np.clip(0.5 * (np.trace(delta[:3, :3]) - 1.0), -1.0, 1.0)))
        trusted = (np.all(np.isfinite(fit.transformation)) and fit.fitness >= MIN_FITNESS
                   and moved_m <= MAX_CORRECTION_M and turned_rad <= MAX_CORRECTION_RAD)
        if not trusted:
            self.n_not_fitted += 1
            return LocalisationResult(T_pred, self.T_map_odom.copy(), fit.fitness,
                                      fit.inlier_rmse, 'not_fitted', moved_m)
        self.T_map_odom = fit.transformation @ invert_transform(T_odom_sensor)
        self.n_localised += 1
        information = icp_information(points[source_index], self.prior.target, fit,
                                      fit.inlier_rmse)
        covariance = UNCERTAINTY.covariance('localised', information,
                                            fit.transformation[:3, :3])
        return LocalisationResult(fit.transformation, self.T_map_odom.copy(), fit.fitness,
                                  fit.inlier_rmse, 'localised', moved_m, covariance)



class MapLocalisation:
    """Localisation beside the odometry, in its frames (what the node and the replay hold).

    The odometry gives `T_world_sensor` (world: the first sensor frame); its odom frame is
    the first base frame, so `T_odom_sensor = T_base_sensor @ T_world_sensor`. The map is in
    the odom frame of the run that saved it. Until a pose in the map is set (a parameter,
    `/initialpose`) nothing is localised.
    """

    def __init__(self, prior: PriorMap, T_base_sensor: np.ndarray) -> None:
        # A map with frequencies weighs its points by smoothness (a map without, every point
        # alike, as --no-filter): what stays from day to day counts most.
        self.prior = (prior.weighted(smoothness_weights(prior.nu))
                      if np.isfinite(prior.nu).any() else prior)
        self.T_base_sensor = np.asarray(T_base_sensor, dtype=float)
        self.localiser: Localiser | None = None
        self._start: np.ndarray | None = None

    def start_at(self, T_map_base: np.ndarray) -> None:
        """The robot is at `T_map_base` at the next scan (a start parameter, `/initialpose`)."""
        self._start = np.asarray(T_map_base, dtype=float)

    def set_pose(self, T_map_base: np.ndarray, T_world_sensor: np.ndarray) -> None:
        """The robot is at `T_map_base` now, when the odometry's pose is `T_world_sensor`."""
        T_map_sensor = np.asarray(T_map_base, dtype=float) @ self.T_base_sensor
        T_map_odom = T_map_sensor @ invert_transform(self.T_base_sensor @ T_world_sensor)
        self.localiser = Localiser(self.prior, T_map_odom)

    def localise(self, points_sensor: np.ndarray, T_world_sensor: np.ndarray,
                 nu: np.ndarray | None = None) -> LocalisationResult | None:
        """The scan (deskewed, sensor frame) whose odometry pose is `T_world_sensor`, in the
        map; None until a pose is set."""
        if self._start is not None:
            self.set_pose(self._start, T_world_sensor)
            self._start = None
        if self.localiser is None:
            return None
        weights = None if nu is None else smoothness_weights(nu)
        return self.localiser.localise(points_sensor, self.T_base_sensor @ T_world_sensor,
                                       weights=weights)

    def base_pose(self, result: LocalisationResult) -> np.ndarray:
        """T_map_base of a localised scan."""
        return result.T_map_sensor @ invert_transform(self.T_base_sensor)


def smoothness_weights(nu: np.ndarray) -> np.ndarray:
    """A point's weight in the match by its graph frequency: rough (canopy, no spectrum)
    ROUGH_WEIGHT, smooth (ground, trunks, posts) 1. On hedged days it cut the error against
    the map 52-87 % and cost at most 3 % where the canopy had not changed (teach_repeat.md)."""
    return ROUGH_WEIGHT + (1.0 - ROUGH_WEIGHT) * smoothness_from_nu(nu, unknown=0.0)


def planar_pose(x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
    """T of a pose on the ground (x, y, yaw): what an operator gives as a start."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = (x_m, y_m)
    return T
