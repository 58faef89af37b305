"""The spectral filter: per-point graph frequency of a scan and band-mask filtering.

Steps per scan (DESIGN sections 1-2): build the scan's graph, estimate lambda_max of each of its
blocks (batched Lanczos), let the frequency definition (`frequency.py`, one class each) give
every node a frequency nu and a band, and keep the points whose band is in the mask.

Graphs:
- `scan_line` (default when the cloud has the VLP-16 `ring` field): every point joined to its
  azimuth neighbour on its ring and to the nearest-azimuth point of the ring above, Gaussian
  weights of the 3-D distance, cut at tau. One block for the whole scan, no KD-tree.
- `slice` (the paper's, and the fallback without `ring`): slice along z, project each slice to
  (x, y), thresholded Gaussian graph per slice (one block-diagonal matrix). Points of one slice
  closer than SLICE_NODE_M share one graph node.

Decisions (measured in benchmarks/bench_frequency_classes.py and bench_spectral.py on
simulated VLP-16 scans; tables in docs/method.md):
- The default definition is `ldos_mean` on the scan-line graph: exact, local, ~10 ms a scan,
  and it tells ground and trunks from canopy (the `signal` definition puts ~97 % of the points
  in band 1 and carries ~0.06 bits about the surface).
- Points with no spectrum get band 0 and nu = NaN: isolated points (no neighbour within tau)
  and, for the slice graph, points outside [z_min_m, z_max_m). `keep_isolated` decides whether
  a mask keeps the isolated ones (default True, so the all-pass mask returns every point); the
  ones outside the z range are always kept; points with a non-finite coordinate never.
- `signal` centres the position signal per connected component: the indicator of each
  component is in the nullspace of L, so a per-component offset is pure nu = 0 energy;
  centring per slice leaves it in band 1, which then wins the argmax for every point.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from gft_odom.core.geometry import finite_rows
from gft_odom.core.spectral.bands import BandMask, validate_n_bands
from gft_odom.core.spectral.chebyshev import lambda_max_per_slice
from gft_odom.core.spectral.frequency import (
    REGISTRY,
    SpectralGraph,
    make_definition,
)
from gft_odom.core.spectral.graph import (
    SCAN_LINE_WEIGHTS,
    GraphLaplacian,
    ScanLineLaplacian,
    components,
    gaussian_graph,
    scan_line_graph,
)
from gft_odom.core.spectral.slicing import Slices, slice_points, voxelise
from gft_odom.errors import ConfigError, SpectralError

log = logging.getLogger(__name__)

GRAPHS = ('scan_line', 'slice')
SOLVERS = ('chebyshev', 'exact')
# lambda_max of the slice graphs: batched Lanczos, 30 steps within 4e-4 (median) of ARPACK,
# worst underestimate 3e-4 (20 steps: 3e-3, 6e-3). The scan-line graph's L is tridiagonal: its
# lambda_max is computed exactly (bisection).
LANCZOS_ITERATIONS = 30
# Slice graph: points of one slice closer than this share one graph node (see `voxelise`).
SLICE_NODE_M = 0.05


@dataclass(frozen=True)
class SpectralConfig:
    """Parameters of the spectral filter, with the reasons for their defaults.

    Geometry is in the sensor frame of a VLP-16 on a Jackal (sensor ~0.7 m above ground).
    """

    # Which graph the frequencies are computed on: 'scan_line' (needs the `ring` field; clouds
    # without it use 'slice') or 'slice' (the paper's per-slice 2-D graph).
    graph: str = 'scan_line'
    # A name from `frequency.REGISTRY`: 'ldos_mean' (the weighted degree over lambda_max) or
    # 'signal' (the paper's band responses of the position signal).
    method: str = 'ldos_mean'
    n_bands: int = 10
    # Default all-pass: a mask is chosen by the band search.
    band_mask: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10)
    # Isolated points (no neighbour within tau) have no spectrum (band 0); kept so that the
    # all-pass mask returns the input.
    keep_isolated: bool = True
    # Edge threshold tau (both graphs) and Gaussian width sigma of the slice graph: 0.2 m joins
    # neighbouring points of one ring (3.5 cm apart at 10 m, 14 cm at 40 m) and adjacent
    # trunk/leaf returns, but not different trees or rows; sigma = tau / 2 makes the weight
    # fall to exp(-2) at the threshold. tau sets the cost: |E| grows with tau^2 on the dense
    # near-ground slices (0.3 m: 1.8x the edges and time of 0.2 m in bench_spectral).
    tau_m: float = 0.2
    sigma_m: float = 0.1
    # Gaussian width of the scan-line graph (3-D distance, same tau): 0.05 m separates the
    # smooth runs of points on ground and trunks (neighbours a few cm apart) from the ragged
    # canopy.
    scan_line_sigma_m: float = 0.05
    # How scan-line edges are weighed (graph.SCAN_LINE_WEIGHTS): 'range_slope' (Gaussian of the
    # range slope along the ring: range-invariant; tells the surface best on held-out labelled
    # scans, docs/method.md) or 'distance' (Gaussian of the 3-D step: nu falls with range).
    scan_line_weight: str = 'range_slope'
    # The paper's slices: thickness h (a VLP-16 ring spacing is 2 deg, ~0.35 m at 10 m; 0.25 m
    # slices hold about one ring per range) and the z range sliced (ground near z = -0.7 m,
    # citrus trees 3-4 m tall). Points outside it have no spectrum (band 0) and are kept.
    slice_thickness_m: float = 0.25
    z_min_m: float = -1.5
    z_max_m: float = 4.0
    # `signal`: 'chebyshev' (Jackson-damped band filters of order chebyshev_order) or 'exact'
    # (eigh for blocks of up to 1000 nodes, Chebyshev above).
    solver: str = 'chebyshev'
    # The same band as the exact path for 98.1 % of the points at 20 (95.7 % at 10, 98.7 % at
    # 30, 99.0 % at 60) in bench_spectral; the cost is linear in the order.
    chebyshev_order: int = 20

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""
        for name in ('slice_thickness_m', 'tau_m', 'sigma_m', 'scan_line_sigma_m'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ConfigError(f'spectral.{name} must be a finite number > 0, got {value!r}')
        if not (np.isfinite(self.z_min_m) and np.isfinite(self.z_max_m)
                and self.z_max_m > self.z_min_m):
            raise ConfigError(f'spectral.z_max_m ({self.z_max_m}) must be > z_min_m '
                              f'({self.z_min_m}), both finite')
        if not SLICE_NODE_M < self.tau_m:
            raise ConfigError(f"spectral.tau_m must exceed the slice graph's node size "
                              f'({SLICE_NODE_M} m), got {self.tau_m}')
        validate_n_bands(self.n_bands)
        BandMask.parse(tuple(self.band_mask), self.n_bands)
        for name, allowed in (('method', tuple(sorted(REGISTRY))), ('solver', SOLVERS),
                              ('graph', GRAPHS), ('scan_line_weight', SCAN_LINE_WEIGHTS)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f'spectral.{name} must be one of {list(allowed)}, '
                                  f'got {getattr(self, name)!r}')
        if not 1 <= self.chebyshev_order <= 500:
            raise ConfigError(f'spectral.chebyshev_order must be in 1..500, '
                              f'got {self.chebyshev_order}')


@dataclass(frozen=True)
class PointFrequencies:
    """Per-point frequency of one scan, computed once and re-filtered with any mask.

    nu (N,) float32 in [0, 1], NaN where the point has no spectrum; band (N,) int16 in 0..B
    (0 = no spectrum); `isolated` and `in_range` say why a band-0 point has none; `finite`
    marks points with finite coordinates; response (N, B) float32 band responses when asked
    for (`signal` only, zeros for band-0 points).
    """

    nu: np.ndarray
    band: np.ndarray
    n_bands: int
    isolated: np.ndarray
    in_range: np.ndarray
    finite: np.ndarray
    n_slices: int
    response: np.ndarray | None = None
    timings_s: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.nu.shape[0])


@dataclass(frozen=True)
class FilterResult:
    """Outcome of `SpectralFilter.apply`: which points are kept, and every point's frequency."""

    keep: np.ndarray
    nu: np.ndarray
    band: np.ndarray
    n_slices: int
    timings_s: dict


