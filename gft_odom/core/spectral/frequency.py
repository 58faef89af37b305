r"""Per-point frequency definitions: one class each, every one a function of the graph Laplacian.

A definition turns a scan's graph (`SpectralGraph`: L = D - W, lambda_max of each block, and
for some definitions the position signal X) into a normalised frequency nu in [0, 1] and a
band 1..B for every graph node. `prepare` does the work that does not depend on the band count
(the band search asks for B = 2..10 from one preparation), `assign` the rest. A new definition
is one subclass with a `name`, registered with `@register`, and one test.

The definitions (DESIGN section 2; measured in benchmarks/bench_frequency_classes.py):
- `ldos_mean`: the mean of the vertex's local spectral density
  rho_m(lambda) = sum_l v_l(m)^2 delta(lambda - lambda_l), normalised:
  nu_m = sum_l nu_l v_l(m)^2 = L_mm / lambda_max, the weighted degree over lambda_max. Exact,
  1-hop local, no eigen-decomposition.
- `signal` (the paper's mode): band responses r_mb = |(h_b(L) X)_m|^2 of the centred position
  signal X (Chebyshev or, for blocks of at most EXACT_MAX_BLOCK_NODES with solver 'exact', by
  eigh); band = argmax. Degenerate on orchard scans: a position signal is smooth, so most
  points land in band 1.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from gft_odom.core.spectral.bands import band_of_nu
from gft_odom.core.spectral.chebyshev import band_responses_from_terms, chebyshev_terms
from gft_odom.core.spectral.gft import band_responses_exact, fourier_basis, signal_frequency
from gft_odom.core.spectral.graph import GraphLaplacian
from gft_odom.core.spectral.slicing import Slices
from gft_odom.errors import SpectralError

log = logging.getLogger(__name__)


@dataclass
class SpectralGraph:
    """One scan's graph and everything about it that does not depend on the band count.

    Graph nodes are sorted into blocks (one per slice for the slice graph, one for the whole
    scan for the scan-line graph); `starts` are the block boundaries over the nodes.
    """

    n_points: int
    sl: Slices  # which input points have a node, in node order (`order`)
    node_of_point: np.ndarray  # graph node of every point of `sl.order`
    starts: np.ndarray
    node_block: np.ndarray  # (n_nodes,) block of every node
    L: GraphLaplacian
    isolated_nodes: np.ndarray
    lmax: np.ndarray  # (n_blocks,) lambda_max of every block
    finite: np.ndarray  # (n_points,) finite coordinates
    X: np.ndarray | None = None  # centred position signal (n_nodes, c), when a definition needs it
    prepared: dict = field(default_factory=dict)  # a definition's band-count-free results
    timings_s: dict = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        """Number of graph nodes."""
        return int(self.L.shape[0])

    def node_lmax(self) -> np.ndarray:
        """lambda_max of each node's block, (n_nodes,)."""
        return self.lmax[self.node_block] if self.lmax.size else np.zeros(0)


@dataclass(frozen=True)
class NodeFrequencies:
    """nu (n_nodes,) in [0, 1], band (n_nodes,) 1..B, optional band responses (n_nodes, B)."""

    nu: np.ndarray
    band: np.ndarray
    response: np.ndarray | None = None


class FrequencyDefinition:
    """Graph -> per-node frequency. Subclasses set `name` and implement `assign`."""

    name: ClassVar[str] = ''
    # True when the definition needs the centred position signal X (built with the graph).
    needs_position_signal: ClassVar[bool] = False

    def __init__(self, config) -> None:
        """`config`: the `SpectralConfig` (order, solver) the definition reads."""
        self.config = config

    def prepare(self, graph: SpectralGraph) -> None:
        """Band-count-free work, stored in `graph.prepared` (default: none)."""

    def assign(self, graph: SpectralGraph, n_bands: int) -> NodeFrequencies:
        """nu and band of every node for `n_bands` equal bands."""
        raise NotImplementedError


REGISTRY: dict[str, type[FrequencyDefinition]] = {}


def register(cls: type[FrequencyDefinition]) -> type[FrequencyDefinition]:
    """Class decorator: make a definition selectable as `spectral.method: <name>`."""
    if not cls.name or cls.name in REGISTRY:
        raise SpectralError(f'frequency definition name {cls.name!r} is empty or taken')
    REGISTRY[cls.name] = cls
    return cls


