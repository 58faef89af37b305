"""Registration modes and estimators on simulated orchard drives: accuracy and latency.

Usage: .venv/bin/python benchmarks/bench_registration.py [--scans 120] [--scenarios row uturn]

Sequences come from `gft_odom.sim` (orchard, Jackal motion, VLP-16 ray caster at 0.2 deg).
Every configuration sees the same scans, unfiltered (the spectral filter is benchmarked
elsewhere; registration must be good on its own). Reported per configuration and sequence:
end-point error and ATE RMSE (SE(3) Umeyama alignment, gft_odom.core.metrics) against the
exact sensor poses, fallback count, and per-scan `register` latency median / p95.
Writes benchmarks/results/registration.json and registration.md.

Motion distortion: like a real VLP-16 driver, the simulator reports every point in the sensor
frame at the time it was fired (per-point `time` offset from the stamp), so deskew is exercised
as on a real sensor.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import platform
import time
from pathlib import Path

import numpy as np

from gft_odom.core.geometry import invert_transform
from gft_odom.core.metrics import ate
from gft_odom.core.registration import RegistrationConfig, ScanRegistration
from gft_odom.core.trajectory import Trajectory
from gft_odom.sim.motion import make_motion, required_row_length_m
from gft_odom.sim.orchard import generate_orchard
from gft_odom.sim.simulator import ScanSimulator, SimConfig

RESULTS_DIR = Path(__file__).resolve().parent / 'results'

CONFIGS = {
    'paper (p2p scan-to-scan)': {'mode': 'paper'},
    'default': {},
    'default, no deskew': {'deskew': False},
    'default, deskew (time field)': {'deskew': True},
    'default, deskew from azimuth': {'deskew': True, '_no_time_field': True},
    'default, deskew velocity window 1': {'deskew': True, 'deskew_velocity_window': 1},
    'default, deskew 6-DoF': {'deskew': True, 'deskew_planar': False},
    'default, 10 iterations': {'max_iterations': 10},
    'default, convergence 1e-6': {'convergence_relative': 1e-6},
    'default, gicp': {'estimation': 'gicp'},
    'default, point_to_point': {'estimation': 'point_to_point'},
    'default, voxel 0.3 m': {'voxel_size_m': 0.3},
    'default, kernel 0.1 m': {'robust_kernel_scale_m': 0.1},
    'default, map voxel 0.2 m': {'map_voxel_size_m': 0.2},
}


def simulate(scenario: str, n_scans: int, seed: int) -> dict:
    """Scans (points, time offsets, stamps) and the true T_world_sensor at each stamp."""
    config = SimConfig()
    period_s = 1.0 / config.scan_rate_hz
    duration_s = (n_scans + 1) * period_s
    orchard = generate_orchard(seed, n_rows=config.n_rows, row_length_m=required_row_length_m(
        scenario, duration_s * config.speed_mps))
    motion = make_motion(orchard, scenario, duration_s, config.speed_mps, seed,
                         config.lateral_wobble_m, config.yaw_wobble_rad)
    sim = ScanSimulator(orchard, motion, config, seed)
    scans, poses, seconds = [], [], []
    for k in range(n_scans):
        s = sim.scan(k)
        scans.append((s.scan.points_xyz, s.scan.stamp_ns, s.scan.time_offset_s))
        poses.append(s.T_world_sensor)
        seconds.append(s.seconds)
    poses = np.array(poses)
    poses = invert_transform(poses[0]) @ poses  # world = first sensor frame, as registration
    stamps = np.array([s[1] for s in scans], dtype=np.int64)
    return {'scans': scans, 'truth': Trajectory(stamps, poses),
            'n_points_median': int(np.median([len(s[0]) for s in scans])),
            'sim_seconds_per_scan': float(np.mean(seconds)),
            'path_length_m': Trajectory(stamps, poses).path_length_m()}


def run(sequence: dict, overrides: dict) -> dict:
    overrides = dict(overrides)
    no_time = overrides.pop('_no_time_field', False)
    reg = ScanRegistration.from_config(dataclasses.replace(RegistrationConfig(), **overrides))
    poses, latency_ms, cpu_ms, statuses = [], [], [], []
    for points, stamp_ns, offsets in sequence['scans']:
        t0, c0 = time.perf_counter(), time.process_time()
        result = reg.register(points, stamp_ns, None if no_time else offsets)
        latency_ms.append((time.perf_counter() - t0) * 1e3)
        cpu_ms.append((time.process_time() - c0) * 1e3)
        poses.append(result.T_world_sensor)
        statuses.append(result.status)
    truth = sequence['truth']
    est = Trajectory(truth.stamps_ns, np.array(poses))
    end_err = float(np.linalg.norm(est.positions_xyz[-1] - truth.positions_xyz[-1]))
    ate_se3 = ate(est, truth, mode='se3')
    latency = np.array(latency_ms[1:])  # the first scan only builds the map
    cpu = np.array(cpu_ms[1:])
    return {
        'end_point_error_m': end_err,
        'end_point_error_pct': 100.0 * end_err / max(sequence['path_length_m'], 1e-9),
        'ate_rmse_m': ate_se3.rmse_m, 'ate_rotation_rmse_deg': ate_se3.rotation_rmse_deg,
        'latency_median_ms': float(np.median(latency)),
        'latency_p95_ms': float(np.percentile(latency, 95)),
        # CPU time of all threads: with OMP_NUM_THREADS=1 it is the latency on an idle core,
        # whatever else the machine runs.
        'cpu_median_ms': float(np.median(cpu)), 'cpu_p95_ms': float(np.percentile(cpu, 95)),
        'fallbacks': int(sum(s.startswith('fallback') for s in statuses)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scans', type=int, default=200)
    parser.add_argument('--scenarios', nargs='+', default=['row', 'uturn'])
    parser.add_argument('--seed', type=int, default=3)
    parser.add_argument('--configs', nargs='*', default=list(CONFIGS))
    parser.add_argument('--cache', type=Path, default=None,
                        help='directory to keep simulated sequences in between runs')
    args = parser.parse_args()
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    report = {'machine': {'cpus': os.cpu_count(), 'python': platform.python_version(),
                          'load_avg_at_start': os.getloadavg(),
                          'OMP_NUM_THREADS': os.environ.get('OMP_NUM_THREADS', 'unset')},
              'scans_per_sequence': args.scans, 'sequences': {}}
    for scenario in args.scenarios:
        t0 = time.perf_counter()
        cached = args.cache and args.cache / (
            f'{scenario}_{args.scans}_{args.seed}.pkl')
        if cached and cached.exists():
            seq = pickle.loads(cached.read_bytes())
        else:
            seq = simulate(scenario, args.scans, args.seed)
            if cached:
                cached.parent.mkdir(parents=True, exist_ok=True)
                cached.write_bytes(pickle.dumps(seq))
        print(f'{scenario}: {args.scans} scans, {seq["path_length_m"]:.1f} m, '
              f'{seq["n_points_median"]} points/scan, '
              f'simulated in {time.perf_counter() - t0:.0f} s', flush=True)
        entry = {'path_length_m': seq['path_length_m'], 'n_points_median': seq['n_points_median'],
                 'results': {}}
        for name in args.configs:
            res = run(seq, CONFIGS[name])
            entry['results'][name] = res
            print(f'  {name:34s} end {res["end_point_error_m"]:6.3f} m '
                  f'({res["end_point_error_pct"]:5.2f} %)  ATE {res["ate_rmse_m"]:6.3f} m  '
                  f'latency {res["latency_median_ms"]:5.1f} / {res["latency_p95_ms"]:5.1f} ms  '
                  f'cpu {res["cpu_median_ms"]:5.1f} / {res["cpu_p95_ms"]:5.1f} ms  '
                  f'fallbacks {res["fallbacks"]}', flush=True)
        report['sequences'][scenario] = entry
    report['load_avg_at_end'] = os.getloadavg()
    (RESULTS_DIR / 'registration.json').write_text(json.dumps(report, indent=2))
    lines = ['| sequence | configuration | end error m (%) | ATE RMSE m | latency median / p95 ms '
             '| CPU median / p95 ms | fallbacks |', '|---|---|---|---|---|---|---|']
    for scenario, entry in report['sequences'].items():
        for name, r in entry['results'].items():
            lines.append(f'| {scenario} ({entry["path_length_m"]:.0f} m) | {name} | '
                         f'{r["end_point_error_m"]:.3f} ({r["end_point_error_pct"]:.2f}) | '
                         f'{r["ate_rmse_m"]:.3f} | {r["latency_median_ms"]:.1f} / '
                         f'{r["latency_p95_ms"]:.1f} | {r["cpu_median_ms"]:.1f} / '
                         f'{r["cpu_p95_ms"]:.1f} | {r["fallbacks"]} |')
    (RESULTS_DIR / 'registration.md').write_text('\n'.join(lines) + '\n')
    print(f'wrote {RESULTS_DIR / "registration.json"}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
