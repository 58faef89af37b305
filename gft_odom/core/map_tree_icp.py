"""open3d's point-to-plane ICP, over a search index kept with the map, not one built per call.

open3d's `registration_icp` builds a KD-tree of the target on every call: on a 50-80k point
local map that is ~28 ms of a ~40 ms match, while its iterations (a few, on ~3k scan points)
cost under 1 ms each. The map changes only at a keyframe (every 1 m), so its tree is built
once then (`LocalMap.target()`), and every scan in between reuses it.

The algorithm is open3d's, step for step, so solver 'map_tree' reproduces solver 'open3d' up to
floating-point rounding: pairs are each scan point's nearest map point within the distance;
rows `J = [p x n, n]`, `r = n . (p - q)` with `p` in world coordinates (rotation about the
world origin, as open3d); robust weights of `|r|`; update `Rz Ry Rx` and translation applied on
the left; stop when both the fitness and the inlier RMSE change by less than the relative
criteria between iterations.

The nearest neighbours are exact but searched rarely: the tree gives each scan point its
`CANDIDATES` nearest map points once; after the estimate moves the point by `m`, no other map
point can be nearer than (the farthest candidate's distance - m), so while the nearest
candidate is within that, it is the nearest map point. Only the points for which that test
fails are searched again (after the first iteration, a few).

Anderson acceleration (`anderson_memory` > 0; off: open3d's sequence). On real orchard scans
the pose slides towards the optimum by a near-constant share of the remaining distance per
iteration (pairs re-found by nearest neighbour trail the estimate), some 14 iterations a
match and the 30-iteration cap on one in twelve. Treating one ICP step as a fixed-point map
of the pose, the extrapolation of Anderson (as AA-ICP, Pavlov et al. 2018, and Zhang et al.'s
fast robust ICP, 2021) takes the combination of the last steps that best cancels their
residuals; a proposal is kept only if it lowers the robust point-to-plane energy, else the
plain step is taken and the history restarts.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from gft_odom.core.gauss_newton import IcpResult, MapTarget, kernel_loss, kernel_weights

CANDIDATES = 4
# The candidates are searched this far beyond the correspondence distance: the margin a point
# may move before its candidates stop proving anything.
SEARCH_MARGIN_M = 0.2
# Where a missing candidate is put (a map is not 1e9 m across).
FAR_M = 1e9


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


class MapTreeICP:
    """Point-to-plane ICP of a scan onto a `MapTarget` (points, normals, its KD-tree)."""

    def __init__(self, kernel: str = 'tukey', kernel_scale_m: float = 0.3,
                 relative_fitness: float = 1e-6, relative_rmse: float = 1e-6,
                 max_iterations: int = 30, anderson_memory: int = 0,
                 anneal_from_m: float = 0.0, anneal_factor: float = 0.7) -> None:
        self.kernel = kernel
        self.kernel_scale_m = kernel_scale_m
        # Graduated kernel (`anneal_from_m` > 0): iteration i weighs residuals with the scale
        # max(kernel_scale_m, anneal_from_m x anneal_factor^i), so that a guess further off
        # than the kernel is still pulled in, and the end is weighed as without it.
        self.anneal_from_m = anneal_from_m
        self.anneal_factor = anneal_factor
        self._anneal = 1.0  # this iteration's factor on every scale
        self.relative_fitness = relative_fitness
        self.relative_rmse = relative_rmse
        self.max_iterations = max_iterations
        # Past steps Anderson acceleration combines (0: plain ICP, open3d's iterates).
        self.anderson_memory = anderson_memory
        self._point_scale_m: np.ndarray | None = None  # of the current call's scan points

    def register(self, source_xyz: np.ndarray, target: MapTarget, init: np.ndarray,
                 max_distance_m: float | np.ndarray, max_iterations: int | None = None,
                 point_scale_m: np.ndarray | None = None) -> IcpResult:
        """Align `source_xyz` (sensor frame) to `target` from `init` (T_world_sensor);
        `point_scale_m` (n,): each scan point's own kernel scale (None: `kernel_scale_m`);
        `max_distance_m`: one gate, or (n,) each scan point's own.

        The result's information is None: `icp_information` computes it from the pairs, as
        for open3d's result."""
        self._point_scale_m = point_scale_m
        T = np.array(init, dtype=float)
        iterations = self.max_iterations if max_iterations is None else max_iterations
        world = source_xyz @ T[:3, :3].T + T[:3, 3]
        nearest = ExactNearest(target, max_distance_m)
        pairs, fitness, rmse = self._correspond(world, nearest)
        anderson = AndersonPose(T, self.anderson_memory) if self.anderson_memory else None
        energy = self._energy(world, target, pairs, max_distance_m) if anderson else 0.0
        self.n_accelerated = 0  # accepted Anderson proposals of the last call
        used = 0
        try:
            for used in range(1, iterations + 1):
                self._anneal = self._anneal_at(used - 1)
                update = self._update(world, target, pairs)
                previous = (fitness, rmse)
                step = None
                if anderson is not None:
                    proposal = anderson.propose(T, update @ T)
                    if proposal is not None:
                        tried = source_xyz @ proposal[:3, :3].T + proposal[:3, 3]
                        step = (proposal, tried) + self._correspond(tried, nearest)
                        tried_energy = self._energy(tried, target, step[2], max_distance_m)
                        if tried_energy < energy:
                            energy = tried_energy
                            self.n_accelerated += 1
                        else:
                            anderson.restart()
                            step = None
                if step is None:
                    T = update @ T
                    world = world @ update[:3, :3].T + update[:3, 3]
                    pairs, fitness, rmse = self._correspond(world, nearest)
                    if anderson is not None:
                        energy = self._energy(world, target, pairs, max_distance_m)
                else:
                    T, world, pairs, fitness, rmse = step
                if (self._anneal == 1.0 and abs(previous[0] - fitness) < self.relative_fitness
                        and abs(previous[1] - rmse) < self.relative_rmse):
                    break  # (a graduated kernel first reaches its end)
        finally:
            self._anneal = 1.0  # none left over for the next call, whatever ends this one
        return IcpResult(T, fitness, rmse, pairs, None, used)

    def _anneal_at(self, iteration: int) -> float:
        """The graduated kernel's factor on the scale at `iteration` (1: none)."""
        if self.anneal_from_m <= self.kernel_scale_m:
            return 1.0
        return max(1.0, self.anneal_from_m * self.anneal_factor ** iteration
                   / self.kernel_scale_m)

    def _energy(self, world: np.ndarray, target: MapTarget, pairs: np.ndarray,
                max_distance_m: float | np.ndarray) -> float:
        """The robust point-to-plane energy: each pair's kernel loss, and a point without a
        pair the loss of its correspondence distance (so losing pairs is not a gain)."""
        _, r = _plane_residuals(world, target, pairs)
        unpaired = np.ones(world.shape[0], dtype=bool)
        unpaired[pairs[:, 0]] = False
        gate_m = np.broadcast_to(np.asarray(max_distance_m, dtype=float), unpaired.shape)
        return float(np.sum(kernel_loss(self.kernel, np.abs(r), self._scale(pairs)))
                     + np.sum(kernel_loss(self.kernel, gate_m[unpaired], self.kernel_scale_m)))

    def _scale(self, pairs: np.ndarray) -> float | np.ndarray:
        """The kernel scale of each pair (one for all when no point has its own)."""
        if self._point_scale_m is None:
            return self.kernel_scale_m * self._anneal
        return self._point_scale_m[pairs[:, 0]] * self._anneal

    @staticmethod
    def _correspond(world: np.ndarray, nearest: 'ExactNearest'):
        """(pairs (m, 2) scan index, map index; fitness; inlier RMSE) of nearest neighbours
        within the distance."""
        n = world.shape[0]
        valid, index, distance = nearest.query(world)
        if valid.shape[0] == 0:
            return np.zeros((0, 2), dtype=np.int64), 0.0, 0.0
        rmse = float(np.sqrt(np.mean(distance ** 2)))
        return np.column_stack([valid, index]), valid.shape[0] / n, rmse

    def _update(self, world: np.ndarray, target: MapTarget, pairs: np.ndarray) -> np.ndarray:
        """One weighted Gauss-Newton step of the point-to-plane residuals (identity when
        there are no pairs or the system cannot be solved, as open3d)."""
        if pairs.shape[0] == 0:
            return np.eye(4)
        p = np.take(world, pairs[:, 0], axis=0)  # np.take: row gathers cheaper than indexing
        normals, r = _plane_residuals(world, target, pairs, p)
        J = np.empty((p.shape[0], 6))
        J[:, 0] = p[:, 1] * normals[:, 2] - p[:, 2] * normals[:, 1]  # p x n
        J[:, 1] = p[:, 2] * normals[:, 0] - p[:, 0] * normals[:, 2]
        J[:, 2] = p[:, 0] * normals[:, 1] - p[:, 1] * normals[:, 0]
        J[:, 3:] = normals
        w = kernel_weights(self.kernel, np.abs(r), self._scale(pairs))
        Jw = J * w[:, None]
        try:
            x = np.linalg.solve(Jw.T @ J, -(Jw.T @ r))
        except np.linalg.LinAlgError:
            return np.eye(4)
        if not np.all(np.isfinite(x)):
            return np.eye(4)
        return euler_update(x)


