"""Matching a scan: point-to-plane ICP against the local map, or (paper mode) open3d's
point-to-point ICP against the previous scan.

The map's match is open3d's point-to-plane ICP step for step, over a search index kept with the
map: open3d's `registration_icp` builds a KD-tree of the target on every call (~28 ms of a
~40 ms match on a 50-80k point map), while the map changes only at a keyframe (every 1 m), so
its tree is built once then (`LocalMap.target()`). Pairs are each scan point's nearest map
point within the gate; rows `J = [p x n, n]`, `r = n . (p - q)` with `p` in world coordinates
(rotation about the world origin, as open3d); Tukey weights of `|r|`; the update `Rz Ry Rx`
and translation applied on the left; the match stops when the fitness and the inlier RMSE
change by less than CONVERGENCE_RELATIVE between iterations.

The nearest neighbours are exact but searched rarely (`ExactNearest`): the tree gives each
scan point its CANDIDATES nearest map points once; after the estimate moves the point by `m`,
no other map point can be nearer than (the farthest candidate's distance - m), so while the
nearest candidate is within that, it is the nearest map point. Only the points for which that
test fails are searched again (after the first iteration, a few).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from gft_odom.core.registration.map_index import MapIndex

o3d_reg = o3d.pipelines.registration

# Stop when the relative fitness and RMSE changes fall below this: 1e-4 gave the same ATE as
# 1e-6 on the simulated drives at half the ICP time.
CONVERGENCE_RELATIVE = 1e-4
# Re-acquisition's fine ICP may iterate this many times longer than a match (it starts
# further away).
RECOVERY_ITERATIONS_FACTOR = 4
CANDIDATES = 4
# The candidates are searched this far beyond the correspondence gate: the margin a point may
# move before its candidates stop proving anything.
SEARCH_MARGIN_M = 0.2
# Where a missing candidate is put (a map is not 1e9 m across).
FAR_M = 1e9


@dataclass
class MapTarget:
    """What a scan is matched against: the map's points, their normals and search index."""

    points: np.ndarray  # (n, 3) world
    normals: np.ndarray  # (n, 3) unit
    tree: MapIndex | None = None
    weights: np.ndarray | None = None  # (n,) a weight per map point (None: all 1)

    def __post_init__(self) -> None:
        if self.tree is None:
            self.tree = MapIndex(self.points)
        self._padded: np.ndarray | None = None

    def axes_and_far_point(self, far_m: float) -> np.ndarray:
        """(3, n + 1): the points one axis per row (contiguous gathers), and a last point at
        `far_m` on every axis, so that a search's "none" (index n) gathers a point that is
        never the nearest. Built once."""
        if self._padded is None or self._padded[0, -1] != far_m:
            self._padded = np.hstack([self.points.T, np.full((3, 1), far_m)])
        return self._padded

    def normals_at(self, index: np.ndarray) -> np.ndarray:
        """The unit normals of the map points `index`."""
        return np.take(self.normals, index, axis=0)


@dataclass
class IcpResult:
    """What a match found: open3d's RegistrationResult's fields the registration reads."""

    transformation: np.ndarray  # (4, 4) T_world_sensor
    fitness: float  # pairs within the correspondence distance / source points
    inlier_rmse: float  # RMS point distance of those pairs
    correspondence_set: np.ndarray  # (m, 2) source index, target index
    n_iterations: int


