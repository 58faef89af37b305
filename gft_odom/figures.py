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
FREQUENCY_COLOURS = ('#08215e', '#1b4f9c', '#2a8fa8', '#55c49a', '#b6f08c')


def frequency_colormap():
    """The colour map of graph frequency nu: dark blue (low) to light green (high)."""
    from matplotlib.colors import LinearSegmentedColormap
    return LinearSegmentedColormap.from_list('gft_frequency', FREQUENCY_COLOURS)


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


def plot_trajectory(path: str | Path, estimate: Trajectory, reference: Trajectory | None,
                    metrics: dict | None = None, label: str = 'gft_odom') -> Path:
    """Top-down estimated path (aligned to the reference when there is one)."""
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


def plot_map(path: str | Path, points_world: np.ndarray, nu: np.ndarray | None,
             trajectory: Trajectory | None = None, max_points: int = 300_000) -> Path:
    """Merged map, top view, coloured by normalised graph frequency (grey when unfiltered)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 7))
    if len(points_world) > max_points:
        pick = np.random.default_rng(0).choice(len(points_world), max_points, replace=False)
        points_world = points_world[pick]
        nu = nu[pick] if nu is not None else None
    has_nu = nu is not None and nu.size and np.isfinite(nu).any()
    if has_nu:
        order = np.argsort(nu)  # high frequencies drawn last, on top
        sc = ax.scatter(points_world[order, 0], points_world[order, 1], c=nu[order], s=0.3,
                        cmap=frequency_colormap(), vmin=0.0, vmax=1.0, linewidths=0)
        fig.colorbar(sc, ax=ax, label='normalised graph frequency  \u03bd = \u03bb / \u03bb_max')
    else:
        ax.scatter(points_world[:, 0], points_world[:, 1], c='0.4', s=0.3, linewidths=0)
    if trajectory is not None and len(trajectory):
        ax.plot(*trajectory.positions_xyz[:, :2].T, color='tab:red', lw=1.5, label='odometry')
        ax.legend(loc='upper right')
    ax.set_title('merged map (top view)')
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal', adjustable='datalim')
    return save_figure(fig, path)