def _plane_residuals(world: np.ndarray, target: MapTarget, pairs: np.ndarray,
                     paired_xyz: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(the pairs' map normals, their point-to-plane residuals n . (p - q))."""
    p = np.take(world, pairs[:, 0], axis=0) if paired_xyz is None else paired_xyz
    normals = target.normals_at(pairs[:, 1])
    return normals, np.einsum('ij,ij->i', p - np.take(target.points, pairs[:, 1], axis=0),
                              normals)


class AndersonPose:
    """Anderson extrapolation (type II) of a pose iteration T -> G(T), in a chart about the
    first pose: the rotation vector of R R0^T (about the sensor, not the world origin, whose
    distance would couple rotation and translation) and the translation from t0."""

    def __init__(self, reference: np.ndarray, memory: int) -> None:
        self.R0 = reference[:3, :3].copy()
        self.t0 = reference[:3, 3].copy()
        self.memory = memory
        self.restart()

    def restart(self) -> None:
        """Forget the steps (after a rejected proposal: they no longer describe the way)."""
        self.x: list[np.ndarray] = []
        self.g: list[np.ndarray] = []

    def chart(self, T: np.ndarray) -> np.ndarray:
        """Pose -> (rotation vector, translation) relative to the first pose."""
        return np.r_[Rotation.from_matrix(T[:3, :3] @ self.R0.T).as_rotvec(), T[:3, 3] - self.t0]

    def pose(self, x: np.ndarray) -> np.ndarray:
        """The chart's inverse."""
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix() @ self.R0
        T[:3, 3] = self.t0 + x[3:]
        return T

    def propose(self, T: np.ndarray, T_next: np.ndarray) -> np.ndarray | None:
        """Record the step T -> T_next; the extrapolated pose once two steps are known."""
        self.x.append(self.chart(T))
        self.g.append(self.chart(T_next))
        del self.x[:-(self.memory + 1)], self.g[:-(self.memory + 1)]
        if len(self.x) < 2:
            return None
        G = np.array(self.g)
        F = G - np.array(self.x)
        dF, dG = np.diff(F, axis=0), np.diff(G, axis=0)
        gamma = np.linalg.lstsq(dF.T, F[-1], rcond=None)[0]
        x = G[-1] - dG.T @ gamma
        return self.pose(x) if np.all(np.isfinite(x)) else None


class ExactNearest:
    """Each query point's nearest map point within `max_distance_m`, over one registration:
    the map's index is searched again only for the points whose candidates no longer prove
    it."""

    def __init__(self, target: MapTarget, max_distance_m: float | np.ndarray) -> None:
        self.target = target
        self.max_distance_m = max_distance_m  # one gate, or (n,) each query point's own
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
