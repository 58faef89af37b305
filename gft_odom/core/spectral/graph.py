r"""Thresholded Gaussian graph of every slice, all slices in one block-diagonal sparse matrix.

Edge (m, n) when \|x_m - x_n\| <= tau (2-D distance within one slice), weight
W_mn = exp(-\|x_m - x_n\|^2 / (2 sigma^2)); unnormalised (combinatorial) Laplacian L = D - W.
All slices go through ONE KD-tree: each slice is lifted to its own height (slice number times a
gap larger than tau) in a third coordinate, so pairs never cross slices and one
`query_pairs` call builds every slice's graph.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from gft_odom.errors import SpectralError


def _check_edge_scales(tau_m: float, sigma_m: float) -> None:
    if not tau_m > 0.0 or not sigma_m > 0.0:
        raise SpectralError(f'tau_m and sigma_m must be > 0, got tau_m={tau_m}, '
                            f'sigma_m={sigma_m}')


def gaussian_graph(xy_m: np.ndarray, slice_of_point: np.ndarray | None, tau_m: float,
                   sigma_m: float, dtype=np.float64) -> sp.csr_matrix:
    """Symmetric weight matrix W (n, n), CSR, zero diagonal; no edge ever joins two slices."""
    _check_edge_scales(tau_m, sigma_m)
    xy_m = np.asarray(xy_m, dtype=np.float64)
    n = xy_m.shape[0]
    if n < 2:
        return sp.csr_matrix((n, n), dtype=dtype)
    if slice_of_point is None:
        lifted = xy_m
    else:
        # Slices sit 3 tau apart in the third coordinate: no pair across slices is within tau.
        lift = np.asarray(slice_of_point, dtype=np.float64) * (3.0 * tau_m)
        lifted = np.column_stack([xy_m, lift])
    tree = cKDTree(lifted, balanced_tree=False, compact_nodes=False)
    pairs = tree.query_pairs(tau_m, output_type='ndarray').astype(np.int32, copy=False)
    i, j = pairs[:, 0], pairs[:, 1]
    dx = xy_m[i, 0] - xy_m[j, 0]
    dy = xy_m[i, 1] - xy_m[j, 1]
    w = np.exp((dx * dx + dy * dy) * (-0.5 / sigma_m**2)).astype(dtype, copy=False)
    rows = np.concatenate([i, j])
    cols = np.concatenate([j, i])
    # query_pairs yields each pair once: no duplicates to sum.
    return sp.coo_matrix((np.concatenate([w, w]), (rows, cols)), shape=(n, n)).tocsr()


class GraphLaplacian:
    """L = D - W kept as (W, degree): `L @ x` costs one product with W and no extra matrix.

    Quacks like the parts of a sparse matrix the solvers use (`@`, `shape`, `diagonal`,
    `block`, `tocsr`, `toarray`).
    """

    def __init__(self, W: sp.spmatrix) -> None:
        self.W = sp.csr_matrix(W)
        self.degree = np.asarray(self.W.sum(axis=1)).ravel()
        self.shape = self.W.shape
        self.dtype = self.W.dtype

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        d = self.degree if x.ndim == 1 else self.degree[:, None]
        return d * x - self.W @ x

    def diagonal(self) -> np.ndarray:
        """The diagonal of L: the weighted degrees."""
        return self.degree

    def block(self, lo: int, hi: int) -> sp.csr_matrix:
        """The diagonal block [lo, hi) of L as CSR."""
        Wb = self.W[lo:hi, lo:hi]
        return (sp.diags(self.degree[lo:hi]) - Wb).tocsr()

    def tocsr(self) -> sp.csr_matrix:
        """L as a CSR matrix."""
        return self.block(0, self.shape[0])

    def toarray(self) -> np.ndarray:
        """L as a dense array (small graphs only)."""
        return self.tocsr().toarray()


def laplacian(W: sp.spmatrix) -> sp.csr_matrix:
    """Unnormalised Laplacian L = D - W, with D = diag(row sums of W)."""
    W = sp.csr_matrix(W)
    degree = np.asarray(W.sum(axis=1)).ravel()
    return (sp.diags(degree.astype(W.dtype), format='csr') - W).tocsr()


def components(W: sp.spmatrix) -> tuple[int, np.ndarray]:
    """Connected components of the graph: (count, label of every vertex)."""
    n_comp, labels = connected_components(W, directed=False)
    return int(n_comp), labels


# Azimuth quantised to 16 bits for sorting (0.0055 deg, far below the VLP-16's 0.2 deg columns):
# two stable 16-bit sorts (numpy's radix sort) order the points by (ring, azimuth).
_AZIMUTH_BINS = 65535
# Components solved first in ScanLineLaplacian.lambda_max (the rest are usually ruled out).
_EXACT_FIRST_COMPONENTS = 8


def scan_line_order(points_xyz: np.ndarray, ring: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, same_ring): the input indices sorted by (ring, azimuth), and `same_ring[k]`
    when sorted points k and k + 1 lie on one ring (neighbours along that ring's scan line)."""
    xyz = np.asarray(points_xyz, dtype=np.float64)
    n = xyz.shape[0]
    ring = np.asarray(ring)
    if ring.shape != (n,):
        raise SpectralError(f'ring must have shape ({n},), got {ring.shape}')
    if ring.dtype != np.uint16:
        if ring.size and (ring.min() < 0 or ring.max() > np.iinfo(np.uint16).max):
            raise SpectralError(f'ring values must be in 0..65535, got {ring.min()}..'
                                f'{ring.max()}')
        ring = ring.astype(np.uint16)
    azimuth_bin = ((np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi)
                   * (_AZIMUTH_BINS / (2.0 * np.pi))).astype(np.uint16)
    order = np.argsort(azimuth_bin, kind='stable')
    order = np.take(order, np.argsort(np.take(ring, order), kind='stable'))
    ring_sorted = np.take(ring, order)
    return order, ring_sorted[1:] == ring_sorted[:-1]


