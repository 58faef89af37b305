r"""A graph low-pass filter of each point's range on the scan-line graph.

The paper filters a scan in the graph-frequency domain by dropping the points of some bands;
this filters the scan's *signal* instead: the range r of every point, as a function on the
scan-line graph, through the Tikhonov low-pass `h(lambda) = 1 / (1 + alpha lambda)`, i.e.
`r' = (I + alpha L)^-1 r`. Each point stays on its beam (x' = x r' / r), so only the range
noise along the beam is smoothed, never the beam's direction. The graph's weights fall with
the 3-D step between ring neighbours, so a depth jump (a trunk's edge, porous canopy) is
barely smoothed across, while a smooth run (ground, a trunk's face) is averaged over a few
neighbours. L is tridiagonal: the solve is one banded solve, O(n).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from gft_odom.core.spectral.graph import scan_line_graph


def range_lowpass(points_xyz: np.ndarray, ring: np.ndarray, alpha: float, tau_m: float,
                  sigma_m: float) -> np.ndarray:
    """The points with each range low-pass filtered on the scan-line graph (a new array).

    `alpha` is the filter's strength (0: the points as they are); `tau_m` and `sigma_m` the
    graph's edge cut and Gaussian width (graph.scan_line_graph). Non-finite points and points
    at the sensor's origin are returned as they are.
    """
    xyz = np.asarray(points_xyz, dtype=np.float64)
    out = xyz.copy()
    index = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    if alpha <= 0.0 or index.size < 2:
        return out
    coords = xyz[index]
    L, order = scan_line_graph(coords, np.asarray(ring)[index], tau_m, sigma_m)
    sorted_xyz = np.take(coords, order, axis=0)
    r = np.sqrt(np.einsum('ij,ij->i', sorted_xyz, sorted_xyz))
    off = -alpha * L.w_next
    banded = np.zeros((3, r.size))
    banded[0, 1:] = off
    banded[1] = 1.0 + alpha * L.degree
    banded[2, :-1] = off
    r_filtered = scipy.linalg.solve_banded((1, 1), banded, r, check_finite=False)
    scale = np.divide(r_filtered, r, out=np.ones_like(r), where=r > 0.0)
    out[index[order]] = sorted_xyz * scale[:, None]
    return out
