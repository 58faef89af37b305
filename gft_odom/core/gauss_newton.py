"""Gauss-Newton ICP with per-correspondence residual types and weights.

open3d's ICP gives every correspondence the same residual and a kernel weight only; the
frequency-aware registration needs a residual type and a weight per pair
(`gft_odom.core.residuals`), so the solver is written here, in numpy: nearest neighbours from
the map's index (`core/nearest.py`, built once per map rebuild), rows from the residual
model, a robust kernel per residual, a 6x6 solve, repeat until the update is below
`convergence_m`.

The index is asked for the `CANDIDATES` nearest map points of every scan point once, and
again only when the estimate has moved a typical scan point (at the median range) by more
than `REQUERY_M` since: in
between, each iteration picks the nearest of those candidates (a few vector operations
instead of a tree search; the map holds one point per 0.3 m voxel, so the true nearest point
of a point moved by a few cm is among its 4 nearest before the move).

The perturbation is (translation, rotation about the sensor position) in world axes, so the
final normal matrix is the information of the pose in the same axes `ScanRegistration`
reports its covariance in.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import least_variance_axis
from gft_odom.core.nearest import MapIndex
from gft_odom.core.residuals import Correspondences, normal_equations

KERNELS = ('none', 'tukey', 'huber', 'cauchy')
CANDIDATES = 4
REQUERY_M = 0.05


@dataclass
class MapTarget:
    """What the solver matches against: map points, their normals, optional smoothness."""

    points: np.ndarray  # (n, 3) world
    # (n, 3) unit; None: each map point's normal is estimated when a pair first asks for it
    # (`normals_at`), from the same kNN neighbourhood open3d's estimate_normals uses.
    normals: np.ndarray | None
    smoothness: np.ndarray | None = None  # (n,) in [0, 1], for map-side models
    tree: MapIndex | None = None
    # (n,) the smoothness of the scan point each map point came from (NaN: unknown), for
    # matching like with like.
    point_smoothness: np.ndarray | None = None
    # (n, 3) where the sensor stood when each map point was measured (None: unknown).
    viewpoints: np.ndarray | None = None
    normal_neighbours: int = 15  # the kNN of an estimated normal (the point itself included)

    def __post_init__(self) -> None:
        self.squared_norms = np.einsum('ij,ij->i', self.points, self.points)
        if self.tree is None:
            self.tree = MapIndex(self.points)
        if self.normals is None:
            n = self.points.shape[0]
            self._k = min(self.normal_neighbours, n)
            self._estimated = np.zeros((n, 3))
            self._known = np.zeros(n, dtype=bool)
            # Per estimated normal: its neighbours and the distance of the farthest, to tell
            # after a rebuild whether the neighbourhood is still the same.
            self._neighbours = np.zeros((n, self._k), dtype=np.int64)
            self._reach_m = np.zeros(n)
        self.n_normals_estimated = 0  # for the tests and the benchmarks
        self.n_normals_inherited = 0
        self._padded: np.ndarray | None = None

    def axes_and_far_point(self, far_m: float) -> np.ndarray:
        """(3, n + 1): the points one axis per row (contiguous gathers), and a last point at
        `far_m` on every axis, so that a search's "none" (index n) gathers a point that is
        never the nearest. Built once."""
        if self._padded is None or self._padded[0, -1] != far_m:
            self._padded = np.hstack([self.points.T, np.full((3, 1), far_m)])
        return self._padded

    def normals_at(self, index: np.ndarray) -> np.ndarray:
        """The unit normals of the map points `index`.

        Estimated on demand: a scan pairs with a few thousand of the ~40k map points, so a
        rebuild that estimated every normal (most of a keyframe's cost) did mostly waste."""
        if self.normals is not None:
            return np.take(self.normals, index, axis=0)
        missing = index[~self._known[index]]
        if missing.shape[0]:
            self._estimate_normals(np.unique(missing))
        return np.take(self._estimated, index, axis=0)

    def inherit_normals(self, previous: 'MapTarget', new_of_old: np.ndarray,
                        kept: bool = False) -> None:
        """Take over the normals `previous` (the map before a rebuild) estimated, for the
        points still in this map (`new_of_old`: each old point's index here, -1 when gone)
        whose k nearest neighbours are still theirs: none of them left, and no new point
        came nearer than the farthest. Those normals are what estimating them again would
        give, so most of a rebuilt map needs none estimated. With `kept`, every normal of a
        point still here, whatever came or went around it ('kept' map normals: cheaper, and
        not what a fresh estimate would give)."""
        if (self.normals is not None or previous.normals is not None
                or previous._k != self._k or self._k == 0):
            return
        old = np.flatnonzero(previous._known & (new_of_old >= 0))
        if old.shape[0] == 0:
            return
        if kept:
            at = new_of_old[old]
        else:
            neighbours = new_of_old[previous._neighbours[old]]
            intact = np.all(neighbours >= 0, axis=1)
            added = np.ones(self.points.shape[0], dtype=bool)
            added[new_of_old[new_of_old >= 0]] = False
            if added.any():
                reach = previous._reach_m[old]
                nearest, _ = cKDTree(self.points[added]).query(previous.points[old],
                                                               distance_upper_bound=reach.max())
                intact &= ~(nearest < reach)
            old, neighbours = old[intact], neighbours[intact]
            at = new_of_old[old]
            self._neighbours[at] = neighbours
            self._reach_m[at] = previous._reach_m[old]
        self._estimated[at] = previous._estimated[old]
        self._known[at] = True
        self.n_normals_inherited += at.shape[0]

    def estimate_missing_normals(self) -> None:
        """Estimate every normal not known yet, in one batch."""
        if self.normals is None and self._k:
            missing = np.flatnonzero(~self._known)
            if missing.shape[0]:
                self._estimate_normals(missing)

    def estimate_normals_until(self, due_s: float, near_xyz: np.ndarray,
                               chunk: int = 2000) -> None:
        """Estimate normals not known yet, nearest `near_xyz` first (where the next scans'
        pairs are), in chunks while the next would still end before `due_s`
        (`time.perf_counter` seconds): time a caller has spare, spent before a pair asks."""
        if self.normals is not None or not self._k:
            return
        missing = np.flatnonzero(~self._known)
        if not missing.shape[0] or time.perf_counter() >= due_s:
            return
        offset = self.points[missing] - near_xyz
        missing = missing[np.argsort(np.einsum('ij,ij->i', offset, offset), kind='stable')]
        chunk_s = 0.0
        for start in range(0, missing.shape[0], chunk):
            t0 = time.perf_counter()
            if t0 + chunk_s > due_s:
                return
            self._estimate_normals(missing[start:start + chunk])
            chunk_s = time.perf_counter() - t0

    def _estimate_normals(self, rows: np.ndarray) -> None:
        """PCA normals: the least-variance axis of each point's nearest neighbours."""
        distance, neighbours = self.tree.query(self.points[rows], k=self._k)
        neighbours = neighbours.reshape(rows.shape[0], self._k)
        around = self.points[neighbours]
        around = around - around.mean(axis=1, keepdims=True)
        self._estimated[rows] = least_variance_axis(np.matmul(around.transpose(0, 2, 1),
                                                              around))
        self._neighbours[rows] = neighbours
        self._reach_m[rows] = np.asarray(distance).reshape(rows.shape[0], self._k)[:, -1]
        self._known[rows] = True
        self.n_normals_estimated += rows.shape[0]


@dataclass
class IcpResult:
    """The open3d RegistrationResult's fields the registration reads, plus the information."""

    transformation: np.ndarray  # (4, 4) T_world_sensor
    fitness: float  # pairs within the correspondence distance / source points
    inlier_rmse: float  # RMS point distance of those pairs
    correspondence_set: np.ndarray  # (m, 2) source index, target index
    information: np.ndarray | None  # (6, 6) J^T W J / rmse^2 at the solution
    n_iterations: int


def kernel_loss(kind: str, e: np.ndarray, scale: float) -> np.ndarray:
    """The loss rho(e) whose IRLS weight `kernel_weights` gives (rho'(e) / e)."""
    if kind == 'tukey':
        u2 = np.minimum(e / scale, 1.0) ** 2
        return scale * scale / 6.0 * (1.0 - (1.0 - u2) ** 3)
    if kind == 'huber':
        return np.where(e <= scale, 0.5 * e * e, scale * (e - 0.5 * scale))
    if kind == 'cauchy':
        return 0.5 * scale * scale * np.log1p((e / scale) ** 2)
    return 0.5 * e * e


def kernel_weights(kind: str, e: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weight of residual norms `e` (the same kernels open3d offers)."""
    if kind == 'tukey':
        u = e / scale
        return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
    if kind == 'huber':
        return np.where(e <= scale, 1.0, scale / np.maximum(e, 1e-12))
    if kind == 'cauchy':
        return 1.0 / (1.0 + (e / scale) ** 2)
    return np.ones_like(e)


class GaussNewtonICP:
    """Point cloud to map registration; the residual model decides each pair's rows."""

    def __init__(self, residual_model, kernel: str = 'tukey', kernel_scale_m: float = 0.3,
                 max_iterations: int = 30, convergence_m: float = 1e-4,
                 affinity_m: float = 0.0) -> None:
        if kernel not in KERNELS:
            raise ValueError(f'kernel must be one of {KERNELS}, got {kernel!r}')
        self.model = residual_model
        self.kernel = kernel
        self.kernel_scale_m = kernel_scale_m
        self.max_iterations = max_iterations
        self.convergence_m = convergence_m
        # Like with like: a pair whose scan and map points differ in smoothness by d costs
        # (affinity_m * d)^2 more when the nearest of the candidates is chosen (0: by
        # distance alone).
        self.affinity_m = affinity_m

    def register(self, source_xyz: np.ndarray, target: MapTarget, init: np.ndarray,
                 max_distance_m: float, source_smoothness: np.ndarray | None = None,
                 max_iterations: int | None = None,
                 match_smoothness: np.ndarray | None = None,
                 prior: tuple[np.ndarray, float] | None = None) -> IcpResult:
        """Align `source_xyz` (sensor frame) to `target` starting at `init` (T_world_sensor).

        `source_smoothness` (n,) in [0, 1] per source point, for frequency-aware models; a
        model reading the map's smoothness takes it from `target.smoothness`.
        `match_smoothness` (n,): the scan points' smoothness the candidate choice compares
        with `target.point_smoothness` (with `affinity_m` > 0). `prior` (T_world_sensor,
        weight): a soft prior on the pose worth `weight` pairs along every axis (rotations
        scaled by the median range squared); the returned information is the data's only."""
        T = np.array(init, dtype=float)
        n = source_xyz.shape[0]
        iterations = self.max_iterations if max_iterations is None else max_iterations
        reach_m = float(np.sqrt(np.median(np.einsum('ij,ij->i', source_xyz, source_xyz)))
                        ) if n else 0.0
        search = _CandidateSearch(target, max_distance_m, match_smoothness, self.affinity_m)
        used = 0
        for used in range(1, iterations + 1):
            pairs, c = self._correspond(source_xyz, search, T, source_smoothness)
            if pairs.shape[0] < 6:
                return IcpResult(T, pairs.shape[0] / max(n, 1), 0.0, pairs, None, used)
            H, g = self._normal_equations(c)
            if prior is not None:
                H, g = _with_prior(H, g, T, prior, reach_m)
            try:
                dx = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
            except np.linalg.LinAlgError:
                break
            if not np.all(np.isfinite(dx)):
                T = np.full((4, 4), np.nan)
                break
            T = apply_update(T, dx)
            # How far a typical scan point moved: the translation plus the rotation's arc at
            # the median range (the few far points may pick a near-nearest candidate meanwhile).
            search.moved_m += np.linalg.norm(dx[:3]) + np.linalg.norm(dx[3:]) * reach_m
            if np.linalg.norm(dx) < self.convergence_m:
                break
        pairs, c = self._correspond(source_xyz, search, T, source_smoothness)
        m = pairs.shape[0]
        if m == 0 or not np.all(np.isfinite(T)):
            return IcpResult(T, m / max(n, 1), 0.0, pairs, None, used)
        distance = np.linalg.norm(c.source_world - c.target, axis=1)
        rmse = float(np.sqrt(np.mean(distance ** 2)))
        information = None
        if m >= 6:
            H, _ = self._normal_equations(c)
            information = H / max(rmse, 1e-3) ** 2
        return IcpResult(T, m / max(n, 1), rmse, pairs, information, used)

    def _correspond(self, source_xyz, search: '_CandidateSearch', T, smoothness):
        world = source_xyz @ T[:3, :3].T + T[:3, 3]
        valid, tgt = search.nearest(world)
        target = search.target
        s = None
        if smoothness is not None:
            s = smoothness[valid]
        elif target.smoothness is not None:
            s = target.smoothness[tgt]
        beam = (None if target.viewpoints is None or target.viewpoints.shape[0] == 0
                else target.points[tgt] - target.viewpoints[tgt])
        c = Correspondences(world[valid], world[valid] - T[:3, 3], target.points[tgt],
                            target.normals_at(tgt), s, beam)
        return np.column_stack([valid, tgt]), c

    def _normal_equations(self, c: Correspondences) -> tuple[np.ndarray, np.ndarray]:
        H, g = np.zeros((6, 6)), np.zeros(6)
        for term in self.model.terms(c):
            dH, dg = normal_equations(c, term, self._kernel)
            H += dH
            g += dg
        return H, g

    def _kernel(self, e: np.ndarray) -> np.ndarray:
        return kernel_weights(self.kernel, e, self.kernel_scale_m)


def _with_prior(H: np.ndarray, g: np.ndarray, T: np.ndarray, prior: tuple[np.ndarray, float],
                reach_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations plus a diagonal prior pulling T towards the prior pose (residual:
    translation difference, rotation vector of R R_prior^T; Jacobian ~ I near it)."""
    T_prior, weight = prior
    W = weight * np.r_[np.ones(3), np.full(3, max(reach_m, 1.0) ** 2)]
    rotvec = Rotation.from_matrix(T[:3, :3] @ T_prior[:3, :3].T).as_rotvec()
    r = np.r_[T[:3, 3] - T_prior[:3, 3], rotvec]
    return H + np.diag(W), g + W * r


class _CandidateSearch:
    """The nearest map point of every scan point, over one registration: the KD-tree gives
    `CANDIDATES` per point, re-asked only after the estimate moved a typical point by
    `REQUERY_M` (`moved_m`, kept by the solver).

    With smoothness on both sides and `affinity_m` > 0 the chosen candidate is the one
    nearest once a smoothness mismatch d counts as (affinity_m * d)^2 of squared distance:
    a canopy return pairs with canopy, a trunk or ground return with its own surface."""

    def __init__(self, target: MapTarget, max_distance_m: float,
                 source_smoothness: np.ndarray | None = None, affinity_m: float = 0.0) -> None:
        self.target = target
        self.max_distance_m = max_distance_m
        self.mismatch: np.ndarray | None = None
        self._source_smoothness = (source_smoothness if affinity_m > 0.0
                                   and target.point_smoothness is not None else None)
        self._affinity_m = affinity_m
        self.candidates: np.ndarray | None = None
        self.found: np.ndarray | None = None
        self.moved_m = 0.0

    def nearest(self, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(scan indices with a map point within the distance, their map indices)."""
        target = self.target
        if self.candidates is None or self.moved_m > REQUERY_M:
            _, index = target.tree.query(world, k=CANDIDATES,
                                         distance_upper_bound=self.max_distance_m + REQUERY_M)
            self.candidates = np.minimum(index, target.points.shape[0] - 1)
            self.found = index < target.points.shape[0]
            self.moved_m = 0.0
            if self._source_smoothness is not None:
                d = np.abs(self._source_smoothness[:, None]
                           - target.point_smoothness[self.candidates])
                self.mismatch = (self._affinity_m * np.nan_to_num(d, nan=0.0)) ** 2
        # |q - p|^2 = |q|^2 - 2 q.p + |p|^2 without an (n, k, 3) difference array.
        dot = np.einsum('nkj,nj->nk', target.points[self.candidates], world)
        d2 = target.squared_norms[self.candidates] - 2.0 * dot + np.einsum(
            'ij,ij->i', world, world)[:, None]
        d2 = np.where(self.found & (d2 <= self.max_distance_m ** 2), d2, np.inf)
        best = np.argmin(d2 if self.mismatch is None else d2 + self.mismatch, axis=1)
        rows = np.arange(world.shape[0])
        valid = np.flatnonzero(np.isfinite(d2[rows, best]))
        return valid, self.candidates[valid, best[valid]]


def rotation_of(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula (scipy's Rotation costs ~10x more per call at this size)."""
    theta = float(np.linalg.norm(rotvec))
    if theta < 1e-12:
        return np.eye(3)
    k = rotvec / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def apply_update(T: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """T moved by dx = (translation, rotation about T's origin), world axes."""
    out = np.eye(4)
    R = rotation_of(dx[3:])
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + dx[:3]
    return out
