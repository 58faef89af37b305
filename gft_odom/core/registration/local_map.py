"""The local map a scan is matched against: a window of recent keyframes, the anchors that
outlive it, and the view rule that serves them.

The map is the union of the last `max_keyframes` keyframes (deskewed scans in the world
frame, taken every `keyframe_distance_m` or KEYFRAME_ROTATION_RAD), voxelised (a voxel keeps the
point of the oldest keyframe that saw it: the map stays anchored to what was seen first) and
cropped to a radius around the newest keyframe. It is rebuilt only when a keyframe is added,
so its normals and search index are computed once per keyframe, not once per scan.

Anchors: when a keyframe leaves the window its points stay in the map (while within range),
so a row met again after the window has moved on registers against what it showed before.

The view rule: a point is served only to a keyframe that sees it from within VIEW_RAD of the
side it was measured from (its beam seen backwards), window and anchors alike. Porous canopy
seen from the far lane is another cloud, a metre or two away, that pulls a scan sideways; a
trunk's far face is another surface too. A fixed draw of ANY_SIDE_SHARE of the voxels is served
from any side. A smooth point (graph frequency: ground, trunks, posts) takes over an anchor
voxel held by a rough one (canopy).
"""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d

from gft_odom.core.geometry import rotation_vector
from gft_odom.core.registration.anchors import AnchorStore
from gft_odom.core.registration.matching import MapTarget, to_cloud
from gft_odom.core.registration.voxels import (
    voxel_downsample_indices,
    voxel_draw,
    voxel_keys,
    voxel_x_slab,
)

# A keyframe also when the sensor turned this much since the last one.
KEYFRAME_ROTATION_RAD = 0.2
# The kNN of a map point's normal (the point itself included).
NORMAL_NEIGHBOURS = 15
# Smoothness (graph frequency nu / SMOOTH_NU, in [0, 1]) at which a point counts as smooth.
ANCHOR_SMOOTHNESS = 0.75
# Memory bound of a long run (~64 bytes a point); beyond it the farthest anchors go.
ANCHOR_MAX_POINTS = 2_000_000
# A point is served from within this angle of the side it was measured from.
VIEW_RAD = math.radians(60.0)
# This share of the voxels (a fixed draw by voxel) is served from any side as well.
ANY_SIDE_SHARE = 0.25