class ScanLineLaplacian(GraphLaplacian):
    """L = D - W of the scan-line graph, nodes in scan-line order: W is tridiagonal.

    Each point is joined to its azimuth neighbours on its own ring (`w_next[k]` is the weight
    of the edge between sorted points k and k + 1, 0 where there is none), so every
    connected component is a weighted path and L is a tridiagonal matrix: products with it
    are three vector operations, and its largest eigenvalue is found exactly by bisection on
    the few components that can hold it (`lambda_max`).
    """

    def __init__(self, w_next: np.ndarray, n: int | None = None) -> None:
        """`w_next` (n - 1,): weight of the edge (k, k + 1) in scan-line order."""
        self.w_next = np.asarray(w_next, dtype=np.float64)
        n = self.w_next.shape[0] + 1 if n is None else int(n)
        self.degree = np.zeros(n)
        if n > 1:
            self.degree[:-1] += self.w_next
            self.degree[1:] += self.w_next
        self.shape = (n, n)
        self.dtype = np.dtype(np.float64)
        self._W = None

    @classmethod
    def empty(cls, n: int) -> 'ScanLineLaplacian':
        """The Laplacian of `n` points with no edge."""
        return cls(np.zeros(max(n - 1, 0)), n)

    @property
    def W(self) -> sp.csr_matrix:
        """W as a sparse matrix, built on first use (only some definitions need it)."""
        if self._W is None:
            n = self.shape[0]
            self._W = (sp.diags([self.w_next, self.w_next], [-1, 1], shape=(n, n), format='csr')
                       if n > 1 else sp.csr_matrix((n, n)))
            self._W.eliminate_zeros()
        return self._W

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        w = self.w_next if x.ndim == 1 else self.w_next[:, None]
        d = self.degree if x.ndim == 1 else self.degree[:, None]
        out = d * x
        if x.shape[0] > 1:
            out[:-1] -= w * x[1:]
            out[1:] -= w * x[:-1]
        return out

    def lambda_max(self) -> float:
        """Largest eigenvalue of L, exactly (LAPACK bisection on tridiagonal blocks, to 1e-9).

        lambda_max is the largest over the connected components (weighted paths), and a
        component's is at most max_k (d_k + d_k+1) (Anderson-Morley). The exact value of the
        components with the largest bounds is a lower bound that rules out every component
        whose bound is below it; only the rest (usually none) are solved too.
        """
        n = self.shape[0]
        if n < 2 or not np.any(self.w_next > 0.0):
            return 0.0
        d, w = self.degree, self.w_next
        comp = np.cumsum(np.r_[False, w <= 0.0])  # component of every node
        bound = np.zeros(int(comp[-1]) + 1)
        np.maximum.at(bound, comp[:-1], np.where(w > 0.0, d[:-1] + d[1:], 0.0))
        first = np.argsort(-bound)[:_EXACT_FIRST_COMPONENTS]
        chosen = np.zeros(bound.size, dtype=bool)
        chosen[first] = True
        best = self._largest(comp, chosen)
        rest = ~chosen & (bound > best)
        if np.any(rest):
            best = max(best, self._largest(comp, rest))
        return best

    def _largest(self, comp: np.ndarray, chosen: np.ndarray) -> float:
        """Largest eigenvalue of the principal block of the `chosen` components (their union
        is block-diagonal: consecutive kept nodes of different components get a 0 coupling)."""
        nodes = np.flatnonzero(chosen[comp])
        n = self.shape[0]
        sub_w = np.where(np.diff(nodes) == 1, self.w_next[np.minimum(nodes[:-1], n - 2)], 0.0)
        m = nodes.size
        return float(scipy.linalg.eigvalsh_tridiagonal(
            self.degree[nodes], -sub_w, select='i', select_range=(m - 1, m - 1),
            lapack_driver='stebz', tol=1e-9, check_finite=False)[0])