def make_definition(config) -> FrequencyDefinition:
    """The definition named by `config.method`."""
    try:
        return REGISTRY[config.method](config)
    except KeyError:
        raise SpectralError(f'unknown frequency definition {config.method!r} '
                            f'(one of {sorted(REGISTRY)})') from None


def _ldos_mean(L: GraphLaplacian, lmax_per_node: np.ndarray) -> np.ndarray:
    """sum_l nu_l v_l(m)^2 = L_mm / lambda_max (0 where the block has no edge)."""
    degree = np.asarray(L.degree, dtype=np.float64)
    return np.where(lmax_per_node > 0.0,
                    degree / np.where(lmax_per_node > 0.0, lmax_per_node, 1.0), 0.0)


@register
class LdosMean(FrequencyDefinition):
    """nu = mean of the vertex's local spectral density = weighted degree / lambda_max."""

    name = 'ldos_mean'

    def assign(self, graph: SpectralGraph, n_bands: int) -> NodeFrequencies:
        """Band of the exact LDOS mean."""
        nu = np.clip(_ldos_mean(graph.L, graph.node_lmax()), 0.0, 1.0)
        return NodeFrequencies(nu, band_of_nu(nu, n_bands))


# The exact path (dense eigh, O(n^3) time, O(n^2) memory) takes blocks up to this many graph
# nodes, Chebyshev the larger: 1000 nodes is ~0.3 s a slice; a whole VLP-16 scan at 2000 took
# ~45 s on the 2-core test machine.
EXACT_MAX_BLOCK_NODES = 1000


def _exact_blocks(graph: SpectralGraph, config) -> tuple[list[int], np.ndarray]:
    """(blocks the exact path handles: solver 'exact' and small enough, the other non-empty
    blocks as a mask)."""
    sizes = np.diff(graph.starts)
    exact = ([s for s in range(len(sizes)) if sizes[s] <= EXACT_MAX_BLOCK_NODES]
             if config.solver == 'exact' else [])
    cheb = np.ones(len(sizes), dtype=bool)
    cheb[exact] = False
    return exact, cheb & (sizes > 0)


@register
class SignalFrequency(FrequencyDefinition):
    """Band of the largest response of the centred position signal (DESIGN 2, `signal`)."""

    name = 'signal'
    needs_position_signal = True

    def prepare(self, graph: SpectralGraph) -> None:
        """Chebyshev terms T_k(M) X for the blocks the exact path does not take."""
        exact, cheb = _exact_blocks(graph, self.config)
        graph.prepared['exact_blocks'] = exact
        graph.prepared['terms'] = graph.prepared['terms_rows'] = None
        if not np.any(cheb):
            return
        if self.config.solver == 'exact':
            log.debug('%d blocks exceed %d nodes; their points use the Chebyshev `signal` '
                      'frequency', int(cheb.sum()), EXACT_MAX_BLOCK_NODES)
        rows = np.flatnonzero(cheb[graph.node_block])
        lmax = graph.node_lmax()
        scale = np.where(lmax > 0.0, 2.0 / np.where(lmax > 0.0, lmax, 1.0), 0.0)
        L_sub = graph.L if rows.size == graph.n_nodes else GraphLaplacian(
            graph.L.W[rows][:, rows])
        graph.prepared['terms'] = chebyshev_terms(L_sub, scale[rows], graph.X[rows],
                                                  self.config.chebyshev_order)
        graph.prepared['terms_rows'] = rows

    def responses(self, graph: SpectralGraph, n_bands: int) -> np.ndarray:
        """(n_nodes, B) band responses, exact blocks by eigh, the rest from the terms."""
        resp = np.zeros((graph.n_nodes, n_bands))
        if graph.prepared['terms'] is not None:
            resp[graph.prepared['terms_rows']] = band_responses_from_terms(
                graph.prepared['terms'], n_bands)
        for s in graph.prepared['exact_blocks']:
            lo, hi = int(graph.starts[s]), int(graph.starts[s + 1])
            lam, U = fourier_basis(graph.L.block(lo, hi))
            resp[lo:hi] = band_responses_exact(lam, U, graph.X[lo:hi], graph.lmax[s], n_bands)
        resp[graph.isolated_nodes] = 0.0
        return resp

    def assign(self, graph: SpectralGraph, n_bands: int) -> NodeFrequencies:
        """argmax of the responses; nu their weighted centre."""
        resp = self.responses(graph, n_bands)
        nu, band = signal_frequency(resp)
        return NodeFrequencies(nu, band, resp)
