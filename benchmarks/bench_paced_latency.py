"""Latency at the sensor's rate, measured: each scan handed over when its stamp says it
arrives, one method at a time, in rounds whose order alternates.

The record's latency at the sensor's rate is a model (`replay.latency_at_rate_s`: one worker,
the scans queued behind the work before them). This benchmark replays a cached drive in real
time instead (`run_method(..., paced=True)`): the latency of a scan runs from its arrival to its
pose, kiss-icp in the same rounds.

    .venv/bin/python benchmarks/bench_paced_latency.py --drive lawnmower-211 --rounds 2

Run it on a quiet machine (nothing else on the cores). Writes
benchmarks/results/paced_latency_<drive>.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from gft_odom.bench.drives import default_cache_dir, ensure_drives
from gft_odom.bench.record import Entry
from gft_odom.bench.report import machine_info
from gft_odom.bench.runner import run_method
from gft_odom.config import GftOdomConfig
from gft_odom.io.atomic import write_text_atomic

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_record import DRIVE_SETS, RESULTS  # noqa: E402

ENTRIES = (Entry('gft_odom', 'default+gft'), Entry('kiss-icp', 'kiss-icp'))
FIGURES = ('latency_median_ms', 'latency_p95_ms', 'ate_rmse_m', 'fallbacks')


def main(argv=None) -> int:
    """Each entry on the drive, paced, `rounds` times; the figures of each run and a table."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    drives = {d.name: d for ds in DRIVE_SETS.values() for d in ds}
    p.add_argument('--drive', choices=sorted(drives), default='lawnmower-211')
    p.add_argument('--rounds', type=int, default=2)
    p.add_argument('--max-scans', type=int, default=None)
    p.add_argument('--only', nargs='*', default=None, help='entry labels to run')
    p.add_argument('--cache', type=Path, default=None,
                   help=f'simulated drives (default {default_cache_dir()})')
    p.add_argument('--out', type=Path, default=RESULTS)
    args = p.parse_args(argv)
    entries = [e for e in ENTRIES if args.only is None or e.label in args.only]
    if not entries or args.rounds < 1:
        p.error(f'need --rounds >= 1 and an entry of {[e.label for e in ENTRIES]}')
    sequence, = ensure_drives([drives[args.drive]], args.cache)
    base = GftOdomConfig()
    runs = []
    for round_index in range(args.rounds):
        for entry in entries if round_index % 2 == 0 else entries[::-1]:
            t0 = time.perf_counter()
            run = run_method(entry.method, sequence, entry.config(base),
                             max_scans=args.max_scans, paced=True)
            figures = {k: run.metrics.get(k) for k in FIGURES}
            over = float(np.mean(1e3 * run.replay.latency_s > 100.0))
            runs.append({'label': entry.label, 'round': round_index,
                         'scans': int(run.replay.latency_s.size), 'share_over_100ms': over,
                         'wall_s': time.perf_counter() - t0, **figures})
            print(f"round {round_index} {entry.label}: median {figures['latency_median_ms']:.1f}"
                  f" ms, p95 {figures['latency_p95_ms']:.1f} ms, {100 * over:.1f} % over "
                  f"100 ms, ATE {figures['ate_rmse_m']}", flush=True)
    out = args.out / f'paced_latency_{args.drive}.json'
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, json.dumps({'drive': args.drive, 'max_scans': args.max_scans,
                                       'machine': machine_info(), 'runs': runs}, indent=2))
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
