"""`gft-odom spectrum`: the graph-frequency colour map of a merged cloud (the paper's Figure 3).

Each of the first N scans gets its per-point frequency nu in its own sensor frame (exactly what
the filter sees online), is moved into the world frame with the ground-truth sensor pose at its
stamp, and the merged cloud is drawn top-down and from the side, low frequencies dark blue,
high light green; points with no spectrum (isolated, outside the z range) in light grey.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from gft_odom.core.trajectory import Trajectory
from gft_odom.figures import NO_SPECTRUM_COLOUR, pyplot
from gft_odom.tools.args import add_bags, add_config

log = logging.getLogger(__name__)

MAX_PLOT_POINTS = 1_500_000
# A scan whose stamp is further than this outside the ground truth's time span is an error.
MAX_EXTRAPOLATION_S = 0.1


HELP = 'colour a merged cloud by graph frequency (PNG)'
DESCRIPTION = ('Merge the first N scans of a bag into the world frame with ground-truth '
               "sensor poses and write a PNG coloured by each point's graph frequency "
               'nu (top-down and side view).')


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `gft-odom spectrum`."""
    add_bags(p, nargs='*')
    p.add_argument('--pcd', metavar='DIR',
                   help='instead of bags: a folder written by `gft-odom frequencies` (the '
                        'frequencies are read, not computed)')
    p.add_argument('--gt', required=True,
                   help='ground-truth SENSOR poses: TUM file (e.g. ground_truth/'
                        'gt_sensor_tum.txt from `gft-odom simulate`), gt.csv or gt.bag')
    p.add_argument('--out', required=True, help='output PNG path')
    p.add_argument('--scans', type=int, default=50, help='number of scans to merge (50)')
    p.add_argument('--every', type=int, default=1, help='use every k-th scan (1)')
    add_config(p, help='ROS params file (spectral section used)')
    p.add_argument('--radius-m', type=float, default=30.0,
                   help='draw points within this distance (x, y) of the sensor path (30)')
    p.add_argument('--colour-scale', choices=('quantile', 'linear'), default='quantile',
                   help='quantile: each colour holds an equal share of the points (nu is '
                        'far from uniform); linear: nu 0..1 (default quantile)')
    p.add_argument('--title', help='figure title')


def scan_frequencies(scans, spectral_filter):
    """(stamp_ns, points_xyz, nu) of every scan, nu computed by the filter."""
    for scan in scans:
        freqs = spectral_filter.scan_frequencies(scan)
        yield scan.stamp_ns, scan.points_xyz, freqs.nu


def pcd_frequencies(pcd_dir: str | Path):
    """(stamp_ns, points_xyz, nu) of every `<stamp ns>.pcd` of `gft-odom frequencies`."""
    from gft_odom.errors import BagError
    from gft_odom.io.pcd import read_pcd

    files = sorted((p for p in Path(pcd_dir).glob('*.pcd') if p.stem.isdigit()),
                   key=lambda p: int(p.stem))
    if not files:
        raise BagError(f'no <stamp ns>.pcd files in {pcd_dir}')
    for path in files:
        cloud = read_pcd(path)
        if 'frequency' not in cloud.dtype.names:
            raise BagError(f'{path} has no frequency field (fields: {cloud.dtype.names})')
        xyz = np.stack([cloud['x'], cloud['y'], cloud['z']], axis=1).astype(np.float64)
        yield int(path.stem), xyz, cloud['frequency']


def merge_frequencies(frames, traj, max_scans: int, every: int = 1):
    """World points (M, 3), their nu (M,) (NaN: no spectrum), and the sensor positions, from
    (stamp_ns, points_xyz, nu) frames in the sensor frame."""
    from gft_odom.core.geometry import transform_points

    order = np.argsort(traj.stamps_ns, kind='stable')
    traj = Trajectory(traj.stamps_ns[order], traj.poses[order])
    points, nus, positions = [], [], []
    for index, (stamp_ns, xyz, nu) in enumerate(frames):
        if len(positions) >= max_scans:
            break
        if index % every:
            continue
        T = traj.pose_at(stamp_ns, MAX_EXTRAPOLATION_S)
        ok = np.isfinite(xyz).all(axis=1)
        points.append(transform_points(T, xyz[ok]))
        nus.append(nu[ok])
        positions.append(T[:3, 3])
    if not positions:
        return np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros((0, 3))
    return np.concatenate(points), np.concatenate(nus), np.array(positions)


def near_path(points: np.ndarray, positions: np.ndarray, radius_m: float) -> np.ndarray:
    """(M,) bool: points within `radius_m` (x, y) of some sensor position."""
    from scipy.spatial import cKDTree

    if positions.shape[0] == 0 or points.shape[0] == 0:
        return np.zeros(points.shape[0], dtype=bool)
    dist, _ = cKDTree(positions[:, :2]).query(points[:, :2], distance_upper_bound=radius_m)
    return np.isfinite(dist)