# How the scan-line graph weighs an edge between azimuth neighbours on one ring.
SCAN_LINE_WEIGHTS = ('distance', 'range_slope')


def scan_line_graph(points_xyz: np.ndarray, ring: np.ndarray, tau_m: float, sigma_m: float,
                    weight: str = 'distance', slope_sigma: float = 2.0,
                    max_gap_rad: float = 0.02, noise_floor_m: float = 0.05
                    ) -> tuple[ScanLineLaplacian, np.ndarray]:
    """The scan-line graph: (L, order), node k being input point `order[k]`.

    Every point is joined to its azimuth neighbours on its own ring. Uses only the `ring`
    field and the azimuth: no KD-tree, and no assumption that the cloud is organised or in
    firing order. Edges across rings were measured to add nothing to what the frequency says
    about the surface (docs/method.md), and without them L is tridiagonal.

    `weight`:
    - 'distance': the Gaussian `exp(-d^2 / (2 sigma^2))` of their 3-D distance d, cut at
      `tau_m`. Neighbours on one ring are ~0.0035 r apart (0.2 deg), so the weight, and nu,
      fall with the range r: a far wall looks like canopy.
    - 'range_slope': the Gaussian of the range slope `|r_k+1 - r_k| / (r_mean * d_azimuth)`
      (the tangent of the incidence angle on a smooth surface) with width `slope_sigma`, cut
      where the azimuth gap exceeds `max_gap_rad` (missing returns). The step along the ring
      is floored by `noise_floor_m` (range noise: near the sensor the step is ~1 cm and the
      noise alone would read as a steep slope). Range-invariant: ground along a ring has
      slope ~0, a trunk a few, porous canopy (returns at random depths) tens.
    """
    _check_edge_scales(tau_m, sigma_m)
    xyz = np.asarray(points_xyz, dtype=np.float64)
    n = xyz.shape[0]
    if n < 2:
        return ScanLineLaplacian.empty(n), np.arange(n)
    order, same_ring = scan_line_order(xyz, ring)
    # np.take: row gathers several times faster than fancy indexing (measured).
    xyz = np.take(xyz, order, axis=0)
    if weight == 'range_slope':
        r = np.sqrt(np.einsum('ij,ij->i', xyz, xyz))
        azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
        gap = np.abs(np.angle(np.exp(1j * (azimuth[1:] - azimuth[:-1]))))
        gap = np.maximum(gap, 1e-6)
        step_m = np.hypot(0.5 * (r[1:] + r[:-1]) * gap, noise_floor_m)
        slope = np.abs(r[1:] - r[:-1]) / step_m
        w = np.where(same_ring & (gap <= max_gap_rad),
                     np.exp(np.minimum(slope * slope * (-0.5 / slope_sigma**2), 0.0)), 0.0)
        return ScanLineLaplacian(w), order
    if weight != 'distance':
        raise SpectralError(f'scan-line weight must be one of {SCAN_LINE_WEIGHTS}, '
                            f'got {weight!r}')
    step = xyz[1:] - xyz[:-1]
    d2 = np.einsum('ij,ij->i', step, step)
    w = np.where(same_ring & (d2 <= tau_m * tau_m), np.exp(d2 * (-0.5 / sigma_m**2)), 0.0)
    return ScanLineLaplacian(w), order


def scan_line_edges(points_xyz: np.ndarray, ring: np.ndarray, tau_m: float = np.inf
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The scan-line graph's edges (i, j) as input indices, each edge once (within `tau_m`)."""
    L, order = scan_line_graph(points_xyz, ring, tau_m, sigma_m=np.inf)  # every weight 1
    k = np.flatnonzero(L.w_next > 0.0)
    return order[k], order[k + 1]
