"""Voxel downsampling and a bounded local map of recent keyframes, for scan-to-map ICP.

The map is the union of the last few keyframes (deskewed scans in the world frame, taken every
`keyframe_distance_m` or `keyframe_rotation_rad`), voxelised and cropped to a radius around the
newest keyframe. It is rebuilt only when a keyframe is added, so its normals and GICP
covariances (the expensive part) are computed once per keyframe, not once per scan.

Anchors (`anchor_smoothness` set): when a keyframe leaves the window, its smooth points
(ground, trunks, posts: what looks the same from any side) stay in the map as anchors for as
long as they are within range; its canopy goes with it. A row met again from its other side
then registers against what it showed before, not against foliage seen from elsewhere.

Rough anchors (`rough_anchor_view_rad` set as well): the rest of a leaving keyframe (canopy,
and every point when no frequency is known) stays too, but is served only while the newest
keyframe sees it from about the side it was measured from (within that angle of its beam
seen backwards). Porous canopy returns depend on where they were seen from: the crown's
other face is a different cloud, a metre or two away, that pulls a scan from the far lane
sideways. Smooth points look the same from every side and are served from anywhere.

Background rebuilds (`add_keyframe(..., background=True)`): the window changes at once, the
merge and every normal are computed on a thread of their own (numpy and open3d's tensor
normals, which let the interpreter run the next scan's match meanwhile; the legacy
`estimate_normals` would hold it), and the map served stays the previous one until `adopt`.
The caller chooses when it adopts, so the poses do not depend on how fast the thread was.
"""

from __future__ import annotations

import threading
import time
from typing import Callable, NamedTuple

import numpy as np
import open3d as o3d

from gft_odom.core.anchors import AnchorStore
from gft_odom.core.gauss_newton import MapTarget
from gft_odom.core.geometry import rotation_vector
from gft_odom.core.residuals import smoothness_from_covariances

# Which keyframe a full map drops: the oldest (a sliding window in time) or the one farthest
# from the newest keyframe (a window in space: revisited places keep their old keyframes).
KEYFRAME_EVICTIONS = ('oldest', 'farthest')
# Which point a map voxel seen by several keyframes keeps: the newest keyframe's, or the
# oldest's (the map then stays anchored to what was seen first, as a voxel map that never
# replaces a filled voxel).
# 'nearest': the point measured from the closest sensor position (the sharpest view of a
# crown or a trunk; docs/registration.md: the map seen only from behind biases along rows).
# 'mean': the centroid of every point the window's keyframes (and anchors) put in the voxel,
# a distribution of all the views instead of one view (the bias study's candidate fix).
# 'mean_rough': the frequency decides: a voxel whose points are smooth on average (ground,
# trunks: one surface, the same from any side) keeps its oldest point, a rough one (canopy,
# whose returns depend on where it was seen from) the mean of its views.
VOXEL_KEEPS = ('newest', 'oldest', 'nearest', 'mean', 'mean_rough')


# Voxel keys: 21 bits per axis, each index offset by 2^20; x is the major axis.
_KEY_OFFSET = 1 << 20
_KEY_X_SHIFT = 42


