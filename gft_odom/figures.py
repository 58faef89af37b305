"""Figures a paper would use: trajectory against ground truth, frequency-coloured map.

matplotlib is imported lazily with the Agg backend, so importing this module costs nothing and
works without a display.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gft_odom.core.trajectory import Trajectory
from gft_odom.io.atomic import write_atomic

# Paper Figure 3: low graph frequencies dark blue, high frequencies light green.
FREQUENCY_COLOURS = ('#081d58', '#253494', '#1d91c0', '#41b6c4', '#7fcdbb', '#c7e9b4',
                     '#edf8b1')
NO_SPECTRUM_COLOUR = '#d0d0d0'
# Map figures show the path plus this much around it: the far, sparse returns of a +-60 m
# sweep otherwise shrink the path to a speck.
PATH_MARGIN_M = 15.0


def frequency_colormap(n_colours: int = 256):
    """The colour map of graph frequency nu: dark blue (low) to light green (high)."""
    from matplotlib.colors import LinearSegmentedColormap
    return LinearSegmentedColormap.from_list('gft_frequency', FREQUENCY_COLOURS, N=n_colours)


def distinct_labels(values, min_decimals: int = 2, max_decimals: int = 6) -> list[str]:
    """Fewest decimals (>= min_decimals) at which neighbouring values read differently."""
    values = np.asarray(values, dtype=float)
    for decimals in range(min_decimals, max_decimals + 1):
        labels = [f'{v:.{decimals}f}' for v in values]
        if all(a != b for a, b in zip(labels, labels[1:])):
            return labels
    return [f'{v:.{max_decimals}g}' for v in values]


def quantile_norm(values: np.ndarray, n_steps: int = 10, cmap_colours=FREQUENCY_COLOURS):
    """(cmap, norm, edges): one colour per quantile step, so each colour holds an equal share
    of the values (nu and heights are far from uniform). edges None: too few distinct values,
    a linear scale over their range instead."""
    from matplotlib.colors import BoundaryNorm, LinearSegmentedColormap, Normalize

    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    if finite.size > n_steps:
        edges = np.unique(np.quantile(finite, np.linspace(0.0, 1.0, n_steps + 1)))
        if edges.size >= 3:
            cmap = LinearSegmentedColormap.from_list('quantiles', cmap_colours,
                                                     N=edges.size - 1)
            return cmap, BoundaryNorm(edges, cmap.N), edges
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    cmap = LinearSegmentedColormap.from_list('linear', cmap_colours)
    return cmap, Normalize(lo, hi if hi > lo else lo + 1.0), None


def label_quantile_colourbar(bar, edges, what: str = 'points') -> None:
    """Ticks at the quantile edges with distinct labels; say the steps are quantiles."""
    if edges is None:
        return
    bar.set_ticks(edges)
    bar.set_ticklabels(distinct_labels(edges))
    steps = edges.size - 1
    name = 'deciles' if steps == 10 else f'{steps} quantile steps'
    bar.ax.set_title(f'{name}\n(equal share\nof {what})', fontsize=7)


def path_window(path_xy: np.ndarray, margin_m: float = PATH_MARGIN_M):
    """(lo, hi) corners of the path's bounding box grown by `margin_m`."""
    path_xy = np.asarray(path_xy, dtype=float).reshape(-1, 2)
    return path_xy.min(axis=0) - margin_m, path_xy.max(axis=0) + margin_m


