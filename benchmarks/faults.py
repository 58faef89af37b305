"""Fault injection table: every case of gft_odom.bench.faults on simulated drives, the ATE of the
valid scans against the clean drive's, and what happened to the scans.

    .venv/bin/python benchmarks/faults.py [--seeds 21 22 23] [--scans 70] [--json out.json]

The same cases are tests (test/robustness/test_fault_injection.py); this prints the figures
for docs/robustness.md over several seeds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

import numpy as np

from gft_odom.bench.faults import CASES, run_case
from gft_odom.config import GftOdomConfig
from gft_odom.io.bags import ScanBagReader
from gft_odom.io.tum import read_tum
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[21, 22, 23])
    parser.add_argument('--scans', type=int, default=70)
    parser.add_argument('--fault-after', type=int, default=12)
    parser.add_argument('--json')
    args = parser.parse_args(argv)
    config = GftOdomConfig()
    rows: dict[str, list[dict]] = {name: [] for name in CASES}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            sim = simulate_to_bag(Path(tmp) / str(seed), scenario='row', n_scans=args.scans,
                                  seed=seed, config=SimConfig(azimuth_step_deg=0.4),
                                  topdown_png=False)
            with ScanBagReader([sim.bag_path]) as reader:
                scans = list(reader)
            truth = read_tum(sim.gt_tum_path).poses
            for name in CASES:
                result = run_case(name, scans, truth, config, args.fault_after)
                row = {k: v for k, v in dataclasses.asdict(result).items() if k != 'results'}
                row['statuses'] = dict(result.statuses)
                row['seed'] = seed
                rows[name].append(row)
                print(f'seed {seed} {name:24s} ATE {result.ate_m:8.3f} m  valid registered '
                      f'{result.n_valid_registered}/{result.n_valid}  {dict(result.statuses)}',
                      flush=True)
    print('\n| case | ATE RMSE of the valid scans [m], median over seeds | max | valid '
          'scans registered | statuses (all seeds) |')
    print('|---|---:|---:|---:|---|')
    for name, per_seed in rows.items():
        ates = [r['ate_m'] for r in per_seed]
        statuses: dict[str, int] = {}
        for r in per_seed:
            for k, v in r['statuses'].items():
                statuses[k] = statuses.get(k, 0) + v
        print(f'| {name} | {np.median(ates):.3f} | {np.max(ates):.3f} | '
              f'{sum(r["n_valid_registered"] for r in per_seed)}/'
              f'{sum(r["n_valid"] for r in per_seed)} | '
              + ', '.join(f'{k} {v}' for k, v in sorted(statuses.items())) + ' |')
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