def voxel_keys(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """One int64 key per point naming its voxel (21 bits per axis, +-1e6 voxels)."""
    ijk = np.floor(points_xyz / voxel_size_m).astype(np.int64) + _KEY_OFFSET
    return (ijk[:, 0] << _KEY_X_SHIFT) | (ijk[:, 1] << 21) | ijk[:, 2]


def voxel_draw(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """A number in [0, 1) per point, fixed by its voxel (a multiplicative hash of the key):
    a share drawn by it is the same voxels at every rebuild."""
    mixed = voxel_keys(points_xyz, voxel_size_m).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    return (mixed >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def voxel_x_slab(x_m: float, radius_m: float, voxel_size_m: float) -> tuple[int, int]:
    """[lo, hi) of the voxel keys of every voxel within `radius_m` of `x_m` along x (sorted
    keys hold them in one run), with one voxel of margin either side against rounding."""
    lo, hi = (np.floor((x_m + np.array([-1.0, 1.0]) * radius_m) / voxel_size_m)
              .astype(np.int64) + _KEY_OFFSET)
    return (int(lo) - 1) << _KEY_X_SHIFT, (int(hi) + 2) << _KEY_X_SHIFT


def voxel_downsample_indices(points_xyz: np.ndarray, voxel_size_m: float,
                             priority: np.ndarray | None = None) -> np.ndarray:
    """Indices of one point per occupied voxel, in input order: the first point, or with
    `priority` (N,) the point of highest priority (the first among equals).

    A real point rather than a centroid: it keeps a real measurement and its per-point time.
    """
    if points_xyz.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    keys = voxel_keys(points_xyz, voxel_size_m)
    if priority is None:
        # The smallest input index of each run of equal keys: an unstable sort and a
        # reduceat, a third of the time of np.unique's stable sort (the same indices).
        order = np.argsort(keys)
        sorted_keys = keys[order]
        head = np.empty(sorted_keys.shape[0], dtype=bool)
        head[0] = True
        np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=head[1:])
        return np.sort(np.minimum.reduceat(order, np.flatnonzero(head)))
    order = np.lexsort((-np.nan_to_num(np.asarray(priority, dtype=np.float64), nan=-np.inf),
                        keys))
    sorted_keys = keys[order]
    head = np.r_[True, sorted_keys[1:] != sorted_keys[:-1]]
    return np.sort(order[head])


def voxel_means(points_xyz: np.ndarray, voxel_size_m: float, *values: np.ndarray
                ) -> tuple[np.ndarray, ...]:
    """The centroid of each occupied voxel, in voxel-key order, the mean of each of
    `values` (N,) or (N, k) over the voxel's points (NaN entries left out; NaN where all are),
    and the index of each voxel's first point."""
    keys = voxel_keys(points_xyz, voxel_size_m)
    _, first, group, count = np.unique(keys, return_index=True, return_inverse=True,
                                       return_counts=True)
    group = group.ravel()

    def mean(v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=np.float64)
        flat = v.reshape(v.shape[0], -1)
        known = np.isfinite(flat)
        out = np.empty((count.shape[0], flat.shape[1]))
        for j in range(flat.shape[1]):  # a column at a time (3 at most)
            n = np.bincount(group, known[:, j], minlength=count.shape[0])
            total = np.bincount(group, np.where(known[:, j], flat[:, j], 0.0),
                                minlength=count.shape[0])
            with np.errstate(invalid='ignore', divide='ignore'):
                out[:, j] = total / n
        return out.reshape((count.shape[0],) + v.shape[1:])

    return (mean(points_xyz),) + tuple(mean(v) for v in values) + (first,)


def to_cloud(points_xyz: np.ndarray) -> o3d.geometry.PointCloud:
    """numpy (N, 3) -> open3d cloud."""
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points_xyz)))


def _normals_releasing_the_interpreter(points_xyz: np.ndarray, neighbours: int
                                       ) -> np.ndarray | None:
    """(n, 3) kNN PCA normals, the ones `PointCloud.estimate_normals` gives (to the sign),
    from open3d's tensor API: it releases the GIL, the legacy call holds it throughout.
    None for fewer than 3 points (as a cloud that small gets none: estimated on demand)."""
    if points_xyz.shape[0] < 3:
        return None
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(points_xyz)))
    cloud.estimate_normals(max_nn=neighbours)
    return cloud.point.normals.numpy().astype(float, copy=False)


