"""Run the simulator and write a CitrusFarm-like dataset: bag, ground truth, top-down picture.

Layout under `out_dir`:
  base_<scenario>_<seed>.bag (ROS 1) or base_<scenario>_<seed>/ (rosbag2 folder) with
      /velodyne_points (sensor_msgs/PointCloud2, velodyne driver fields, frame `velodyne`) and
      /gps/fix/odometry (nav_msgs/Odometry: GPS antenna position at ~10 Hz; the orientation is
      the true one but, as in CitrusFarm, not meant to be used);
  ground_truth/gt.csv            the same antenna track (time x y z qx qy qz qw, seconds);
  ground_truth/gt_sensor_tum.txt T_world_velodyne at every scan stamp (what odometry estimates);
  topdown.png                    merged scans seen from above with the ground-truth path.
The world frame is the orchard frame (rows at a seed-dependent heading), so the first sensor
pose is not the identity.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from gft_odom.core.constants import NS_PER_S, ns_to_sec_nanosec
from gft_odom.core.geometry import transform_points
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import SimulationError
from gft_odom.io.atomic import write_text_atomic
from gft_odom.sim.motion import ROUTES, SCENARIOS
from gft_odom.sim.simulator import ScanSimulator, SimConfig
from gft_odom.sim.variation import OrchardVariation

log = logging.getLogger(__name__)

LIDAR_TOPIC = '/velodyne_points'
GPS_TOPIC = '/gps/fix/odometry'
# The drive's metadata: a file beside the bag, a custom_data key / a ROS 1 topic inside it.
METADATA_FILE = 'sim_metadata.json'
METADATA_KEY = 'gft_odom.sim'
METADATA_TOPIC = '/gft_odom/sim_metadata'
# GPS fixes are not synchronised with the LiDAR: they start this long after the first sweep.
GPS_PHASE_S = 0.037
# Points kept for the picture (a stride over each scan keeps memory bounded on long runs).
TOPDOWN_MAX_POINTS = 3_000_000
# topdown.png shows the path plus this much around it.
TOPDOWN_MARGIN_M = 15.0
# Pixels whose highest point is below this height are ground (one colour in topdown.png).
TOPDOWN_GROUND_M = 0.2


@dataclass
class SimulationResult:
    """Where a simulated run went and what it cost."""

    out_dir: Path
    bag_path: Path
    gt_csv_path: Path
    gt_tum_path: Path
    topdown_png_path: Path | None
    n_scans: int
    seconds_per_scan: list[float] = field(default_factory=list)
    points_per_scan: list[int] = field(default_factory=list)

    @property
    def median_seconds_per_scan(self) -> float:
        """Median wall time to simulate one sweep (0 when none)."""
        return float(np.median(self.seconds_per_scan)) if self.seconds_per_scan else 0.0


def bag_path_for(out_dir: Path, scenario: str, seed: int, fmt: str) -> Path:
    """CitrusFarm-like bag name: base_<scenario>_<seed>.bag (ROS 1) or a folder (rosbag2)."""
    name = f'base_{scenario}_{seed}'
    return Path(out_dir) / (name + '.bag' if fmt == 'ros1' else name)


def simulate_to_bag(out_dir: str | Path, scenario: str = 'row', n_scans: int | None = 100,
                    seed: int = 0, config: SimConfig | None = None, fmt: str = 'ros2',
                    storage: str = 'sqlite3', topdown_png: bool = True,
                    progress: Callable[[int], None] | None = None,
                    distance_m: float = 300.0, vary: bool = False,
                    family: str = 'varied', day: int = 0, map_route: str | None = None,
                    canopy: str = 'changed', map_distance_m: float | None = None
                    ) -> SimulationResult:
    """Simulate `n_scans` sweeps of `scenario` in the orchard of `seed`; write the dataset.

    Routes (lawnmower, every_other_row, spiral, out_and_back, edge_lawnmower) drive about
    `distance_m`; `n_scans=None` simulates the whole route. `vary` draws the orchard, terrain,
    driving, mount and wind from the seed; the draws go into `sim_metadata.json` beside the
    bag and into the bag (rosbag2 custom_data, a ROS 1 bag a std_msgs/String on
    `METADATA_TOPIC`); `family` 'stress' draws them outside the varied ranges. `progress(k)`
    is called after each scan with the number of scans done. `day` >= 1 (with `vary`): a later
    day in the block `map_route` drove on day 0 over `map_distance_m` (sim/later_day.py), its
    canopy `canopy`, its ground truth in the same frame as day 0's.
    Nothing already written is overwritten: an existing bag raises SimulationError.
    """
    from gft_odom.io.bags import BagWriter
    from gft_odom.io.pointcloud2 import VELODYNE_XYZIR_ROS1, VELODYNE_XYZIRT, encode_scan
    from gft_odom.io.tum import write_tum

    config = config or SimConfig()
    config.validate()
    if scenario not in SCENARIOS + ROUTES:
        raise SimulationError(f'unknown scenario {scenario!r}; choose one of '
                              f'{SCENARIOS + ROUTES}')
    if fmt not in ('ros1', 'ros2'):
        raise SimulationError(f'bag format must be ros1 or ros2, got {fmt!r}')
    if n_scans is None and scenario not in ROUTES:
        raise SimulationError(f'scenario {scenario!r} needs a number of scans')
    if n_scans is not None and int(n_scans) < 1:
        raise SimulationError(f'n_scans must be >= 1, got {n_scans}')
    if not distance_m > 0.0:
        raise SimulationError(f'distance_m must be > 0, got {distance_m}')
    out_dir = Path(out_dir)
    bag_path = bag_path_for(out_dir, scenario, seed, fmt)
    if bag_path.exists():
        raise SimulationError(f'{bag_path} exists already; remove it or choose another --out')
    gt_dir = out_dir / 'ground_truth'
    gt_dir.mkdir(parents=True, exist_ok=True)

    canopy_change = None
    if int(day) > 0:
        if not vary or family != 'varied':
            raise SimulationError('a later day is of a varied block: give --vary (not --stress)')
        from gft_odom.sim.later_day import simulate_day
        sim, canopy_change = simulate_day(config, seed, map_route or scenario, int(day),
                                          scenario, canopy, map_distance_m or distance_m,
                                          distance_m)
        variation = None
    else:
        sim, variation = ScanSimulator.for_drive(config, scenario, seed, n_scans, distance_m,
                                                 vary, family)
    config = sim.config
    period_s = 1.0 / config.scan_rate_hz
    if n_scans is None:  # the whole route
        n_scans = sim.n_scans_in_drive
    elif scenario in ROUTES:  # a route ends where it ends
        n_scans = min(int(n_scans), sim.n_scans_in_drive)
    else:
        n_scans = int(n_scans)
    orchard = sim.orchard
    metadata = drive_metadata(sim, scenario, seed, n_scans, variation)
    if canopy_change is not None:
        metadata['later_day'] = {'day': int(day), 'map_route': map_route or scenario,
                                 'map_distance_m': map_distance_m or distance_m,
                                 'canopy': asdict(canopy_change)}
    layout = VELODYNE_XYZIR_ROS1 if config.legacy_fields else VELODYNE_XYZIRT
    log.info('simulating %d scans of %r in orchard seed %d (%d rows, %.0f m long, rows %.1f m '
             'apart, trees %.1f m apart) -> %s', n_scans, scenario, seed, len(orchard.row_v_m),
             orchard.row_end_u_m - orchard.row_start_u_m, orchard.row_spacing_m,
             orchard.tree_spacing_m, bag_path)

    # GPS antenna track at its own rate, not aligned with the sweeps.
    gps_t = GPS_PHASE_S + np.arange(0.0, n_scans * period_s, 1.0 / config.gps_rate_hz)
    T_world_gps = sim.sensor_poses(gps_t) @ sim.T_sensor_gps
    gps_stamps = sim.start_ns + np.round(gps_t * NS_PER_S).astype(np.int64)

    result = SimulationResult(out_dir, bag_path, gt_dir / 'gt.csv',
                              gt_dir / 'gt_sensor_tum.txt',
                              out_dir / 'topdown.png' if topdown_png else None, n_scans)
    sensor_stamps = np.zeros(n_scans, np.int64)
    sensor_poses = np.zeros((n_scans, 4, 4))
    stride = max(1, int(np.ceil(n_scans * len(sim.rays['ring']) / TOPDOWN_MAX_POINTS)))
    merged: list[np.ndarray] = []
    gps_next = 0
    with BagWriter(bag_path, fmt=fmt, storage=storage) as writer:
        writer.write_metadata(METADATA_TOPIC, sim.stamp_ns(0), METADATA_KEY,
                              json.dumps(metadata, sort_keys=True))
        for k in range(n_scans):
            sim_scan = sim.scan(k)
            scan = sim_scan.scan
            while gps_next < gps_stamps.size and gps_stamps[gps_next] < scan.stamp_ns:
                writer.write_odometry(GPS_TOPIC, int(gps_stamps[gps_next]),
                                      T_world_gps[gps_next], frame_id='map',
                                      child_frame_id='gps')
                gps_next += 1
            writer.write_cloud(LIDAR_TOPIC, scan.stamp_ns, encode_scan(scan, layout),
                               scan.frame_id)
            sensor_stamps[k] = scan.stamp_ns
            sensor_poses[k] = sim_scan.T_world_sensor
            result.seconds_per_scan.append(sim_scan.seconds)
            result.points_per_scan.append(len(scan))
            if topdown_png:
                merged.append(transform_points(sim_scan.T_world_sensor,
                                               scan.points_xyz[::stride]).astype(np.float32))
            if progress is not None:
                progress(k + 1)
        for i in range(gps_next, gps_stamps.size):
            writer.write_odometry(GPS_TOPIC, int(gps_stamps[i]), T_world_gps[i],
                                  frame_id='map', child_frame_id='gps')

    write_tum(result.gt_tum_path, Trajectory(sensor_stamps, sensor_poses))
    travelled = np.linalg.norm(np.diff(sensor_poses[:, :3, 3], axis=0), axis=1).sum()
    metadata['distance_m'] = float(travelled)
    write_text_atomic(out_dir / METADATA_FILE, json.dumps(metadata, indent=2,
                                                          sort_keys=True) + '\n')
    _write_gt_csv(result.gt_csv_path, Trajectory(gps_stamps, T_world_gps))
    if topdown_png:
        points = np.concatenate(merged) if merged else np.zeros((0, 3), np.float32)
        ground_z = orchard.ground.height(points[:, 0], points[:, 1])
        render_topdown(result.topdown_png_path, points, points[:, 2] - ground_z,
                       sensor_poses[:, :3, 3],
                       title=f'{scenario}, seed {seed}: {n_scans} scans merged with the '
                             'ground-truth poses')
    log.info('wrote %s (%d scans, median %.3f s/scan, %.0f points/scan)', bag_path, n_scans,
             result.median_seconds_per_scan, float(np.mean(result.points_per_scan)))
    return result


def drive_metadata(sim: ScanSimulator, scenario: str, seed: int, n_scans: int,
                   variation: OrchardVariation | None) -> dict:
    """What a bag's drive was made of: scenario, seed, the effective SimConfig, the draws."""
    orchard = sim.orchard
    return {
        'gft_odom_sim_version': 2,
        'scenario': scenario,
        'seed': int(seed),
        'n_scans': int(n_scans),
        'varied': variation is not None,
        'variation': variation.as_dict() if variation is not None else None,
        'sim_config': {k: (list(v) if isinstance(v, tuple) else v)
                       for k, v in asdict(sim.config).items()},
        'orchard': {'n_rows': int(len(orchard.row_v_m)),
                    'row_spacing_m': float(orchard.row_spacing_m),
                    'tree_spacing_m': float(orchard.tree_spacing_m),
                    'row_length_m': float(orchard.row_end_u_m - orchard.row_start_u_m)},
        'duration_s': float(sim.motion.duration_s),
    }