def tukey_weights(e: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weight of residual norms `e` under Tukey's biweight (open3d's TukeyLoss)."""
    u = e / scale
    return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)


def euler_update(x: np.ndarray) -> np.ndarray:
    """open3d's TransformVector6dToMatrix4d: x = (alpha, beta, gamma, tx, ty, tz) ->
    Rz(gamma) Ry(beta) Rx(alpha) with translation t."""
    ca, sa = np.cos(x[0]), np.sin(x[0])
    cb, sb = np.cos(x[1]), np.sin(x[1])
    cg, sg = np.cos(x[2]), np.sin(x[2])
    out = np.eye(4)
    out[:3, :3] = (np.array([[cg, -sg, 0.0], [sg, cg, 0.0], [0.0, 0.0, 1.0]])
                   @ np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
                   @ np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]]))
    out[:3, 3] = x[3:]
    return out


def point_to_plane_icp(source_xyz: np.ndarray, target: MapTarget, init: np.ndarray,
                       max_distance_m: float, max_iterations: int,
                       kernel_scale_m: float, source_weights: np.ndarray | None = None
                       ) -> IcpResult:
    """Align `source_xyz` (sensor frame) to `target` from `init` (T_world_sensor); a pair's
    residual is weighed by its source and map point's weights when they are given."""
    T = np.array(init, dtype=float)
    world = source_xyz @ T[:3, :3].T + T[:3, 3]
    nearest = ExactNearest(target, max_distance_m)
    pairs, fitness, rmse = _correspond(world, nearest)
    used = 0
    for used in range(1, max_iterations + 1):
        update = _plane_step(world, target, pairs, kernel_scale_m, source_weights)
        previous = (fitness, rmse)
        T = update @ T
        world = world @ update[:3, :3].T + update[:3, 3]
        pairs, fitness, rmse = _correspond(world, nearest)
        if (abs(previous[0] - fitness) < CONVERGENCE_RELATIVE
                and abs(previous[1] - rmse) < CONVERGENCE_RELATIVE):
            break
    return IcpResult(T, fitness, rmse, pairs, used)


def _correspond(world: np.ndarray, nearest: 'ExactNearest'):
    """(pairs (m, 2) scan index, map index; fitness; inlier RMSE) of nearest neighbours
    within the gate."""
    n = world.shape[0]
    valid, index, distance = nearest.query(world)
    if valid.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64), 0.0, 0.0
    rmse = float(np.sqrt(np.mean(distance ** 2)))
    return np.column_stack([valid, index]), valid.shape[0] / n, rmse


def _plane_step(world: np.ndarray, target: MapTarget, pairs: np.ndarray,
                kernel_scale_m: float, source_weights: np.ndarray | None = None) -> np.ndarray:
    """One weighted Gauss-Newton step of the point-to-plane residuals (identity when there
    are no pairs or the system cannot be solved, as open3d)."""
    if pairs.shape[0] == 0:
        return np.eye(4)
    p = np.take(world, pairs[:, 0], axis=0)  # np.take: row gathers cheaper than indexing
    normals = target.normals_at(pairs[:, 1])
    r = np.einsum('ij,ij->i', p - np.take(target.points, pairs[:, 1], axis=0), normals)
    J = np.empty((p.shape[0], 6))
    J[:, 0] = p[:, 1] * normals[:, 2] - p[:, 2] * normals[:, 1]  # p x n
    J[:, 1] = p[:, 2] * normals[:, 0] - p[:, 0] * normals[:, 2]
    J[:, 2] = p[:, 0] * normals[:, 1] - p[:, 1] * normals[:, 0]
    J[:, 3:] = normals
    w = tukey_weights(np.abs(r), kernel_scale_m)
    if source_weights is not None:
        w = w * np.take(source_weights, pairs[:, 0])
    if target.weights is not None:
        w = w * np.take(target.weights, pairs[:, 1])
    Jw = J * w[:, None]
    try:
        x = np.linalg.solve(Jw.T @ J, -(Jw.T @ r))
    except np.linalg.LinAlgError:
        return np.eye(4)
    if not np.all(np.isfinite(x)):
        return np.eye(4)
    return euler_update(x)