def keep_mask(freqs: PointFrequencies, band_mask: BandMask, keep_isolated: bool = True
              ) -> np.ndarray:
    """(N,) bool: points whose band is in the mask, the points outside the sliced z range,
    and (`keep_isolated`) the isolated ones."""
    if band_mask.n_bands != freqs.n_bands:
        raise ConfigError(f'band mask {band_mask} has {band_mask.n_bands} bands but the '
                          f'frequencies were computed for n_bands = {freqs.n_bands}')
    keep = band_mask.lookup()[freqs.band]
    if keep_isolated:
        keep |= freqs.isolated
    keep |= ~freqs.in_range
    return keep & freqs.finite




class SpectralFilter:
    """Graph-frequency analysis and band-pass filtering of single scans (see module doc)."""

    def __init__(self, config: SpectralConfig | None = None,
                 band_mask: BandMask | None = None) -> None:
        """`config` validated here (defaults: `SpectralConfig()`); `band_mask` None = the
        config's mask."""
        self.config = SpectralConfig() if config is None else config
        self.config.validate()
        self.n_bands = self.config.n_bands
        self.band_mask = (BandMask.parse(tuple(self.config.band_mask), self.n_bands)
                          if band_mask is None else band_mask)
        self.definition = make_definition(self.config)
        self._warned_no_ring = False

    @classmethod
    def from_config(cls, cfg: SpectralConfig) -> 'SpectralFilter':
        """The filter of a `SpectralConfig` (same as the constructor)."""
        return cls(cfg)

    @property
    def keep_isolated(self) -> bool:
        """Whether masks keep isolated points (band 0)."""
        return self.config.keep_isolated

    def keeps_every_finite_point(self, band_mask: BandMask | None = None) -> bool:
        """Whether `band_mask` (default: the filter's) keeps every point with finite
        coordinates whatever its frequency: all bands, and band 0 kept for both reasons."""
        mask = self.band_mask if band_mask is None else band_mask
        return mask.is_all_pass and self.keep_isolated

    # -- public API ------------------------------------------------------------------------

    def frequencies(self, points_xyz: np.ndarray, n_bands: int | None = None,
                    with_response: bool = False, ring: np.ndarray | None = None
                    ) -> PointFrequencies:
        """Band and nu of every point for `n_bands` bands (default: the filter's).

        `ring` (N,) laser ring of every point, for the scan-line graph; `with_response` also
        returns the (N, B) band responses (definitions that have them).
        """
        n = self.n_bands if n_bands is None else n_bands
        return self.frequencies_multi(points_xyz, (n,), with_response, ring)[
            validate_n_bands(n)]

    def scan_frequencies(self, scan, n_bands: int | None = None) -> PointFrequencies:
        """`frequencies` of a `Scan` (uses its `ring` when it has one)."""
        return self.frequencies(scan.points_xyz, n_bands, ring=scan.ring)

    def frequencies_multi(self, points_xyz: np.ndarray, n_bands_list,
                          with_response: bool = False, ring: np.ndarray | None = None
                          ) -> dict[int, PointFrequencies]:
        """Frequencies for several band counts, sharing graph, lambda_max and preparation
        (the band search's B = 2..10 cost little more than one B)."""
        counts = [validate_n_bands(n) for n in n_bands_list]
        graph = self.graph(points_xyz, ring)
        t = time.perf_counter()
        self.definition.prepare(graph)
        graph.timings_s['prepare'] = time.perf_counter() - t
        return {n: self._assign(graph, n, with_response) for n in counts}

    def keep_mask(self, freqs: PointFrequencies, band_mask: BandMask | None = None
                  ) -> np.ndarray:
        """Re-filter cached frequencies with any mask (default: the filter's own)."""
        mask = self.band_mask if band_mask is None else band_mask
        return keep_mask(freqs, mask, self.keep_isolated)

    def apply(self, points_xyz: np.ndarray, band_mask: BandMask | None = None,
              ring: np.ndarray | None = None) -> FilterResult:
        """Frequencies of the scan and the points kept by the mask (default: the filter's)."""
        t0 = time.perf_counter()
        mask = self.band_mask if band_mask is None else band_mask
        freqs = self.frequencies(points_xyz, mask.n_bands, ring=ring)
        keep = self.keep_mask(freqs, mask)
        timings = dict(freqs.timings_s)
        timings['total'] = time.perf_counter() - t0
        return FilterResult(keep=keep, nu=freqs.nu, band=freqs.band, n_slices=freqs.n_slices,
                            timings_s=timings)

    def graph(self, points_xyz: np.ndarray, ring: np.ndarray | None = None) -> SpectralGraph:
        """The scan's graph (scan-line when configured and `ring` is given, else slices),
        with lambda_max of each block and, when the definition needs it, the position signal."""
        points = np.asarray(points_xyz)
        if points.ndim != 2 or points.shape[1] != 3:
            raise SpectralError(f'points_xyz must have shape (N, 3), got {points.shape}')
        points = points.astype(np.float64, copy=False)
        if ring is not None and np.shape(ring) != (points.shape[0],):
            raise SpectralError(f'ring must have shape ({points.shape[0]},), '
                                f'got {np.shape(ring)}')
        use_scan_line = self.config.graph == 'scan_line' and ring is not None
        if self.config.graph == 'scan_line' and ring is None and not self._warned_no_ring:
            log.warning("the cloud has no `ring` field: spectral.graph 'scan_line' falls back to "
                        "the slice graph")
            self._warned_no_ring = True
        timings: dict[str, float] = {}
        t = time.perf_counter()
        finite = finite_rows(points)
        if use_scan_line:
            index = np.flatnonzero(finite) if not finite.all() else None
            coords = points if index is None else points[index]
            ring_f = np.asarray(ring) if index is None else np.asarray(ring)[index]
            L, order = scan_line_graph(coords, ring_f, self.config.tau_m,
                                       self.config.scan_line_sigma_m,
                                       self.config.scan_line_weight)
            if index is not None:
                order = index[order]
            sl = Slices(order=order, starts=np.array([0, order.size], dtype=np.int64),
                        slice_of_point=np.zeros(order.size, dtype=np.int64), in_range=finite,
                        z_bottom_m=np.full(1, np.nan))
            coords = points[order] if self.definition.needs_position_signal else None
            node_of_point = np.arange(order.size)
            node_block = sl.slice_of_point
            starts = sl.starts
            points_per_node = 1
        else:
            z = np.where(finite, points[:, 2], np.nan)
            sl = slice_points(z, self.config.slice_thickness_m, self.config.z_min_m,
                              self.config.z_max_m)
            coords, node_block, starts, node_of_point = voxelise(
                points[sl.order, :2], sl.slice_of_point, sl.n_slices, SLICE_NODE_M)
            timings['slice'] = time.perf_counter() - t
            t = time.perf_counter()
            W = gaussian_graph(coords, node_block, self.config.tau_m, self.config.sigma_m)
            points_per_node = np.bincount(node_of_point, minlength=coords.shape[0])
            L = GraphLaplacian(W)
        # A node with no neighbour is isolated (band 0) unless it merges several points: those
        # form a cluster tighter than the voxel, i.e. a perfectly smooth component (nu = 0).
        isolated_nodes = (L.degree == 0.0) & (points_per_node <= 1)
        X = (self._centred_signal(L.W, coords, node_block)
             if self.definition.needs_position_signal else None)
        timings['graph'] = time.perf_counter() - t
        t = time.perf_counter()
        if isinstance(L, ScanLineLaplacian):  # tridiagonal: exact, cheaper than Lanczos
            lmax = np.array([L.lambda_max()])
        else:
            lmax = lambda_max_per_slice(L, starts, 'lanczos', LANCZOS_ITERATIONS)
        timings['lambda_max'] = time.perf_counter() - t
        return SpectralGraph(n_points=points.shape[0], sl=sl, node_of_point=node_of_point,
                             starts=starts, node_block=node_block, L=L,
                             isolated_nodes=isolated_nodes, lmax=lmax, finite=finite, X=X,
                             timings_s=timings)

    # -- steps ------------------------------------------------------------------------------

    def _centred_signal(self, W: sp.csr_matrix, coords: np.ndarray, node_block: np.ndarray
                        ) -> np.ndarray:
        """Position signal X (n, c), minus its mean per connected component."""
        if coords.shape[0] == 0:
            return np.zeros((0, coords.shape[1]))
        labels = components(W)[1]
        count = np.bincount(labels).astype(np.float64)
        mean = np.column_stack([np.bincount(labels, weights=coords[:, c]) / count
                                for c in range(coords.shape[1])])
        return coords - mean[labels]

    def _assign(self, graph: SpectralGraph, n_bands: int, with_response: bool = False
                ) -> PointFrequencies:
        """The definition's node frequencies, spread to the input points; band 0 / NaN for
        isolated nodes and points with no node."""
        t = time.perf_counter()
        node = self.definition.assign(graph, n_bands)
        nu_s = np.asarray(node.nu, dtype=np.float64).copy()
        band_s = np.asarray(node.band, dtype=np.int16).copy()
        nu_s[graph.isolated_nodes] = np.nan
        band_s[graph.isolated_nodes] = 0
        N = graph.n_points
        order, idx = graph.sl.order, graph.node_of_point
        nu = np.full(N, np.nan, dtype=np.float32)
        band = np.zeros(N, dtype=np.int16)
        isolated = np.zeros(N, dtype=bool)
        nu[order] = nu_s[idx]
        band[order] = band_s[idx]
        isolated[order] = graph.isolated_nodes[idx]
        response = None
        if node.response is not None and with_response:
            response = np.zeros((N, n_bands), dtype=np.float32)
            response[order] = node.response[idx]
        timings = dict(graph.timings_s)
        timings['assign'] = time.perf_counter() - t
        return PointFrequencies(nu=nu, band=band, n_bands=n_bands, isolated=isolated,
                                in_range=graph.sl.in_range.copy(), finite=graph.finite,
                                n_slices=graph.sl.n_slices, response=response, timings_s=timings)
