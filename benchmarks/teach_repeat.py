"""Teach a block once, repeat it on a later day: odometry alone against localisation in the map.

For each block (simulator seed): the map day drives `--map-route` and leaves a map (the
odometry's poses, every deskewed scan 1 m / 0.2 rad apart, one point per 0.3 m voxel, each
with its frequency and the simulator's surface class). A later day drives `--route` in the
same block twice, with the same driving: once with the map day's canopy (`same`) and once
with a changed one (`changed`: grown or hedged, sim/later_day.py). Each repeat runs the
odometry and, beside it, localisers in the map that differ only in which points they use:

- `all`: every point of the map and of the scan;
- `oracle`: only what stays from one day to the next by the simulator's true class (ground,
  trunks, posts, pipes, buildings, vehicles), in the map and in the scan;
- `frequency`: only the smooth points by their graph frequency (nu >= 0.3, the cut the
  odometry's map anchors use), in the map and in the scan;
- `shuffled`: the same with the frequencies permuted (the map's once, each scan's), the
  control for any effect of the frequency;
- `weighted` (and `weighted_shuffled`, its control): every point, a pair's residual weighed by
  its points' smoothness (rough: 0.25, smooth: 1).

The start pose is the true one moved by 0.2 m, -0.15 m and 0.03 rad (a pose set by hand in
RViz). Scored three ways: against the truth in the map frame without alignment (what a robot
acts on; the map day's own drift is in it), the same after a rigid alignment of the positions
(ATE), and against the map as drawn (where the map day's odometry put the same place: the
localisation's own error). Mean errors in each 50 m of distance travelled. Odometry alone is
scored the same way from the same start.

Writes benchmarks/results/teach_repeat.json and prints a table.

Run: .venv/bin/python benchmarks/teach_repeat.py --seeds 401 402 [--quick]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from gft_odom.config import GftOdomConfig
from gft_odom.core.alignment import umeyama_alignment
from gft_odom.core.geometry import invert_transform, rpy_transform
from gft_odom.core.localisation import DriveMap, Localiser, PriorMap, smoothness_weights
from gft_odom.core.registration.local_map import ANCHOR_SMOOTHNESS
from gft_odom.core.registration.sweep import SMOOTH_NU
from gft_odom.pipeline import DRIVE_MAP_STATUSES, OdometryPipeline
from gft_odom.sim.later_day import simulate_day
from gft_odom.sim.orchard import CANOPY
from gft_odom.sim.simulator import SimConfig

RESULTS = Path(__file__).parent / 'results' / 'teach_repeat.json'
START_ERROR = rpy_transform((0.2, -0.15, 0.0), (0.0, 0.0, 0.03))
BIN_M = 50.0
# A point is smooth (ground, trunks, posts) at this frequency: the map anchors' cut.
SMOOTH_CUT = ANCHOR_SMOOTHNESS * SMOOTH_NU
ROLES = ('all', 'oracle', 'frequency', 'shuffled', 'weighted', 'weighted_shuffled')


def drive(sim, n_scans: int | None, config: GftOdomConfig):
    """Run the odometry over a simulated day: yields (frame result, deskewed kept points in
    the sensor frame, their surface class, true T_sim_sensor at the pose's stamp)."""
    pipeline = OdometryPipeline(config)
    n = min(n_scans or sim.n_scans_in_drive, sim.n_scans_in_drive)
    for k in range(n):
        sim_scan = sim.scan(k)
        index = pipeline._crop_index(sim_scan.scan)
        result = pipeline.register_frame(sim_scan.scan)
        points = pipeline.registration.deskewed_like_last(result.filtered.points_xyz)
        surface = sim_scan.surface[index]
        if surface.shape[0] != points.shape[0]:
            raise RuntimeError('the kept cloud does not follow the crop: use an all-pass mask')
        t_s = (result.stamp_ns - sim.start_ns) * 1e-9
        truth = sim.sensor_poses(np.array([t_s]))[0]
        yield result, points, surface, truth
        pipeline.update_map()


def teach(sim, n_scans, config) -> tuple[DriveMap, np.ndarray, dict]:
    """The map day's map (odometry world frame, as the pipeline's drive map takes it, with
    the surface class), T_map_sim, and the map day's own poses: true positions (sim world)
    and odometry poses, to tell a later day's error against the map as drawn."""
    drive_map, T_map_sim = DriveMap(), None
    true_xyz, odometry = [], []
    every_m = config.registration.keyframe_distance_m
    for result, points, surface, truth in drive(sim, n_scans, config):
        if T_map_sim is None:
            T_map_sim = result.T_world_sensor @ invert_transform(truth)
        true_xyz.append(truth[:3, 3])
        odometry.append(result.T_world_sensor @ invert_transform(truth))  # sim -> map, here
        if result.status in DRIVE_MAP_STATUSES and drive_map.due(result.T_world_sensor,
                                                                 every_m):
            drive_map.add_scan(result.T_world_sensor, points, result.nu, surface=surface)
    map_day = {'true_xyz': np.asarray(true_xyz), 'T_map_sim_here': np.asarray(odometry)}
    end = map_day['T_map_sim_here'][-1] @ invert_transform(T_map_sim)
    map_day['end_error_m'] = float(np.linalg.norm(end[:3, 3]))
    return drive_map, T_map_sim, map_day


def _keep(nu: np.ndarray) -> np.ndarray:
    """The frequency's role: the smooth points (ground, trunks, posts), by the anchors' cut."""
    return np.nan_to_num(np.asarray(nu, dtype=float), nan=0.0) >= SMOOTH_CUT


def localisers(prior: PriorMap, rng: np.random.Generator, roles) -> dict:
    """name -> (localiser, f(surface, nu) -> (the scan's points kept or None, their weights or
    None))."""
    stable = prior.attributes['surface'] != CANOPY
    shuffled_nu = rng.permutation(prior.nu)
    out = {
        'all': (Localiser(prior, np.eye(4)), lambda surface, nu: (None, None)),
        'oracle': (Localiser(prior.selected(stable), np.eye(4)),
                   lambda surface, nu: (surface != CANOPY, None)),
        'frequency': (Localiser(prior.selected(_keep(prior.nu)), np.eye(4)),
                      lambda surface, nu: (_keep(nu), None)),
        'shuffled': (Localiser(prior.selected(_keep(shuffled_nu)), np.eye(4)),
                     lambda surface, nu: (_keep(rng.permutation(nu)), None)),
        'weighted': (Localiser(prior.weighted(smoothness_weights(prior.nu)), np.eye(4)),
                     lambda surface, nu: (None, smoothness_weights(nu))),
        'weighted_shuffled': (
            Localiser(prior.weighted(smoothness_weights(shuffled_nu)), np.eye(4)),
            lambda surface, nu: (None, smoothness_weights(rng.permutation(nu)))),
    }
    return {name: out[name] for name in roles}


def repeat(sim, n_scans, config, prior: PriorMap, T_map_sim: np.ndarray, map_day: dict,
           seed: int, roles=ROLES) -> dict:
    """Odometry alone and each localiser on a later day: per-scan errors and summaries."""
    rng = np.random.default_rng(seed)
    methods = localisers(prior, rng, roles)
    nearest = cKDTree(map_day['true_xyz'])
    errors = {name: [] for name in ('odometry', *methods)}
    to_map = {name: [] for name in errors}
    poses = {name: [] for name in errors}
    truth_xyz, distance, started = [], [], False
    work_s = {name: 0.0 for name in methods}
    statuses = {name: {} for name in methods}
    for result, points, surface, truth in drive(sim, n_scans, config):
        true_map = T_map_sim @ truth
        # Where the map day's odometry put this place: the map as drawn, not the world.
        as_drawn = map_day['T_map_sim_here'][nearest.query(truth[:3, 3])[1]] @ truth
        if not started:
            T_map_odom0 = true_map @ START_ERROR @ invert_transform(result.T_world_sensor)
            for loc, _ in methods.values():
                loc.T_map_odom = T_map_odom0.copy()
            started = True
        xyz = true_map[:3, 3]
        distance.append(0.0 if not truth_xyz else distance[-1]
                        + float(np.linalg.norm(xyz - truth_xyz[-1])))
        truth_xyz.append(xyz)
        estimates = {'odometry': T_map_odom0 @ result.T_world_sensor}
        nu = result.nu if result.nu is not None else np.full(len(points), np.nan)
        for name, (loc, keep) in methods.items():
            t0 = time.perf_counter()
            kept, weights = keep(surface, nu)
            out = loc.localise(points, result.T_world_sensor, keep=kept, weights=weights)
            work_s[name] += time.perf_counter() - t0
            statuses[name][out.status] = statuses[name].get(out.status, 0) + 1
            estimates[name] = out.T_map_sensor
        for name, T in estimates.items():
            errors[name].append(float(np.linalg.norm(T[:3, 3] - xyz)))
            to_map[name].append(float(np.linalg.norm(T[:3, 3] - as_drawn[:3, 3])))
            poses[name].append(T[:3, 3])
    distance, truth_xyz = np.asarray(distance), np.asarray(truth_xyz)
    bins = np.floor(distance / BIN_M).astype(int)
    summary = {}
    for name, e in errors.items():
        e, m = np.asarray(e), np.asarray(to_map[name])
        R, t, _ = umeyama_alignment(np.asarray(poses[name]), truth_xyz)
        aligned = np.linalg.norm(np.asarray(poses[name]) @ R.T + t - truth_xyz, axis=1)
        summary[name] = {
            'rmse_m': float(np.sqrt(np.mean(e ** 2))), 'max_m': float(e.max()),
            'ate_rmse_m': float(np.sqrt(np.mean(aligned ** 2))),
            'ate_max_m': float(aligned.max()),
            'to_map_rmse_m': float(np.sqrt(np.mean(m ** 2))), 'to_map_max_m': float(m.max()),
            'mean_per_50m_m': [float(e[bins == b].mean()) for b in range(bins.max() + 1)],
            'to_map_per_50m_m': [float(m[bins == b].mean()) for b in range(bins.max() + 1)],
        }
        if name in methods:
            summary[name]['statuses'] = statuses[name]
            summary[name]['work_ms_per_scan'] = 1e3 * work_s[name] / len(e)
    return {'distance_m': float(distance[-1]), 'n_scans': int(distance.size),
            'methods': summary}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[401, 402])
    parser.add_argument('--map-route', default='lawnmower')
    parser.add_argument('--route', default='spiral')
    parser.add_argument('--map-distance-m', type=float, default=150.0)
    parser.add_argument('--distance-m', type=float, default=150.0)
    parser.add_argument('--roles', nargs='+', default=list(ROLES), choices=ROLES)
    parser.add_argument('--changes', nargs='+', default=['same', 'changed'])
    parser.add_argument('--quick', action='store_true', help='coarse scans, 150 of each day')
    parser.add_argument('--out', type=Path, default=RESULTS)
    args = parser.parse_args()
    sim_config = SimConfig(azimuth_step_deg=0.8) if args.quick else SimConfig()
    n_scans = 150 if args.quick else None
    config = GftOdomConfig()
    runs = []
    for seed in args.seeds:
        t0 = time.time()
        map_sim, _ = simulate_day(sim_config, seed, args.map_route,
                                  map_distance_m=args.map_distance_m)
        drive_map, T_map_sim, map_day = teach(map_sim, n_scans, config)
        prior = PriorMap.from_drive_map(drive_map)
        map_error = map_day['end_error_m']
        print(f'block {seed}: map of {len(drive_map)} points, map day ends {map_error:.3f} m '
              f'off ({time.time() - t0:.0f} s)', flush=True)
        for change in args.changes:
            sim, canopy = simulate_day(sim_config, seed, args.map_route, day=1,
                                       route=args.route, change=change,
                                       map_distance_m=args.map_distance_m,
                                       distance_m=args.distance_m)
            run = repeat(sim, n_scans, config, prior, T_map_sim, map_day, seed, args.roles)
            run.update(seed=seed, change=change, canopy=canopy.kind,
                       map_points=len(drive_map), map_day_end_error_m=map_error)
            runs.append(run)
            line = ', '.join(f"{k} {v['ate_rmse_m']:.3f}/{v['to_map_rmse_m']:.3f}/"
                             f"{v['to_map_max_m']:.3f}" for k, v in run['methods'].items())
            print(f'  {change} ({canopy.kind}), {run["distance_m"]:.0f} m: ATE / to the map '
                  f'RMSE / max [m]: {line} '
                  f'({time.time() - t0:.0f} s)', flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({'args': {k: str(v) for k, v in vars(args).items()},
                                    'runs': runs}, indent=1) + '\n')
    print(f'wrote {args.out}')


if __name__ == '__main__':
    main()