class _CostPerPoint:
    """The seconds a point costs, per kind of map work: a moving average of its runs."""

    SMOOTHING = 0.3

    def __init__(self) -> None:
        self._seconds: dict[str, float] = {}

    def observe(self, kind: str, seconds: float, n_points: int) -> None:
        if n_points <= 0:
            return
        per_point = seconds / n_points
        before = self._seconds.get(kind)
        self._seconds[kind] = (per_point if before is None
                               else before + self.SMOOTHING * (per_point - before))

    def predict(self, kinds: tuple[str, ...], n_points: int) -> float | None:
        """The seconds `kinds` together would take for `n_points`; None before each ran."""
        if any(kind not in self._seconds for kind in kinds):
            return None
        return n_points * sum(self._seconds[kind] for kind in kinds)


class _Served(NamedTuple):
    """What a rebuild serves: the cloud, per point the smoothness of the scan point it came
    from (None when unknown) and where the sensor stood, and (background) its target."""

    cloud: o3d.geometry.PointCloud
    smoothness: np.ndarray | None
    viewpoints: np.ndarray
    target: MapTarget | None = None


class _Worker:
    """One function at a time on a thread; its result (or its exception) when waited for."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._outcome: tuple = (None, None)

    @property
    def pending(self) -> bool:
        return self._thread is not None

    def submit(self, work: Callable[[], object]) -> None:
        if self._thread is not None:
            raise RuntimeError('a map rebuild is already in flight')

        def run() -> None:
            try:
                self._outcome = (work(), None)
            except BaseException as exc:  # handed to the waiting thread
                self._outcome = (None, exc)
        self._thread = threading.Thread(target=run, name='gft_odom-map', daemon=True)
        self._thread.start()

    def wait(self):
        """The result of the work submitted last (re-raises its exception)."""
        thread, self._thread = self._thread, None
        thread.join()
        (result, exc), self._outcome = self._outcome, (None, None)
        if exc is not None:
            raise exc
        return result


class LocalMap:
    """Sliding window of keyframes in the world frame, served as one open3d cloud."""

    def __init__(self, voxel_size_m: float, max_range_m: float, max_points: int,
                 max_keyframes: int, keyframe_distance_m: float, keyframe_rotation_rad: float,
                 normal_neighbours: int, with_normals: bool = True,
                 with_covariances: bool = False, eviction: str = 'oldest',
                 voxel_keeps: str = 'oldest', anchor_smoothness: float | None = None,
                 anchor_max_points: int = 2_000_000,
                 rough_anchor_view_rad: float | None = None,
                 rough_anchor_any_side_share: float = 0.0,
                 rough_window_view_rad: float | None = None,
                 smooth_view_rad: float | None = None):
        self.voxel_size_m = voxel_size_m
        self.max_range_m = max_range_m
        self.max_points = max_points
        self.keyframe_distance_m = keyframe_distance_m
        self.keyframe_rotation_rad = keyframe_rotation_rad
        self.normal_neighbours = normal_neighbours
        self.with_normals = with_normals
        # Without `with_normals`: True estimates a point's normal once, when it enters the
        # served map, and keeps it while the point stays ('kept'); False estimates it when a
        # pair first asks, carried over only while its neighbourhood stays ('on_demand').
        self.keep_normals = False
        # With `with_normals`: True estimates them at a rebuild only when they fit before
        # the rebuild's `normals_due_s` (their measured cost per point), else leaves them to
        # the pairs as without ('in_time').
        self.normals_in_time = False
        self.normals_slack_s = 0.0  # how late past `normals_due_s` they may still end
        self._seconds_per_point = _CostPerPoint()
        self.n_rebuilds_left_to_pairs = 0  # 'in_time' rebuilds whose normals did not fit
        # Such a rebuild's deadline and centre: its target estimates what it can before.
        self._normals_left: tuple[float, np.ndarray] | None = None
        self.with_covariances = with_covariances
        if eviction not in KEYFRAME_EVICTIONS:
            raise ValueError(f'eviction must be one of {KEYFRAME_EVICTIONS}, got {eviction!r}')
        self.eviction = eviction
        if voxel_keeps not in VOXEL_KEEPS:
            raise ValueError(f'voxel_keeps must be one of {VOXEL_KEEPS}, got {voxel_keeps!r}')
        self.voxel_keeps = voxel_keeps
        self.max_keyframes = max_keyframes
        # Smoothness (in [0, 1]) at which a point outlives its keyframe; None: no anchors.
        self.anchor_smoothness = anchor_smoothness
        # Memory bound of a long run: beyond it the anchors farthest from the sensor go.
        self.anchor_max_points = anchor_max_points
        # Rough points stay too, served only when seen from within this angle of where they
        # were measured from; None: rough points leave with their keyframe.
        self.rough_anchor_view_rad = rough_anchor_view_rad
        # This share of the rough anchors (a fixed draw by voxel) is served from any side too.
        self.rough_anchor_any_side_share = rough_anchor_any_side_share
        # The window's rough points (every point of a keyframe without frequencies) served by
        # the same rule as rough anchors: from within this angle of where they were measured
        # from, or in the any-side share; None: the window serves every point.
        self.rough_window_view_rad = rough_window_view_rad
        # Where those rules serve points, smooth ones too only from within this angle of
        # their side (a trunk's far face is another surface too); None: from any side.
        self.smooth_view_rad = smooth_view_rad
        self._anchors = AnchorStore()
        # Set (surface variation of a rough neighbourhood) when a model reads the map's
        # planarity: the served target then carries a smoothness per map point.
        self.smoothness_variation: float | None = None
        self._keyframes: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        self.cloud = o3d.geometry.PointCloud()
        # Per served point: the smoothness of the scan point it came from (None when a
        # keyframe came without one); the solver matches like with like when it has it.
        self.smoothness: np.ndarray | None = None
        # Per served point: where the sensor stood when it was measured (its beam's origin).
        self.viewpoints = np.zeros((0, 3))
        self._target: MapTarget | None = None
        self._previous_target: MapTarget | None = None
        self._worker = _Worker()

    def __len__(self) -> int:
        return len(self.cloud.points)

    def clear(self) -> None:
        """Drop every keyframe (and a rebuild in flight)."""
        if self._worker.pending:
            try:
                self._worker.wait()
            except Exception:  # noqa: BLE001 - what it built is dropped anyway
                pass
        self._keyframes.clear()
        self._anchors.clear()
        self.cloud = o3d.geometry.PointCloud()
        self.smoothness = None
        self.viewpoints = np.zeros((0, 3))
        self._target = None
        self._previous_target = None
        self._normals_left = None

    def target(self) -> MapTarget:
        """The map as the solvers' target (KD-tree built once per rebuild; without
        `with_normals` its normals are estimated as pairs ask for them)."""
        if self._target is None:
            smoothness = None
            if self.smoothness_variation is not None:  # with_covariances is set with it
                covariances = (np.asarray(self.cloud.covariances)
                               if self.cloud.has_covariances() else np.zeros((len(self), 3, 3)))
                smoothness = smoothness_from_covariances(covariances, self.smoothness_variation)
            t0 = time.perf_counter()
            self._target = MapTarget(np.asarray(self.cloud.points),
                                     np.asarray(self.cloud.normals)
                                     if self.cloud.has_normals() else None, smoothness,
                                     point_smoothness=self.smoothness,
                                     viewpoints=self.viewpoints,
                                     normal_neighbours=self.normal_neighbours)
            self._seconds_per_point.observe('tree', time.perf_counter() - t0, len(self))
            previous, self._previous_target = self._previous_target, None
            if previous is not None:
                self._target.inherit_normals(previous, self._index_of(previous.points),
                                             kept=self.keep_normals)
            if self.keep_normals:
                self._target.estimate_missing_normals()
            elif self._normals_left is not None:
                self._target.estimate_normals_until(*self._normals_left)
            self._normals_left = None
        return self._target

    def distances_within(self, points_world: np.ndarray, distance_m: float) -> np.ndarray:
        """Each point's distance to the nearest map point, inf beyond `distance_m`."""
        if not points_world.shape[0] or not len(self):
            return np.full(points_world.shape[0], np.inf)
        distance, _ = self.target().tree.query(points_world, distance_upper_bound=distance_m)
        return distance

    def share_near(self, points_world: np.ndarray, distance_m: float) -> float:
        """The share of `points_world` with a map point within `distance_m` (0 for none)."""
        distance = self.distances_within(points_world, distance_m)
        return float(np.mean(np.isfinite(distance))) if distance.size else 0.0

    def _index_of(self, points_xyz: np.ndarray) -> np.ndarray:
        """Each point's index in the served map, -1 where it is not there (one point per
        voxel: found by its voxel key, then checked to be the same point)."""
        served = self.points_xyz
        keys = voxel_keys(served, self.voxel_size_m)
        order = np.argsort(keys)
        wanted = voxel_keys(points_xyz, self.voxel_size_m)
        at = order[np.minimum(np.searchsorted(keys, wanted, sorter=order), keys.shape[0] - 1)]
        same = (keys[at] == wanted) & np.all(served[at] == points_xyz, axis=1)
        return np.where(same, at, -1)

    @property
    def points_xyz(self) -> np.ndarray:
        """The map points (world frame), all keyframes merged."""
        return np.asarray(self.cloud.points)

    def needs_keyframe(self, T_world_sensor: np.ndarray) -> bool:
        """True when the sensor moved or turned enough since the last keyframe."""
        if not self._keyframes:
            return True
        T_last = self._keyframes[-1][0]
        if np.linalg.norm(T_world_sensor[:3, 3] - T_last[:3, 3]) >= self.keyframe_distance_m:
            return True
        R_rel = T_last[:3, :3].T @ T_world_sensor[:3, :3]
        return np.linalg.norm(rotation_vector(R_rel)) >= self.keyframe_rotation_rad

    @property
    def rebuild_in_flight(self) -> bool:
        """A background rebuild not adopted yet (the map served is the one before it)."""
        return self._worker.pending

    def adopt(self) -> float:
        """Serve the background rebuild in flight, once it is done; the seconds waited."""
        if not self._worker.pending:
            return 0.0
        t0 = time.perf_counter()
        self._serve(self._worker.wait())
        return time.perf_counter() - t0

    def add_keyframe(self, points_world: np.ndarray, T_world_sensor: np.ndarray,
                     smoothness: np.ndarray | None = None, background: bool = False,
                     normals_due_s: float | None = None) -> None:
        """Store a keyframe (world-frame points, optional per-point smoothness in [0, 1])
        and rebuild the served cloud; `background`: on a thread, served after `adopt`;
        `normals_due_s` (`time.perf_counter` seconds; None: no deadline): with
        `normals_in_time`, when the next scan is due."""
        self.adopt()  # the window changes only once the rebuild before is served
        keep = voxel_downsample_indices(points_world, self.voxel_size_m,
                                        self._view_priority(points_world, T_world_sensor))
        if len(self._keyframes) >= self.max_keyframes:
            if self.eviction == 'farthest':
                # Keep what is near: a lane driven again, or the next lane over, stays mapped.
                where = np.array([T[:3, 3] for T, _, _ in self._keyframes])
                d2 = np.einsum('ij,ij->i', where - T_world_sensor[:3, 3],
                               where - T_world_sensor[:3, 3])
                self._anchor(self._keyframes.pop(int(np.argmax(d2))), T_world_sensor[:3, 3])
            else:
                self._anchor(self._keyframes.pop(0), T_world_sensor[:3, 3])
        self._keyframes.append((T_world_sensor.copy(), points_world[keep],
                                None if smoothness is None else smoothness[keep]))
        centre = T_world_sensor[:3, 3].copy()
        if background:
            self._worker.submit(lambda: self._rebuilt(centre, in_background=True))
        else:
            self._normals_left = None
            self._serve(self._rebuilt(centre, normals_due_s=normals_due_s))
            if self.normals_in_time and not self.cloud.has_normals() and len(self):
                self._normals_left = (normals_due_s, centre)

    @property
    def n_anchors(self) -> int:
        """Points kept after their keyframe left the window (all of them, in range or not)."""
        return len(self._anchors)

    def _anchor(self, keyframe, centre_xyz: np.ndarray) -> None:
        """Keep the smooth points of a keyframe leaving the window, and with rough anchors
        the rest too. A filled voxel keeps its older anchor, unless that one is rough and
        the new one smooth (a trunk first seen far off, as rough, is later seen near). Over
        `anchor_max_points` the farthest from `centre_xyz` are dropped."""
        T, points, smoothness = keyframe
        if self.anchor_smoothness is None:
            return
        if smoothness is None:  # no frequency: nothing is known to be smooth
            smoothness = np.full(points.shape[0], np.nan)
        if self.anchor_smoothness <= 0.0 or self.rough_anchor_view_rad is not None:
            chosen = np.arange(points.shape[0])  # every point (rough ones view-gated)
        else:
            chosen = np.flatnonzero(smoothness >= self.anchor_smoothness)  # NaN: never
        keys = voxel_keys(points[chosen], self.voxel_size_m)
        # One point per voxel (np.unique keeps the first): where rough points come along,
        # the smoothest first.
        order = (np.lexsort((-np.nan_to_num(smoothness[chosen], nan=-np.inf), keys))
                 if self.rough_anchor_view_rad is not None else slice(None))
        keys, first = np.unique(keys[order], return_index=True)
        chosen = chosen[order][first]
        known, anchored_smoothness = self._anchors.find(keys)
        viewpoints = np.broadcast_to(T[:3, 3], (chosen.shape[0], 3))
        if self.rough_anchor_view_rad is not None and known.any():
            # A smooth point takes over a rough anchor's voxel.
            upgrade = (known & self._is_smooth(smoothness[chosen])
                       & ~self._is_smooth(anchored_smoothness))
            self._anchors.replace(keys[upgrade], points[chosen[upgrade]],
                                  smoothness[chosen[upgrade]], viewpoints[upgrade])
        new = ~known
        self._anchors.add(keys[new], points[chosen[new]], smoothness[chosen[new]],
                          viewpoints[new])
        self._anchors.keep_nearest(centre_xyz, self.anchor_max_points)

    def _is_smooth(self, smoothness: np.ndarray) -> np.ndarray:
        """Served from any side: smoothness at or above the anchor threshold (NaN: never)."""
        return np.asarray(smoothness) >= self.anchor_smoothness

    def _served_anchors(self, centre_xyz: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points, smoothness, viewpoints) of the anchors that may be served to a keyframe
        at `centre_xyz`, sorted by voxel key: those near it (the radius crop follows), of them
        every smooth one, and a rough one only when seen from within `rough_anchor_view_rad`
        of the direction it was measured from."""
        points, smoothness, viewpoints = self._anchors.in_slab(
            *voxel_x_slab(centre_xyz[0], self.max_range_m, self.voxel_size_m))
        if self.rough_anchor_view_rad is None or self.anchor_smoothness <= 0.0:
            return points, smoothness, viewpoints
        served = self._served_from_its_side(points, smoothness, viewpoints, centre_xyz,
                                            self.rough_anchor_view_rad)
        return points[served], smoothness[served], viewpoints[served]

    def _served_from_its_side(self, points: np.ndarray, smoothness: np.ndarray,
                              viewpoints: np.ndarray, centre_xyz: np.ndarray,
                              view_rad: float) -> np.ndarray:
        """Which points a keyframe at `centre_xyz` is served: a rough one (NaN: rough) when
        seen from within `view_rad` of the direction it was measured from (porous canopy seen
        from its other side is another cloud), a smooth one from any side or within
        `smooth_view_rad`, and any point in the any-side share."""
        to_view = viewpoints - points
        to_centre = centre_xyz - points
        dot = np.einsum('ij,ij->i', to_view, to_centre)
        norms = np.sqrt(np.einsum('ij,ij->i', to_view, to_view)
                        * np.einsum('ij,ij->i', to_centre, to_centre))
        smooth = self._is_smooth(smoothness)
        if self.smooth_view_rad is None:
            served = smooth | (dot >= np.cos(view_rad) * norms)
        else:
            served = dot >= np.where(smooth, np.cos(self.smooth_view_rad),
                                     np.cos(view_rad)) * norms
        if self.rough_anchor_any_side_share > 0.0:
            served |= voxel_draw(points, self.voxel_size_m) < self.rough_anchor_any_side_share
        return served

    def _window_part_from_its_side(self, part, centre_xyz: np.ndarray):
        """A keyframe's (points, smoothness, viewpoints, priority) as served from its side,
        within the map's radius (the crop that follows would drop the rest: cropped first,
        the gate's geometry runs on fewer points)."""
        points, smoothness, viewpoints, priority = part
        offset = points - centre_xyz
        near = np.flatnonzero(np.einsum('ij,ij->i', offset, offset) <= self.max_range_m ** 2)
        points, viewpoints = points[near], viewpoints[near]
        smoothness = None if smoothness is None else smoothness[near]
        served = near[self._served_from_its_side(
            points, np.full(len(points), np.nan) if smoothness is None else smoothness,
            viewpoints, centre_xyz, self.rough_window_view_rad)]
        return (part[0][served], None if part[1] is None else part[1][served],
                part[2][served], None if priority is None else priority[served])

    def _view_priority(self, points_world: np.ndarray, T_world_sensor: np.ndarray):
        """With voxel_keeps 'nearest': minus each point's range from its keyframe's sensor."""
        if self.voxel_keeps != 'nearest':
            return None
        offset = points_world - T_world_sensor[:3, 3]
        return -np.einsum('ij,ij->i', offset, offset)

    def _voxel_means(self, points, viewpoints, smoothness):
        """(centroids, mean viewpoints, mean smoothness or None) of the voxels; with
        'mean_rough' a voxel smooth on average (the anchor threshold; without anchors none
        is) keeps its first (oldest) point and view."""
        if smoothness is None:
            centroids, views, _ = voxel_means(points, self.voxel_size_m, viewpoints)
            return centroids, views, None
        centroids, views, smooth, first = voxel_means(points, self.voxel_size_m, viewpoints,
                                                      smoothness)
        if self.voxel_keeps == 'mean_rough' and self.anchor_smoothness is not None:
            one = self._is_smooth(smooth)  # NaN: rough
            centroids[one], views[one] = points[first[one]], viewpoints[first[one]]
        return centroids, views, smooth

    def _rebuilt(self, centre_xyz: np.ndarray, in_background: bool = False,
                 normals_due_s: float | None = None) -> _Served:
        """The map of the window and the anchors around `centre_xyz`. `in_background`: its
        target too, with every normal, computed so that the thread leaves the interpreter to
        the next scan's match."""
        # The first point of a voxel wins: newest keyframe first keeps the freshest point,
        # oldest first the one seen first; 'nearest' the one seen from closest. Each part:
        # (points, smoothness or None, viewpoints, view priority or None).
        keyframes = reversed(self._keyframes) if self.voxel_keeps == 'newest' else self._keyframes
        parts = [(pts, s, np.broadcast_to(T[:3, 3], pts.shape), self._view_priority(pts, T))
                 for T, pts, s in keyframes]
        if self.rough_window_view_rad is not None:
            parts = [self._window_part_from_its_side(part, centre_xyz) for part in parts]
        if self.n_anchors:
            # Anchors first: they are the oldest content, and a voxel they fill keeps them
            # (with 'nearest' they compete by their range from where they were seen).
            points, anchor_smoothness, viewpoints = self._served_anchors(centre_xyz)
            offset = points - viewpoints
            anchors = (points, anchor_smoothness, viewpoints,
                       -np.einsum('ij,ij->i', offset, offset)
                       if self.voxel_keeps == 'nearest' else None)
            parts = [anchors] + parts
        merged = np.concatenate([p[0] for p in parts])
        viewpoints = np.concatenate([p[2] for p in parts])
        # A keyframe without smoothness counts as unknown (NaN): the solver then matches its
        # points by distance alone.
        smooth = (np.concatenate([np.full(len(p[0]), np.nan) if p[1] is None else p[1]
                                  for p in parts])
                  if any(p[1] is not None for p in parts) else None)
        priority = (np.concatenate([p[3] for p in parts]) if self.voxel_keeps == 'nearest'
                    else None)
        d2 = np.einsum('ij,ij->i', merged - centre_xyz, merged - centre_xyz)
        index = np.flatnonzero(d2 <= self.max_range_m ** 2)
        if self.voxel_keeps in ('mean', 'mean_rough'):
            merged, viewpoints, smooth = self._voxel_means(
                merged[index], viewpoints[index], None if smooth is None else smooth[index])
            d2 = np.einsum('ij,ij->i', merged - centre_xyz, merged - centre_xyz)
            index = np.arange(merged.shape[0])
        else:
            index = index[voxel_downsample_indices(
                merged[index], self.voxel_size_m,
                None if priority is None else priority[index])]
        if index.shape[0] > self.max_points:
            # Keep the nearest points: registration is best conditioned close to the sensor.
            index = index[np.argpartition(d2[index], self.max_points - 1)[:self.max_points]]
        merged = merged[index]
        served = _Served(to_cloud(merged), None if smooth is None else smooth[index],
                         viewpoints[index])
        if merged.shape[0] >= 3:
            search = o3d.geometry.KDTreeSearchParamKNN(self.normal_neighbours)
            if (self.with_normals and not in_background
                    and self._normals_in_time(merged.shape[0], normals_due_s)):
                t0 = time.perf_counter()
                served.cloud.estimate_normals(search)
                self._seconds_per_point.observe('normals', time.perf_counter() - t0,
                                                merged.shape[0])
            if self.with_covariances:
                served.cloud.estimate_covariances(search)
        if in_background:
            served = served._replace(target=MapTarget(
                merged, _normals_releasing_the_interpreter(merged, self.normal_neighbours),
                point_smoothness=served.smoothness, viewpoints=served.viewpoints,
                normal_neighbours=self.normal_neighbours))
        return served

    def _normals_in_time(self, n_points: int, due_s: float | None) -> bool:
        """Whether a rebuild of `n_points` estimates every normal: always, unless
        `normals_in_time` and its normals and KD-tree, at their cost per point so far, would
        end after `due_s` + `normals_slack_s` (a first rebuild, with no cost measured yet,
        estimates them). A map left to the pairs estimates the nearest of them that fit
        before `due_s` (`target`)."""
        if not self.normals_in_time or due_s is None:
            return True
        needed_s = self._seconds_per_point.predict(('normals', 'tree'), n_points)
        if needed_s is None or time.perf_counter() + needed_s <= due_s + self.normals_slack_s:
            return True
        self.n_rebuilds_left_to_pairs += 1
        return False

    def _serve(self, served: _Served) -> None:
        self.cloud, self.smoothness, self.viewpoints = served[:3]
        if self._target is not None and self._target.normals is None:
            self._previous_target = self._target  # its estimated normals carry over
        self._target = served.target
