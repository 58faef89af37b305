"""Teach a block once, repeat it on a later day: odometry alone against localisation in the map.

For each block (simulator seed): the map day drives `--map-route` and leaves a map (the
odometry's poses, every deskewed scan 1 m / 0.2 rad apart, one point per 0.3 m voxel, each
with its frequency and the simulator's surface class). A later day drives `--route` in the
same block twice, with the same driving: once with the map day's canopy (`same`) and once
with a changed one (`changed`: grown or hedged, sim/later_day.py). Each repeat runs the
odometry and, beside it, localisers in the map that differ only in which points they use:

- `all`: every point of the map and of the scan;
- `oracle`: only what stays from one day to the next by the simulator's true class (ground,
  trunks, posts, pipes, buildings, vehicles), in the map and in the scan.

The start pose is the true one moved by 0.2 m, -0.15 m and 0.03 rad (a pose set by hand in
RViz). Scored in the map frame, without any alignment (what a robot would act on): the
sensor's position error at every scan, its RMSE and maximum, and the mean error in each 50 m
of distance travelled. Odometry alone is scored the same way from the same start.

Writes benchmarks/results/teach_repeat.json and prints a table.

Run: .venv/bin/python benchmarks/teach_repeat.py --seeds 401 402 [--quick]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from gft_odom.config import GftOdomConfig
from gft_odom.core.geometry import invert_transform, rpy_transform
from gft_odom.core.localisation import DriveMap, Localiser, PriorMap
from gft_odom.pipeline import OdometryPipeline
from gft_odom.sim.later_day import simulate_day
from gft_odom.sim.orchard import CANOPY
from gft_odom.sim.simulator import SimConfig

RESULTS = Path(__file__).parent / 'results' / 'teach_repeat.json'
START_ERROR = rpy_transform((0.2, -0.15, 0.0), (0.0, 0.0, 0.03))
BIN_M = 50.0
TRUSTED = ('first', 'ok', 'recovered')


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


def teach(sim, n_scans, config) -> tuple[DriveMap, np.ndarray, float]:
    """The map day's map (odometry world frame, as the pipeline's drive map takes it, with
    the surface class), T_map_sim, and how far the map day's odometry ended from the truth."""
    drive_map, T_map_sim, error = DriveMap(), None, 0.0
    every_m = config.registration.keyframe_distance_m
    for result, points, surface, truth in drive(sim, n_scans, config):
        if T_map_sim is None:
            T_map_sim = result.T_world_sensor @ invert_transform(truth)
        error = float(np.linalg.norm((T_map_sim @ truth)[:3, 3] - result.T_world_sensor[:3, 3]))
        if result.status in TRUSTED and drive_map.due(result.T_world_sensor, every_m):
            drive_map.add_scan(result.T_world_sensor, points, result.nu, surface=surface)
    return drive_map, T_map_sim, error


def repeat(sim, n_scans, config, prior: PriorMap, T_map_sim: np.ndarray) -> dict:
    """Odometry alone and each localiser on a later day: per-scan errors and summaries."""
    stable_map = prior.attributes['surface'] != CANOPY
    localisers = {'all': (Localiser(prior, np.eye(4)), False),
                  'oracle': (Localiser(prior.selected(stable_map), np.eye(4)), True)}
    errors = {name: [] for name in ('odometry', *localisers)}
    distance, last_xyz, started = [], None, False
    work_s = {name: 0.0 for name in localisers}
    statuses = {name: {} for name in localisers}
    for result, points, surface, truth in drive(sim, n_scans, config):
        true_map = T_map_sim @ truth
        if not started:
            T_map_odom0 = true_map @ START_ERROR @ invert_transform(result.T_world_sensor)
            for loc, _ in localisers.values():
                loc.T_map_odom = T_map_odom0.copy()
            started = True
        xyz = true_map[:3, 3]
        distance.append(0.0 if last_xyz is None else distance[-1]
                        + float(np.linalg.norm(xyz - last_xyz)))
        last_xyz = xyz
        odometry = T_map_odom0 @ result.T_world_sensor
        errors['odometry'].append(float(np.linalg.norm(odometry[:3, 3] - xyz)))
        for name, (loc, oracle) in localisers.items():
            t0 = time.perf_counter()
            out = loc.localise(points, result.T_world_sensor,
                               keep=(surface != CANOPY) if oracle else None)
            work_s[name] += time.perf_counter() - t0
            statuses[name][out.status] = statuses[name].get(out.status, 0) + 1
            errors[name].append(float(np.linalg.norm(out.T_map_sensor[:3, 3] - xyz)))
    distance = np.asarray(distance)
    bins = np.floor(distance / BIN_M).astype(int)
    summary = {}
    for name, e in errors.items():
        e = np.asarray(e)
        summary[name] = {
            'rmse_m': float(np.sqrt(np.mean(e ** 2))), 'max_m': float(e.max()),
            'end_m': float(e[-1]),
            'mean_per_50m_m': [float(e[bins == b].mean()) for b in range(bins.max() + 1)],
        }
        if name in localisers:
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
        drive_map, T_map_sim, map_error = teach(map_sim, n_scans, config)
        prior = PriorMap.from_drive_map(drive_map)
        print(f'block {seed}: map of {len(drive_map)} points, map day ends {map_error:.3f} m '
              f'off ({time.time() - t0:.0f} s)', flush=True)
        for change in ('same', 'changed'):
            sim, canopy = simulate_day(sim_config, seed, args.map_route, day=1,
                                       route=args.route, change=change,
                                       map_distance_m=args.map_distance_m,
                                       distance_m=args.distance_m)
            run = repeat(sim, n_scans, config, prior, T_map_sim)
            run.update(seed=seed, change=change, canopy=canopy.kind,
                       map_points=len(drive_map), map_day_end_error_m=map_error)
            runs.append(run)
            line = ', '.join(f"{k} {v['rmse_m']:.3f}/{v['max_m']:.3f}"
                             for k, v in run['methods'].items())
            print(f'  {change} ({canopy.kind}), {run["distance_m"]:.0f} m: RMSE/max [m] {line} '
                  f'({time.time() - t0:.0f} s)', flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({'args': {k: str(v) for k, v in vars(args).items()},
                                    'runs': runs}, indent=1) + '\n')
    print(f'wrote {args.out}')


if __name__ == '__main__':
    main()