def read_drive_metadata(bag_path: str | Path) -> dict | None:
    """The `sim_metadata.json` beside a simulated bag, or None for a bag from elsewhere."""
    path = Path(bag_path).parent / METADATA_FILE
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SimulationError(f'cannot read the drive metadata {path}: {exc}') from exc


def _write_gt_csv(path: Path, traj: Trajectory) -> None:
    """CitrusFarm-style gt.csv: a header, then time (s, 9 decimals) x y z qx qy qz qw."""
    from gft_odom.core.geometry import xyz_quat_from_poses
    from gft_odom.io.atomic import write_text_atomic

    xyz, quat = xyz_quat_from_poses(traj.poses)
    lines = ['timestamp,x,y,z,qx,qy,qz,qw']
    for stamp, p, q in zip(traj.stamps_ns.tolist(), xyz, quat):
        sec, nsec = ns_to_sec_nanosec(stamp)
        lines.append(f'{sec}.{nsec:09d},' + ','.join(f'{v:.6f}' for v in p) + ','
                     + ','.join(f'{v:.9f}' for v in q))
    write_text_atomic(path, '\n'.join(lines) + '\n')


def render_topdown(path: Path, points_xyz: np.ndarray, height_above_ground_m: np.ndarray,
                   path_xyz: np.ndarray, title: str = '', pixel_m: float = 0.1,
                   margin_m: float = TOPDOWN_MARGIN_M) -> None:
    """Top-down image around the path: per pixel the highest point above the ground, on a
    quantile colour scale (most pixels are ground, a linear scale hides the trees)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm

    if points_xyz.shape[0] == 0:
        raise SimulationError(f'no points to draw in {path}')
    xy = points_xyz[:, :2].astype(float)
    lo = np.minimum(xy.min(axis=0), path_xyz[:, :2].min(axis=0)) - 1.0
    hi = np.maximum(xy.max(axis=0), path_xyz[:, :2].max(axis=0)) + 1.0
    # The path plus a margin: the far returns of a +-60 m sweep make the path a speck.
    lo = np.maximum(lo, path_xyz[:, :2].min(axis=0) - margin_m)
    hi = np.minimum(hi, path_xyz[:, :2].max(axis=0) + margin_m)
    pixel_m = max(pixel_m, float((hi - lo).max()) / 1500.0)  # at most ~1500 pixels a side
    shape = np.ceil((hi - lo) / pixel_m).astype(int) + 1
    ij = np.floor((xy - lo) / pixel_m).astype(int)
    inside = (ij >= 0).all(axis=1) & (ij < shape).all(axis=1)
    flat = np.full(shape[0] * shape[1], -np.inf)
    np.maximum.at(flat, ij[inside, 0] * shape[1] + ij[inside, 1],
                  np.asarray(height_above_ground_m, float)[inside])
    image = flat.reshape(shape)
    image[~np.isfinite(image)] = np.nan
    width_in = 10.0
    aspect = shape[1] / shape[0]
    fig, ax = plt.subplots(figsize=(width_in, float(np.clip(width_in * aspect, 4.0, 14.0))))
    # Ground (most pixels) one colour, then deciles of the pixels above it: a quantile scale
    # over all pixels spends its colours on centimetres of ground noise.
    seen = image[np.isfinite(image)]
    above = seen[seen > TOPDOWN_GROUND_M]
    edges = None
    if above.size > 10:
        edges = np.unique(np.concatenate((
            [min(seen.min(), TOPDOWN_GROUND_M - 0.1), TOPDOWN_GROUND_M],
            np.quantile(above, np.linspace(0.0, 1.0, 11))[1:])))
    scale = {'vmin': -0.2, 'vmax': 3.5}
    if edges is not None and edges.size >= 3:
        cmap = plt.get_cmap('viridis', edges.size - 1)
        scale = {'norm': BoundaryNorm(edges, cmap.N)}
    else:
        cmap, edges = plt.get_cmap('viridis'), None
    im = ax.imshow(image.T, origin='lower', cmap=cmap, **scale,
                   extent=(lo[0], lo[0] + shape[0] * pixel_m, lo[1], lo[1] + shape[1] * pixel_m),
                   interpolation='nearest')
    ax.plot(path_xyz[:, 0], path_xyz[:, 1], color='red', lw=1.2, label='ground truth (LiDAR)')
    ax.plot(path_xyz[0, 0], path_xyz[0, 1], 'o', color='red', ms=5, label='start')
    ax.set_xlabel('x [m] (orchard frame)')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal')
    ax.set_title(title, fontsize=9)
    ax.legend(loc='upper right', fontsize=8)
    bar = fig.colorbar(im, ax=ax, shrink=0.7, label='highest point above ground [m]')
    if edges is not None:
        bar.set_ticks(edges)
        bar.set_ticklabels(_distinct_labels(edges))
        bar.ax.set_title(f'ground, then\ndeciles of the\npixels above\n{TOPDOWN_GROUND_M} m',
                         fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100, bbox_inches='tight')
    plt.close(fig)


def _distinct_labels(values: np.ndarray) -> list[str]:
    """Fewest decimals (>= 2) at which neighbouring tick values read differently."""
    for decimals in range(2, 7):
        labels = [f'{v:.{decimals}f}' for v in values]
        if all(a != b for a, b in zip(labels, labels[1:])):
            return labels
    return [f'{v:.6g}' for v in values]


__all__ = ['GPS_TOPIC', 'LIDAR_TOPIC', 'SimulationResult', 'bag_path_for', 'render_topdown',
           'simulate_to_bag']