def pyplot():
    """matplotlib.pyplot with the Agg backend (no display needed), imported on first use."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def save_figure(fig, path: str | Path, dpi: int = 150) -> Path:
    """Save atomically (temp file then rename) and close the figure."""
    path = Path(path)
    try:
        write_atomic(path, lambda f: fig.savefig(f, dpi=dpi, format=path.suffix.lstrip('.')
                                                 or 'png', bbox_inches='tight'))
    finally:
        pyplot().close(fig)
    return path


def aligned_positions(estimate: Trajectory, reference: Trajectory) -> np.ndarray:
    """Estimated positions in the reference frame (rigid alignment on matched positions)."""
    from gft_odom.core.metrics import ate
    result = ate(estimate, reference, mode='position')
    T = result.T_ref_est
    return estimate.positions_xyz @ T[:3, :3].T + T[:3, 3]


def run_label(metrics: dict | None) -> str:
    """'paper ICP + GFT filter (B=4 [3, 4])' / 'default ICP, filter off' from a run's metrics."""
    if not metrics or 'registration_mode' not in metrics:
        return 'estimate'
    mode = f'{metrics["registration_mode"]} ICP'
    n_bands, mask = metrics.get('n_bands'), list(metrics.get('band_mask') or [])
    if not metrics.get('use_spectral_filter', True):
        return f'{mode}, filter off'
    if n_bands is not None and mask == list(range(1, int(n_bands) + 1)):
        return f'{mode}, all-pass mask (B={n_bands})'
    return f'{mode} + GFT filter (B={n_bands} {mask})'


def plot_trajectory(path: str | Path, estimate: Trajectory, reference: Trajectory | None,
                    metrics: dict | None = None, label: str | None = None) -> Path:
    """Top-down estimated path (aligned to the reference when there is one); the legend names
    the run (registration mode and band mask, from `metrics`) unless `label` is given."""
    label = run_label(metrics) if label is None else label
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 6))
    if reference is not None and len(reference):
        ax.plot(*reference.positions_xyz[:, :2].T, color='0.3', lw=2.0, label='ground truth')
        xy = aligned_positions(estimate, reference)[:, :2]
    else:
        xy = estimate.positions_xyz[:, :2]
    ax.plot(*xy.T, color='tab:red', lw=1.4, label=label)
    ax.plot(*xy[0], 'o', color='tab:red', ms=5)
    title = 'trajectory (top view)'
    if metrics and metrics.get('ate_rmse_m') is not None:
        title += f'\nATE RMSE {metrics["ate_rmse_m"]:.2f} m'
        if metrics.get('rpe_drift_pct') is not None:
            title += f', RPE drift {metrics["rpe_drift_pct"]:.2f} %'
    ax.set_title(title)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(alpha=0.3)
    ax.legend(loc='best')
    return save_figure(fig, path)


