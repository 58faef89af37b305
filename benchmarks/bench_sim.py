"""Speed of the orchard simulator: seconds per VLP-16 sweep (0.2 deg, real geometry).

For each scenario it simulates `--scans` sweeps and reports the median and p95 wall and CPU
time per sweep (ray casting, noise, intensity: `ScanSimulator.scan`) and the points per sweep;
then one `simulate_to_bag` run (ROS 2 bag, no picture) gives the end-to-end time per sweep
including PointCloud2 encoding and bag writing. BLAS/OpenMP threads are pinned to one, so the
figures are for one core (the target is under 0.3 s per sweep). Wall time is what a user waits
on a shared machine; CPU time is the cost on an idle core.

Writes benchmarks/results/sim.json.
Run: .venv/bin/python benchmarks/bench_sim.py [--scans 20] [--seed 0]
"""

from __future__ import annotations

import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from gft_odom.sim.motion import SCENARIOS  # noqa: E402
from gft_odom.sim.orchard import SURFACE_NAMES  # noqa: E402
from gft_odom.sim.simulator import ScanSimulator, SimConfig  # noqa: E402
from gft_odom.sim.writer import simulate_to_bag  # noqa: E402

RESULTS = Path(__file__).parent / 'results' / 'sim.json'


def bench_scenario(scenario: str, n_scans: int, seed: int, config: SimConfig) -> dict:
    t0 = time.perf_counter()
    sim = ScanSimulator.from_config(config, scenario, n_scans, seed)
    setup_s = time.perf_counter() - t0
    wall, cpu, points = [], [], []
    surfaces = np.zeros(len(SURFACE_NAMES), int)
    for k in range(n_scans):
        c0, w0 = time.process_time(), time.perf_counter()
        out = sim.scan(k)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
        points.append(len(out.scan))
        surfaces += np.bincount(out.surface, minlength=len(SURFACE_NAMES))
    return {
        'scenario': scenario,
        'scans': n_scans,
        'orchard_and_motion_setup_s': round(setup_s, 3),
        'wall_s_per_scan_median': round(float(np.median(wall)), 4),
        'wall_s_per_scan_p95': round(float(np.percentile(wall, 95)), 4),
        'cpu_s_per_scan_median': round(float(np.median(cpu)), 4),
        'cpu_s_per_scan_p95': round(float(np.percentile(cpu, 95)), 4),
        'points_per_scan_median': int(np.median(points)),
        'rays_per_scan': int(sim.rays['ring'].size),
        'point_share_by_surface': {name: round(float(n) / max(1, surfaces.sum()), 4)
                                   for name, n in zip(SURFACE_NAMES, surfaces)},
    }


def bench_end_to_end(n_scans: int, seed: int, config: SimConfig) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        c0, w0 = time.process_time(), time.perf_counter()
        result = simulate_to_bag(Path(tmp) / 'out', 'row', n_scans, seed, config,
                                 topdown_png=False)
        wall = time.perf_counter() - w0
        cpu = time.process_time() - c0
        bag_bytes = sum(p.stat().st_size for p in result.bag_path.rglob('*') if p.is_file())
    return {'scenario': 'row', 'scans': n_scans, 'format': 'ros2 sqlite3',
            'wall_s_per_scan': round(wall / n_scans, 4), 'cpu_s_per_scan': round(cpu / n_scans, 4),
            'bag_bytes_per_scan': int(bag_bytes / n_scans)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scans', type=int, default=20)
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    config = SimConfig()
    rows = [bench_scenario(s, args.scans, args.seed, config) for s in SCENARIOS]
    e2e = bench_end_to_end(args.scans, args.seed, config)
    print(f'VLP-16 at {config.azimuth_step_deg} deg ({rows[0]["rays_per_scan"]} rays/sweep), '
          f'{args.scans} sweeps per scenario, seed {args.seed}, one thread')
    print(f'{"scenario":9s} {"wall med":>9s} {"wall p95":>9s} {"cpu med":>8s} {"cpu p95":>8s} '
          f'{"points":>7s}')
    for r in rows:
        print(f'{r["scenario"]:9s} {r["wall_s_per_scan_median"]:9.3f} '
              f'{r["wall_s_per_scan_p95"]:9.3f} {r["cpu_s_per_scan_median"]:8.3f} '
              f'{r["cpu_s_per_scan_p95"]:8.3f} {r["points_per_scan_median"]:7d}')
    print(f'end to end (simulate + encode + write ros2 bag): {e2e["wall_s_per_scan"]:.3f} s wall,'
          f' {e2e["cpu_s_per_scan"]:.3f} s cpu per sweep, {e2e["bag_bytes_per_scan"]} bytes/sweep')
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({
        'benchmark': 'bench_sim',
        'machine': {'python': platform.python_version(), 'processor': platform.processor(),
                    'cpu_count': os.cpu_count(), 'load_avg_1min': os.getloadavg()[0]},
        'config': {'azimuth_step_deg': config.azimuth_step_deg,
                   'max_range_m': config.max_range_m, 'n_rows': config.n_rows},
        'scenarios': rows,
        'end_to_end': e2e,
    }, indent=2) + '\n')
    print(f'wrote {RESULTS}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