def draw(points: np.ndarray, nu: np.ndarray, positions: np.ndarray, out: Path,
         title: str, colour_scale: str = 'quantile') -> None:
    """Top-down and side view, coloured by nu, written to `out` as PNG."""
    from matplotlib.colors import Normalize

    from gft_odom.figures import frequency_colormap, label_quantile_colourbar, quantile_norm

    plt = pyplot()
    if points.shape[0] > MAX_PLOT_POINTS:
        keep = np.random.default_rng(0).choice(points.shape[0], MAX_PLOT_POINTS, replace=False)
        points, nu = points[keep], nu[keep]
    has = np.isfinite(nu)
    norm, cmap, edges = Normalize(0.0, 1.0), frequency_colormap(), None
    if colour_scale == 'quantile':
        cmap, norm, edges = quantile_norm(nu[has])
        if edges is None:
            norm = Normalize(0.0, 1.0)
    # Draw low frequencies last so the sparse trunk/frame structure is not buried under canopy.
    order = np.flatnonzero(has)[np.argsort(-nu[has], kind='stable')]
    extent = np.ptp(points[:, :2], axis=0) if points.size else np.ones(2)
    width = 14.0
    height = float(np.clip(width * extent[1] / max(extent[0], 1e-6), 3.0, 10.0)) + 3.5
    fig, (ax_top, ax_side) = plt.subplots(
        2, 1, figsize=(width, height), gridspec_kw={'height_ratios': [3, 1]},
        constrained_layout=True)
    scatter = None
    for ax, (i, j), label in ((ax_top, (0, 1), 'y [m]'), (ax_side, (0, 2), 'z [m]')):
        ax.scatter(points[~has, i], points[~has, j], s=0.2, c=NO_SPECTRUM_COLOUR,
                   linewidths=0, rasterized=True)
        scatter = ax.scatter(points[order, i], points[order, j], s=0.3, c=nu[order], cmap=cmap,
                             norm=norm, linewidths=0, rasterized=True)
        ax.set_xlabel('x [m]')
        ax.set_ylabel(label)
        ax.set_aspect('equal')
        ax.set_facecolor('white')
    if positions.size:
        ax_top.plot(positions[:, 0], positions[:, 1], '-', color='#e34a33', lw=1.2,
                    label='sensor path (ground truth)')
        ax_top.legend(loc='upper right', fontsize=8)
    ax_top.set_title(title)
    ax_side.set_title('side view')
    bar = fig.colorbar(scatter, ax=[ax_top, ax_side], shrink=0.6,
                       label='graph frequency nu = lambda / lambda_max')
    label_quantile_colourbar(bar, edges)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=150)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    """Merge the scans and draw their frequencies."""
    from gft_odom.core.spectral import SpectralFilter
    from gft_odom.io.bags import ScanBagReader
    from gft_odom.io.ground_truth import read_ground_truth
    from gft_odom.params_file import load_config

    if args.scans < 1 or args.every < 1:
        from gft_odom.errors import ConfigError
        raise ConfigError(f'--scans and --every must be >= 1, got {args.scans}, {args.every}')
    from gft_odom.errors import BagError

    if bool(args.bags) == bool(args.pcd):
        from gft_odom.errors import ConfigError
        raise ConfigError('give either BAG... or --pcd DIR')
    config = load_config(args.config, args.overrides)
    spectral_filter = SpectralFilter.from_config(config.spectral)
    traj = read_ground_truth(args.gt)
    if args.pcd:
        points, nu, positions = merge_frequencies(pcd_frequencies(args.pcd), traj, args.scans,
                                                  args.every)
        source = f'read from {args.pcd}'
    else:
        with ScanBagReader(args.bags, args.topic) as reader:
            points, nu, positions = merge_frequencies(
                scan_frequencies(reader, spectral_filter), traj, args.scans, args.every)
        if positions.shape[0] == 0:
            raise BagError(f'no scans on {args.topic} in {", ".join(map(str, args.bags))}')
        s = config.spectral
        source = (f'h={s.slice_thickness_m} m, tau={s.tau_m} m, sigma={s.sigma_m} m, '
                  f'{s.method}, {s.solver}')
    title = args.title or (f'graph frequency of {positions.shape[0]} merged scans '
                           f'({points.shape[0]} points); {source}')
    s = config.spectral
    near = near_path(points, positions, args.radius_m)
    out = Path(args.out)
    draw(points[near], nu[near], positions, out, title, args.colour_scale)
    has = np.isfinite(nu)
    counts = np.histogram(nu[has], bins=s.n_bands, range=(0.0, 1.0))[0]
    print(f'{positions.shape[0]} scans, {points.shape[0]} points, '
          f'{100.0 * (1.0 - has.mean()):.1f} % without spectrum')
    print('points per nu band: ' + ' '.join(
        f'{b + 1}:{100.0 * c / max(has.sum(), 1):.1f}%' for b, c in enumerate(counts)))
    print(f'wrote {out}')
    return 0
