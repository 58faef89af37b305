"""The spectral filter: per-point graph frequency of a scan and band-mask filtering.

Steps per scan (DESIGN sections 1-2): slice along z, project each slice to (x, y), build the
thresholded Gaussian graph of every slice (one block-diagonal matrix), centre the position
signal X per connected component, estimate lambda_max per slice (batched Lanczos), compute the
band responses (Chebyshev recursion, or dense eigh for small slices), give each point a band and
a frequency nu, and keep the points whose band is in the mask.

Decisions (DESIGN leaves them open; measured in benchmarks/bench_spectral.py on simulated
VLP-16 scans, figures in benchmarks/results/spectral.json):
- `signal` band = argmax over bands of the response r_mb (DESIGN 2, the default
  `band_assignment='argmax'`); nu = response-weighted mean of the band centres. A centred
  position signal is smooth on the graph (a ring arc's X is nearly the first eigenvector), so
  this puts ~93 % of the points in band 1. `band_assignment='relative'` takes the argmax of
  r_mb divided by the slice's mean r_b instead (the band where the point stands out from its
  slice) and spreads the points over all bands (23/16/11/10/8/9/9/8/5/2 %); it is the
  lead's call which one the band search uses.
- Centring per connected component (default): the indicator of each component is in the
  nullspace of L, so any per-component offset of X is pure nu = 0 energy. Centring per slice
  leaves every component's offset from the slice mean in band 1, which then wins the argmax for
  100 % of the points (measured) and says nothing about shape. Per component, X has no
  nullspace part and band 1 means genuinely smooth shape.
- Points with no spectrum get band 0 and nu = NaN: isolated points (no neighbour within tau)
  and points outside [z_min_m, z_max_m). `keep_isolated` and `keep_out_of_range` decide whether
  a mask keeps them (both default True, so the all-pass mask returns every point); points with
  a non-finite coordinate are never kept.
- Points of one slice closer than `voxel_size_m` (0.05 m, a quarter of tau) share one graph
  node: 2.3x less CPU per scan, same band as the unmerged graph for 98 % of the points.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from gft_odom.core.spectral.bands import BandMask, band_of_nu, validate_n_bands
from gft_odom.core.spectral.chebyshev import (
    band_responses_from_terms,
    chebyshev_terms,
    lambda_max_per_slice,
)
from gft_odom.core.spectral.gft import (
    band_responses_exact,
    dominant_frequency,
    fourier_basis,
    signal_frequency,
)
from gft_odom.core.spectral.graph import GraphLaplacian, components, gaussian_graph
from gft_odom.core.spectral.slicing import Slices, slice_points, voxelise
from gft_odom.errors import ConfigError, SpectralError

log = logging.getLogger(__name__)

METHODS = ('signal', 'dominant')
SOLVERS = ('chebyshev', 'exact')
CENTRINGS = ('component', 'slice')
BAND_ASSIGNMENTS = ('argmax', 'relative')
LAMBDA_MAX_METHODS = ('lanczos', 'arpack')


@dataclass(frozen=True)
class SpectralConfig:
    """Parameters of the spectral filter, with the reasons for their defaults.

    Geometry is in the sensor frame of a VLP-16 on a Jackal (sensor ~0.7 m above ground).
    """

    # Layer thickness h: a VLP-16 ring spacing is 2 deg, ~0.35 m at 10 m; 0.25 m slices hold
    # about one ring per range, so a slice is a clean 2-D section (trunk arcs, canopy outline).
    slice_thickness_m: float = 0.25
    # Ground is near z = -0.7 m; the range reaches below it (slopes, pitch) and above the
    # canopy (citrus trees are ~3-4 m), so every real return gets a frequency, as in the paper.
    z_min_m: float = -1.5
    z_max_m: float = 4.0
    # Points outside [z_min_m, z_max_m) have no spectrum (band 0); kept so that no mask silently
    # deletes returns the filter never looked at (birds, overhanging branches, pits).
    keep_out_of_range: bool = True
    # Edge threshold tau and Gaussian width sigma: 0.2 m joins neighbouring points of one ring
    # (3.5 cm apart at 10 m, 14 cm at 40 m) and adjacent trunk/leaf returns, but not different
    # trees or rows; sigma = tau / 2 makes the weight fall to exp(-2) at the threshold. tau sets
    # the cost: |E| grows with tau^2 on the dense near-ground slices (0.3 m: 1.8x the edges and
    # time of 0.2 m in bench_spectral).
    tau_m: float = 0.2
    sigma_m: float = 0.1
    n_bands: int = 10
    # Default all-pass: the tuned mask is chosen later by the band search.
    band_mask: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10)
    method: str = 'signal'
    solver: str = 'chebyshev'
    # Order K of the Jackson-Chebyshev expansion: same band as the exact path for 98.1 % of the
    # points at K = 20 (95.7 % at 10, 98.7 % at 30, 99.0 % at 60) in bench_spectral; the cost
    # of the recursion is linear in K.
    chebyshev_order: int = 20
    # Batched Lanczos over all slices: 30 steps give lambda_max within 4e-4 (median) of ARPACK,
    # worst underestimate 3e-4 (20 steps: 3e-3, 6e-3), at a fraction of ARPACK's time.
    lambda_max_method: str = 'lanczos'
    lanczos_iterations: int = 30
    # Isolated points (no neighbour within tau) are band 0; kept so all-pass returns the input.
    keep_isolated: bool = True
    # The exact path (dense eigh, O(n^3) time, O(n^2) memory) is used for slices up to this
    # many graph nodes, Chebyshev above: 1000 nodes is ~0.3 s per slice; a whole VLP-16 scan
    # at 2000 took ~45 s on the 2-core test machine.
    exact_max_slice_points: int = 1000
    centring: str = 'component'
    # How a `signal` point gets its band: 'argmax' of the band responses r_mb (DESIGN 2), or
    # 'relative': argmax of r_mb / (mean of r_b over the slice), i.e. the band in which the
    # point stands out from its slice. Position signals are smooth, so with 'argmax' ~95 % of a
    # VLP-16 scan lands in band 1 (bench_spectral); 'relative' spreads the points over the bands.
    band_assignment: str = 'argmax'
    # Points of one slice closer than this share one graph node (0.0: off); see `voxelise`.
    voxel_size_m: float = 0.05

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""
        def positive(name: str) -> None:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ConfigError(f'spectral.{name} must be a finite number > 0, got {value!r}')

        for name in ('slice_thickness_m', 'tau_m', 'sigma_m'):
            positive(name)
        if not (np.isfinite(self.z_min_m) and np.isfinite(self.z_max_m)
                and self.z_max_m > self.z_min_m):
            raise ConfigError(f'spectral.z_max_m ({self.z_max_m}) must be > z_min_m '
                              f'({self.z_min_m}), both finite')
        validate_n_bands(self.n_bands)
        BandMask.parse(tuple(self.band_mask), self.n_bands)
        for name, allowed in (('method', METHODS), ('solver', SOLVERS),
                              ('band_assignment', BAND_ASSIGNMENTS),
                              ('centring', CENTRINGS),
                              ('lambda_max_method', LAMBDA_MAX_METHODS)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f'spectral.{name} must be one of {list(allowed)}, '
                                  f'got {getattr(self, name)!r}')
        if self.method == 'dominant' and self.solver != 'exact':
            raise ConfigError("spectral.method 'dominant' needs every eigenvector: set "
                              "solver 'exact' (Chebyshev only serves method 'signal')")
        if not 1 <= self.chebyshev_order <= 500:
            raise ConfigError(f'spectral.chebyshev_order must be in 1..500, '
                              f'got {self.chebyshev_order}')
        if not 2 <= self.lanczos_iterations <= 500:
            raise ConfigError(f'spectral.lanczos_iterations must be in 2..500, '
                              f'got {self.lanczos_iterations}')
        if not (np.isfinite(self.voxel_size_m) and 0.0 <= self.voxel_size_m < self.tau_m):
            raise ConfigError(f'spectral.voxel_size_m must be in [0, tau_m = {self.tau_m}), '
                              f'got {self.voxel_size_m}')
        if self.exact_max_slice_points < 1:
            raise ConfigError(f'spectral.exact_max_slice_points must be >= 1, '
                              f'got {self.exact_max_slice_points}')


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


def keep_mask(freqs: PointFrequencies, band_mask: BandMask, keep_isolated: bool = True,
              keep_out_of_range: bool = True) -> np.ndarray:
    """(N,) bool: points whose band is in the mask, plus band-0 points the flags keep."""
    if band_mask.n_bands != freqs.n_bands:
        raise ConfigError(f'band mask {band_mask} has {band_mask.n_bands} bands but the '
                          f'frequencies were computed for n_bands = {freqs.n_bands}')
    keep = band_mask.lookup()[freqs.band]
    if keep_isolated:
        keep |= freqs.isolated
    if keep_out_of_range:
        keep |= ~freqs.in_range
    return keep & freqs.finite


_DEFAULTS = SpectralConfig()


@dataclass
class _Analysis:
    """Everything about a scan that does not depend on the number of bands."""

    n_points: int
    sl: Slices
    node_of_point: np.ndarray  # graph node of every sorted in-range point
    starts: np.ndarray  # slice block boundaries over the nodes
    L: GraphLaplacian
    X: np.ndarray
    isolated_nodes: np.ndarray
    lmax: np.ndarray
    finite: np.ndarray
    terms: np.ndarray | None
    terms_rows: np.ndarray | None
    exact_slices: list
    timings_s: dict


class SpectralFilter:
    """Graph-frequency analysis and band-pass filtering of single scans (see module doc)."""

    def __init__(self, slice_thickness_m: float = _DEFAULTS.slice_thickness_m,
                 z_min_m: float = _DEFAULTS.z_min_m, z_max_m: float = _DEFAULTS.z_max_m,
                 tau_m: float = _DEFAULTS.tau_m, sigma_m: float = _DEFAULTS.sigma_m,
                 n_bands: int = _DEFAULTS.n_bands, band_mask: BandMask | None = None,
                 method: str = _DEFAULTS.method, solver: str = _DEFAULTS.solver,
                 chebyshev_order: int = _DEFAULTS.chebyshev_order,
                 lambda_max_method: str = _DEFAULTS.lambda_max_method,
                 lanczos_iterations: int = _DEFAULTS.lanczos_iterations,
                 keep_isolated: bool = _DEFAULTS.keep_isolated,
                 keep_out_of_range: bool = _DEFAULTS.keep_out_of_range,
                 exact_max_slice_points: int = _DEFAULTS.exact_max_slice_points,
                 centring: str = _DEFAULTS.centring, voxel_size_m: float = _DEFAULTS.voxel_size_m,
                 band_assignment: str = _DEFAULTS.band_assignment) -> None:
        """Plain arguments (defaults from `SpectralConfig`); `band_mask` None = all-pass."""
        self.slice_thickness_m = float(slice_thickness_m)
        self.z_min_m = float(z_min_m)
        self.z_max_m = float(z_max_m)
        self.tau_m = float(tau_m)
        self.sigma_m = float(sigma_m)
        self.n_bands = validate_n_bands(n_bands)
        self.band_mask = BandMask.all_pass(n_bands) if band_mask is None else band_mask
        self.method = method
        self.solver = solver
        self.chebyshev_order = int(chebyshev_order)
        self.lambda_max_method = lambda_max_method
        self.lanczos_iterations = int(lanczos_iterations)
        self.keep_isolated = bool(keep_isolated)
        self.keep_out_of_range = bool(keep_out_of_range)
        self.exact_max_slice_points = int(exact_max_slice_points)
        self.centring = centring
        self.voxel_size_m = float(voxel_size_m)
        self.band_assignment = band_assignment
        SpectralConfig(
            slice_thickness_m=self.slice_thickness_m, z_min_m=self.z_min_m,
            z_max_m=self.z_max_m, keep_out_of_range=self.keep_out_of_range, tau_m=self.tau_m,
            sigma_m=self.sigma_m, n_bands=self.n_bands,
            band_mask=tuple(self.band_mask.as_list()), method=method, solver=solver,
            chebyshev_order=self.chebyshev_order, lambda_max_method=lambda_max_method,
            lanczos_iterations=self.lanczos_iterations, keep_isolated=self.keep_isolated,
            exact_max_slice_points=self.exact_max_slice_points, centring=centring,
            voxel_size_m=self.voxel_size_m, band_assignment=band_assignment).validate()

    @classmethod
    def from_config(cls, cfg: SpectralConfig) -> 'SpectralFilter':
        """Unpack a validated `SpectralConfig` into constructor arguments."""
        cfg.validate()
        return cls(slice_thickness_m=cfg.slice_thickness_m, z_min_m=cfg.z_min_m,
                   z_max_m=cfg.z_max_m, tau_m=cfg.tau_m, sigma_m=cfg.sigma_m,
                   n_bands=cfg.n_bands,
                   band_mask=BandMask.parse(tuple(cfg.band_mask), cfg.n_bands),
                   method=cfg.method, solver=cfg.solver, chebyshev_order=cfg.chebyshev_order,
                   lambda_max_method=cfg.lambda_max_method,
                   lanczos_iterations=cfg.lanczos_iterations, keep_isolated=cfg.keep_isolated,
                   keep_out_of_range=cfg.keep_out_of_range,
                   exact_max_slice_points=cfg.exact_max_slice_points, centring=cfg.centring,
                   voxel_size_m=cfg.voxel_size_m, band_assignment=cfg.band_assignment)

    # -- public API ------------------------------------------------------------------------

    def frequencies(self, points_xyz: np.ndarray, n_bands: int | None = None,
                    with_response: bool = False) -> PointFrequencies:
        """Band and nu of every point for `n_bands` bands (default: the filter's).

        `with_response` also returns the (N, B) band responses (`signal` method only).
        """
        n = self.n_bands if n_bands is None else n_bands
        return self.frequencies_multi(points_xyz, (n,), with_response)[validate_n_bands(n)]

    def frequencies_multi(self, points_xyz: np.ndarray, n_bands_list,
                          with_response: bool = False) -> dict[int, PointFrequencies]:
        """Frequencies for several band counts, sharing graph, lambda_max and recursion
        (the band search's B = 2..10 cost little more than one B)."""
        counts = [validate_n_bands(n) for n in n_bands_list]
        analysis = self._analyse(points_xyz)
        return {n: self._assign(analysis, n, with_response) for n in counts}

    def keep_mask(self, freqs: PointFrequencies, band_mask: BandMask | None = None
                  ) -> np.ndarray:
        """Re-filter cached frequencies with any mask (default: the filter's own)."""
        mask = self.band_mask if band_mask is None else band_mask
        return keep_mask(freqs, mask, self.keep_isolated, self.keep_out_of_range)

    def apply(self, points_xyz: np.ndarray, band_mask: BandMask | None = None) -> FilterResult:
        """Frequencies of the scan and the points kept by the mask (default: the filter's)."""
        t0 = time.perf_counter()
        mask = self.band_mask if band_mask is None else band_mask
        freqs = self.frequencies(points_xyz, mask.n_bands)
        keep = self.keep_mask(freqs, mask)
        timings = dict(freqs.timings_s)
        timings['total'] = time.perf_counter() - t0
        return FilterResult(keep=keep, nu=freqs.nu, band=freqs.band, n_slices=freqs.n_slices,
                            timings_s=timings)

    # -- steps ------------------------------------------------------------------------------

    def _analyse(self, points_xyz: np.ndarray) -> _Analysis:
        points = np.asarray(points_xyz)
        if points.ndim != 2 or points.shape[1] != 3:
            raise SpectralError(f'points_xyz must have shape (N, 3), got {points.shape}')
        points = points.astype(np.float64, copy=False)
        timings: dict[str, float] = {}
        t = time.perf_counter()

        finite = np.all(np.isfinite(points), axis=1)
        z = np.where(finite, points[:, 2], np.nan)
        sl = slice_points(z, self.slice_thickness_m, self.z_min_m, self.z_max_m)
        xy, node_slice, starts, node_of_point = voxelise(
            points[sl.order, :2], sl.slice_of_point, sl.n_slices, self.voxel_size_m)
        timings['slice'] = time.perf_counter() - t

        t = time.perf_counter()
        W = gaussian_graph(xy, node_slice, self.tau_m, self.sigma_m)
        L = GraphLaplacian(W)
        # A node with no neighbour is isolated (band 0) unless it merges several points: those
        # form a cluster tighter than the voxel, i.e. a perfectly smooth component (nu = 0).
        points_per_node = np.bincount(node_of_point, minlength=xy.shape[0])
        isolated_nodes = (np.diff(W.indptr) == 0) & (points_per_node <= 1)
        X = self._centred_signal(W, xy, node_slice)
        timings['graph'] = time.perf_counter() - t

        t = time.perf_counter()
        lmax = lambda_max_per_slice(L, starts, self.lambda_max_method, self.lanczos_iterations)
        timings['lambda_max'] = time.perf_counter() - t

        t = time.perf_counter()
        sizes = np.diff(starts)
        if self.solver == 'exact':
            exact_slices = [s for s in range(sl.n_slices)
                            if sizes[s] <= self.exact_max_slice_points]
        else:
            exact_slices = []
        cheb = np.ones(sl.n_slices, dtype=bool)
        cheb[exact_slices] = False
        terms = rows = None
        if np.any(cheb & (sizes > 0)):
            if self.solver == 'exact':
                emit = log.debug if getattr(self, '_warned_large', False) else log.warning
                emit('%d slices exceed exact_max_slice_points = %d (largest %d nodes); their '
                     'points use the Chebyshev `signal` frequency',
                     int(cheb.sum()), self.exact_max_slice_points, int(sizes.max()))
                self._warned_large = True
            rows = np.flatnonzero(cheb[node_slice])
            scale = np.where(lmax > 0.0, 2.0 / np.where(lmax > 0.0, lmax, 1.0), 0.0)
            L_sub = L if rows.size == L.shape[0] else GraphLaplacian(L.W[rows][:, rows])
            terms = chebyshev_terms(L_sub, scale[node_slice[rows]], X[rows],
                                    self.chebyshev_order)
        timings['recursion'] = time.perf_counter() - t
        return _Analysis(points.shape[0], sl, node_of_point, starts, L, X, isolated_nodes, lmax,
                         finite, terms, rows, exact_slices, timings)

    def _centred_signal(self, W: sp.csr_matrix, xy: np.ndarray, node_slice: np.ndarray
                        ) -> np.ndarray:
        """Position signal X (n, 2), minus its mean per component (or per slice)."""
        if xy.shape[0] == 0:
            return np.zeros((0, 2))
        labels = components(W)[1] if self.centring == 'component' else node_slice
        count = np.bincount(labels).astype(np.float64)
        mean = np.column_stack([np.bincount(labels, weights=xy[:, c]) / count
                                for c in range(2)])
        return xy - mean[labels]

    def _assign(self, a: _Analysis, n_bands: int, with_response: bool = False
                ) -> PointFrequencies:
        t = time.perf_counter()
        n_nodes = a.L.shape[0]
        nu_s = np.zeros(n_nodes)
        band_s = np.ones(n_nodes, dtype=np.int16)
        resp_s = np.zeros((n_nodes, n_bands)) if self.method == 'signal' else None
        signal_rows = np.ones(n_nodes, dtype=bool)
        if a.terms is not None:
            resp_s = np.zeros((n_nodes, n_bands)) if resp_s is None else resp_s
            resp_s[a.terms_rows] = band_responses_from_terms(a.terms, n_bands)
        for s in a.exact_slices:
            lo, hi = int(a.starts[s]), int(a.starts[s + 1])
            lam, U = fourier_basis(a.L.block(lo, hi))
            if self.method == 'dominant':
                nu_s[lo:hi] = dominant_frequency(lam, U, a.lmax[s])
                band_s[lo:hi] = band_of_nu(nu_s[lo:hi], n_bands)
                signal_rows[lo:hi] = False
            else:
                resp_s[lo:hi] = band_responses_exact(lam, U, a.X[lo:hi], a.lmax[s], n_bands)
        if resp_s is not None:
            resp_s[a.isolated_nodes] = 0.0
            weights = resp_s
            if self.band_assignment == 'relative':
                weights = resp_s / self._slice_band_means(resp_s, a)
            nu_s[signal_rows], band_s[signal_rows] = signal_frequency(weights[signal_rows])
            if self.method == 'dominant':
                resp_s = None
        # Isolated nodes have no spectrum.
        nu_s[a.isolated_nodes] = np.nan
        band_s[a.isolated_nodes] = 0

        N = a.n_points
        order, node = a.sl.order, a.node_of_point
        nu = np.full(N, np.nan, dtype=np.float32)
        band = np.zeros(N, dtype=np.int16)
        isolated = np.zeros(N, dtype=bool)
        nu[order] = nu_s[node]
        band[order] = band_s[node]
        isolated[order] = a.isolated_nodes[node]
        response = None
        if resp_s is not None and with_response:
            response = np.zeros((N, n_bands), dtype=np.float32)
            response[order] = resp_s[node]
        timings = dict(a.timings_s)
        timings['assign'] = time.perf_counter() - t
        return PointFrequencies(nu=nu, band=band, n_bands=n_bands, isolated=isolated,
                                in_range=a.sl.in_range.copy(), finite=a.finite,
                                n_slices=a.sl.n_slices, response=response, timings_s=timings)

    @staticmethod
    def _slice_band_means(resp: np.ndarray, a: _Analysis) -> np.ndarray:
        """(n, B) mean response of each band over the non-isolated nodes of each node's slice;
        bands with no energy in a slice get 1 (their zero responses stay zero)."""
        if resp.shape[0] == 0:
            return np.ones_like(resp)
        sizes = np.diff(a.starts)
        nonempty = sizes > 0
        counts = np.add.reduceat((~a.isolated_nodes).astype(np.float64),
                                 a.starts[:-1][nonempty])
        sums = np.add.reduceat(resp, a.starts[:-1][nonempty], axis=0)
        means = sums / np.maximum(counts, 1.0)[:, None]
        means = np.where(means > 0.0, means, 1.0)
        return np.repeat(means, sizes[nonempty], axis=0)