def plot_trajectories(path: str | Path, reference: Trajectory,
                      estimates: list[tuple[str, Trajectory]], title: str = '',
                      margin_m: float = 3.0, error_floor_m: float = 1e-3,
                      match: str = 'auto') -> Path:
    """Several estimates against one reference: the top view, each estimate rigidly aligned on
    positions as the ATE aligns it (`match` as `evaluation.match`), and beside it each one's
    position error along the
    reference's path (log scale: centimetres and metres share the axis). The view is the
    reference plus a margin (a lost run must not shrink the others; its legend entry says it
    leaves the view); the first estimate is drawn on top."""
    from gft_odom.core.metrics import ate

    plt = pyplot()
    fig, (ax, ax_err) = plt.subplots(1, 2, figsize=(13, 5.5),
                                     gridspec_kw={'width_ratios': [1.1, 1.0]})
    ref_xy = reference.positions_xyz[:, :2]
    lo, hi = path_window(ref_xy, max(margin_m, 0.1 * float(np.ptp(ref_xy, axis=0).max())))
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(
        np.diff(reference.positions_xyz, axis=0), axis=1))])
    ax.plot(*ref_xy.T, 'k--', lw=1.2, label='ground truth (GPS antenna)', zorder=10)
    colours = ('tab:red', 'tab:blue', 'tab:green', 'tab:orange', 'tab:purple', 'tab:brown')
    for k, (label, estimate) in enumerate(estimates):
        result = ate(estimate, reference, mode='position', match=match)
        T = result.T_ref_est
        xy = (estimate.positions_xyz @ T[:3, :3].T + T[:3, 3])[:, :2]
        colour, width, z = colours[k % len(colours)], 2.0 if k == 0 else 1.2, 9 - k
        # Distance along the reference at each matched estimate stamp.
        at = np.interp(estimate.stamps_ns[result.est_idx].astype(float),
                       reference.stamps_ns.astype(float), travelled)
        ax_err.plot(at, np.maximum(result.errors_m, error_floor_m), color=colour, lw=width,
                    label=f'{label}: mean {result.mean_m:.2f} m', zorder=z)
        if not ((xy >= lo) & (xy <= hi)).all():
            label += ' (leaves the view)'
        ax.plot(*xy.T, color=colour, lw=width, label=label, zorder=z)
    ax.plot(*ref_xy[0], 'ko', ms=5)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_title('top view, aligned on positions')
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal', adjustable='box')
    ax.grid(alpha=0.3)
    ax.legend(loc='best', fontsize=8)
    ax_err.set_yscale('log')
    ax_err.set_title('position error after the alignment')
    ax_err.set_xlabel('distance along the ground truth [m]')
    ax_err.set_ylabel('position error [m] (log)')
    ax_err.grid(alpha=0.3, which='both')
    ax_err.legend(loc='upper center', bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_map(path: str | Path, points_world: np.ndarray, nu: np.ndarray | None,
             trajectory: Trajectory | None = None, max_points: int = 300_000,
             margin_m: float = PATH_MARGIN_M) -> Path:
    """Merged map, top view, around the path, coloured by graph frequency on a quantile scale
    (grey, and said so, when no spectrum was computed)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 7))
    points_world = np.asarray(points_world).reshape(-1, 3)
    nu = None if nu is None else np.asarray(nu)
    if trajectory is not None and len(trajectory):
        lo, hi = path_window(trajectory.positions_xyz[:, :2], margin_m)
        inside = ((points_world[:, :2] >= lo) & (points_world[:, :2] <= hi)).all(axis=1)
        points_world = points_world[inside]
        nu = nu[inside] if nu is not None else None
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    if len(points_world) > max_points:
        pick = np.random.default_rng(0).choice(len(points_world), max_points, replace=False)
        points_world = points_world[pick]
        nu = nu[pick] if nu is not None else None
    has = np.isfinite(nu) if nu is not None else np.zeros(len(points_world), dtype=bool)
    if has.any():
        cmap, norm, edges = quantile_norm(nu[has])
        if not has.all():
            ax.scatter(points_world[~has, 0], points_world[~has, 1], c=NO_SPECTRUM_COLOUR,
                       s=0.3, linewidths=0, rasterized=True)
            ax.plot([], [], 's', color=NO_SPECTRUM_COLOUR, label='no spectrum (isolated, '
                    'outside the z range)')
        # Low frequencies (trunks, frames) last, on top of the canopy.
        order = np.flatnonzero(has)[np.argsort(-nu[has], kind='stable')]
        sc = ax.scatter(points_world[order, 0], points_world[order, 1], c=nu[order], s=0.3,
                        cmap=cmap, norm=norm, linewidths=0, rasterized=True)
        bar = fig.colorbar(sc, ax=ax, label='graph frequency  \u03bd = \u03bb / \u03bb_max')
        label_quantile_colourbar(bar, edges)
        title = 'merged map of the points registration used, by graph frequency'
    else:
        ax.scatter(points_world[:, 0], points_world[:, 1], c='0.4', s=0.3, linewidths=0,
                   rasterized=True)
        title = 'merged map (top view)'
        ax.text(0.02, 0.02, 'no graph frequencies: the spectrum was not computed\n'
                '(filter off, or an all-pass mask)', transform=ax.transAxes, fontsize=9,
                va='bottom', ha='left', bbox={'facecolor': 'white', 'alpha': 0.8,
                                              'edgecolor': '0.6'})
    if trajectory is not None and len(trajectory):
        ax.plot(*trajectory.positions_xyz[:, :2].T, color='tab:red', lw=1.5, label='odometry')
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc='upper right', fontsize=8)
    ax.set_title(title)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal', adjustable='box')
    return save_figure(fig, path)