class LocalMap:
    """Sliding window of keyframes and their anchors in the world frame."""

    def __init__(self, voxel_size_m: float, max_range_m: float, max_points: int,
                 max_keyframes: int, keyframe_distance_m: float):
        self.voxel_size_m = voxel_size_m
        self.max_range_m = max_range_m
        self.max_points = max_points
        self.max_keyframes = max_keyframes
        self.keyframe_distance_m = keyframe_distance_m
        self._anchors = AnchorStore()
        # (T_world_sensor, world points, smoothness or None) per keyframe, oldest first.
        self._keyframes: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        self.cloud = o3d.geometry.PointCloud()
        self._target: MapTarget | None = None

    def __len__(self) -> int:
        return len(self.cloud.points)

    def clear(self) -> None:
        """Drop every keyframe and anchor."""
        self._keyframes.clear()
        self._anchors.clear()
        self.cloud = o3d.geometry.PointCloud()
        self._target = None

    @property
    def points_xyz(self) -> np.ndarray:
        """The map points served (world frame)."""
        return np.asarray(self.cloud.points)

    @property
    def n_anchors(self) -> int:
        """Points kept after their keyframe left the window (all of them, in range or not)."""
        return len(self._anchors)

    def target(self) -> MapTarget:
        """The map as the matcher's target (its search index built once per rebuild)."""
        if self._target is None:
            normals = (np.asarray(self.cloud.normals) if self.cloud.has_normals()
                       else np.zeros((len(self), 3)))
            self._target = MapTarget(np.asarray(self.cloud.points), normals)
        return self._target

    def share_near(self, points_world: np.ndarray, distance_m: float) -> float:
        """The share of `points_world` with a map point within `distance_m` (0 for none)."""
        if not points_world.shape[0] or not len(self):
            return 0.0
        distance, _ = self.target().tree.query(points_world, distance_upper_bound=distance_m)
        return float(np.mean(np.isfinite(distance)))

    def needs_keyframe(self, T_world_sensor: np.ndarray) -> bool:
        """True when the sensor moved or turned enough since the last keyframe."""
        if not self._keyframes:
            return True
        T_last = self._keyframes[-1][0]
        if np.linalg.norm(T_world_sensor[:3, 3] - T_last[:3, 3]) >= self.keyframe_distance_m:
            return True
        R_rel = T_last[:3, :3].T @ T_world_sensor[:3, :3]
        return np.linalg.norm(rotation_vector(R_rel)) >= KEYFRAME_ROTATION_RAD

    def add_keyframe(self, points_world: np.ndarray, T_world_sensor: np.ndarray,
                     smoothness: np.ndarray | None = None) -> None:
        """Store a keyframe (world-frame points, optional per-point smoothness in [0, 1]; NaN
        or None: unknown) and rebuild the map around it."""
        keep = voxel_downsample_indices(points_world, self.voxel_size_m)
        if len(self._keyframes) >= self.max_keyframes:
            self._anchor(self._keyframes.pop(0), T_world_sensor[:3, 3])
        self._keyframes.append((T_world_sensor.copy(), points_world[keep],
                                None if smoothness is None else smoothness[keep]))
        self.cloud = self._rebuilt(T_world_sensor[:3, 3].copy())
        self._target = None

    def _anchor(self, keyframe, centre_xyz: np.ndarray) -> None:
        """Keep the points of a keyframe leaving the window, one per voxel (the smoothest).
        A filled voxel keeps its older anchor, unless that one is rough and the new one
        smooth (a trunk first seen far off, as rough, is later seen near). Over
        ANCHOR_MAX_POINTS the farthest from `centre_xyz` are dropped."""
        T, points, smoothness = keyframe
        if smoothness is None:  # no frequency: nothing is known to be smooth
            smoothness = np.full(points.shape[0], np.nan)
        chosen = np.arange(points.shape[0])
        keys = voxel_keys(points, self.voxel_size_m)
        order = np.lexsort((-np.nan_to_num(smoothness, nan=-np.inf), keys))
        keys, first = np.unique(keys[order], return_index=True)
        chosen = chosen[order][first]
        known, anchored_smoothness = self._anchors.find(keys)
        viewpoints = np.broadcast_to(T[:3, 3], (chosen.shape[0], 3))
        if known.any():
            upgrade = (known & _is_smooth(smoothness[chosen])
                       & ~_is_smooth(anchored_smoothness))
            self._anchors.replace(keys[upgrade], points[chosen[upgrade]],
                                  smoothness[chosen[upgrade]], viewpoints[upgrade])
        new = ~known
        self._anchors.add(keys[new], points[chosen[new]], smoothness[chosen[new]],
                          viewpoints[new])
        self._anchors.keep_nearest(centre_xyz, ANCHOR_MAX_POINTS)

    def _served_from_its_side(self, points: np.ndarray, viewpoints: np.ndarray,
                              centre_xyz: np.ndarray) -> np.ndarray:
        """Which points a keyframe at `centre_xyz` is served: seen from within VIEW_RAD of
        the direction each was measured from, or in the any-side share."""
        to_view = viewpoints - points
        to_centre = centre_xyz - points
        dot = np.einsum('ij,ij->i', to_view, to_centre)
        norms = np.sqrt(np.einsum('ij,ij->i', to_view, to_view)
                        * np.einsum('ij,ij->i', to_centre, to_centre))
        served = dot >= np.cos(VIEW_RAD) * norms
        served |= voxel_draw(points, self.voxel_size_m) < ANY_SIDE_SHARE
        return served

    def _served_keyframe(self, T: np.ndarray, points: np.ndarray,
                         centre_xyz: np.ndarray) -> np.ndarray:
        """A keyframe's points served to `centre_xyz`: within the map's radius (the crop that
        follows would drop the rest) and from their side."""
        offset = points - centre_xyz
        near = np.flatnonzero(np.einsum('ij,ij->i', offset, offset) <= self.max_range_m ** 2)
        viewpoints = np.broadcast_to(T[:3, 3], (near.shape[0], 3))
        return points[near[self._served_from_its_side(points[near], viewpoints, centre_xyz)]]

    def _rebuilt(self, centre_xyz: np.ndarray) -> o3d.geometry.PointCloud:
        """The map of the window and the anchors around `centre_xyz`, with its normals."""
        # The first point of a voxel wins: anchors first (the oldest content), then the
        # keyframes oldest first.
        parts = [self._served_keyframe(T, points, centre_xyz)
                 for T, points, _ in self._keyframes]
        if self.n_anchors:
            points, _, viewpoints = self._anchors.in_slab(
                *voxel_x_slab(centre_xyz[0], self.max_range_m, self.voxel_size_m))
            parts = [points[self._served_from_its_side(points, viewpoints, centre_xyz)]] + parts
        merged = np.concatenate(parts)
        d2 = np.einsum('ij,ij->i', merged - centre_xyz, merged - centre_xyz)
        index = np.flatnonzero(d2 <= self.max_range_m ** 2)
        index = index[voxel_downsample_indices(merged[index], self.voxel_size_m)]
        if index.shape[0] > self.max_points:
            # Keep the nearest points: registration is best conditioned close to the sensor.
            index = index[np.argpartition(d2[index], self.max_points - 1)[:self.max_points]]
        cloud = to_cloud(merged[index])
        if index.shape[0] >= 3:
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
        return cloud


def _is_smooth(smoothness: np.ndarray) -> np.ndarray:
    """At or above the anchors' smoothness threshold (NaN: never)."""
    return np.asarray(smoothness) >= ANCHOR_SMOOTHNESS