class ExactNearest:
    """Each query point's nearest map point within `max_distance_m`, over one registration:
    the map's index is searched again only for the points whose candidates no longer prove
    it."""

    def __init__(self, target: MapTarget, max_distance_m: float) -> None:
        self.target = target
        self.max_distance_m = max_distance_m
        self.searched_at: np.ndarray | None = None  # (n, 3) where each point was searched
        self.candidates: np.ndarray | None = None  # (n, k) map indices (n_map: none)
        # (3, n, k) their coordinates, one axis per plane (vector operations on contiguous
        # (n, k) planes: half the time of an (n, k, 3) difference; measured).
        self.candidate_xyz: np.ndarray | None = None
        self.proof_m: np.ndarray | None = None  # (n,) no other map point was nearer
        self.n_searched = 0  # points searched, for the tests and the benchmarks

    def query(self, world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(query indices with a map point within the distance, their map indices, the
        distances)."""
        n_map = self.target.points.shape[0]
        if world.shape[0] == 0 or n_map == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
        if self.candidates is None:
            self.searched_at = world.copy()
            self.candidates = np.zeros((world.shape[0], CANDIDATES), dtype=np.int64)
            self.candidate_xyz = np.zeros((3, world.shape[0], CANDIDATES))
            self.proof_m = np.zeros(world.shape[0])
            self._search(np.arange(world.shape[0]), world)
        best, distance = self._nearest_candidate(world)
        step = world - self.searched_at
        # By columns: the same values as np.linalg.norm(step, axis=1), a quarter of the time.
        moved = np.sqrt(step[:, 0] * step[:, 0] + step[:, 1] * step[:, 1]
                        + step[:, 2] * step[:, 2])
        stale = np.flatnonzero(np.minimum(distance, self.max_distance_m)
                               > self.proof_m - moved)
        if stale.shape[0]:
            self._search(stale, world)
            best[stale], distance[stale] = self._nearest_candidate(world, stale)
        valid = np.flatnonzero(distance <= self.max_distance_m)
        return valid, best[valid], distance[valid]

    def _search(self, rows: np.ndarray, world: np.ndarray) -> None:
        bound = float(np.max(self.max_distance_m)) + SEARCH_MARGIN_M
        d, index = self.target.tree.query(world[rows], k=CANDIDATES, distance_upper_bound=bound)
        self.candidates[rows] = index
        # A missing candidate (index n_map) is the far point, so it is never the nearest.
        axes = self.target.axes_and_far_point(FAR_M)
        for axis in range(3):
            self.candidate_xyz[axis][rows] = np.take(axes[axis], index)
        self.searched_at[rows] = world[rows]
        # Every map point not among the candidates is at least this far.
        self.proof_m[rows] = np.minimum(d[:, -1], bound)
        self.n_searched += rows.shape[0]

    def _nearest_candidate(self, world: np.ndarray, rows: np.ndarray | slice = slice(None)
                           ) -> tuple[np.ndarray, np.ndarray]:
        """(map index, distance) of each point's nearest candidate (distance beyond the
        search bound: none)."""
        offset = self.candidate_xyz[:, rows] - world[rows].T[:, :, None]
        offset *= offset
        d2 = offset[0] + offset[1]
        d2 += offset[2]
        # The picked column of each row, as flat indices (cheaper than take_along_axis).
        flat = np.argmin(d2, axis=1)
        flat += np.arange(0, d2.size, CANDIDATES)
        return self.candidates[rows].ravel()[flat], np.sqrt(d2.ravel()[flat])


def to_cloud(points_xyz: np.ndarray) -> o3d.geometry.PointCloud:
    """numpy (N, 3) -> open3d cloud."""
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points_xyz)))


def point_to_point_icp(source_xyz: np.ndarray, target: o3d.geometry.PointCloud,
                       init: np.ndarray, max_distance_m: float, max_iterations: int):
    """The paper's ICP: open3d's point-to-point, plain least squares (its RegistrationResult)."""
    criteria = o3d_reg.ICPConvergenceCriteria(relative_fitness=CONVERGENCE_RELATIVE,
                                              relative_rmse=CONVERGENCE_RELATIVE,
                                              max_iteration=max_iterations)
    return o3d_reg.registration_icp(to_cloud(source_xyz), target, max_distance_m, init,
                                    o3d_reg.TransformationEstimationPointToPoint(), criteria)


class MapMatcher:
    """Point-to-plane ICP of a scan against the local map's current target."""

    def __init__(self, local_map, max_iterations: int, kernel_scale_m: float) -> None:
        self.local_map = local_map  # LocalMap: its `target()` is what is matched against
        self.max_iterations = max_iterations
        self.kernel_scale_m = kernel_scale_m

    def match(self, source_xyz: np.ndarray, init: np.ndarray, distance_m: float,
              recovery: bool = False) -> IcpResult:
        """ICP from `init` with pairs up to `distance_m` apart (`recovery`: the longer
        iteration budget of re-acquisition)."""
        iterations = self.max_iterations * (RECOVERY_ITERATIONS_FACTOR if recovery else 1)
        return point_to_plane_icp(np.ascontiguousarray(source_xyz, dtype=np.float64),
                                  self.local_map.target(), init, distance_m, iterations,
                                  self.kernel_scale_m)
