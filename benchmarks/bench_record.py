"""Benchmark of record: gft_odom against its peers on long, varied, held-out drives.

Usage:
  .venv/bin/python benchmarks/bench_record.py
      [--drives record|never-used|edge|stress|training]
      [--jobs N] [--cache DIR] [--only LABEL ...] [--names DRIVE ...]
      [--ablation] [--fresh | --cached-only] [--out benchmarks/results]

Simulates the drives once into the cache (`~/.cache/gft_odom/drives` or $GFT_ODOM_DRIVES;
~0.1 s per full-resolution scan, ~4 min a drive on one core), then runs every entry on every
drive and writes record_<drives>.json / .md and record_<drives>_ate_over_distance.png.
`--ablation` runs the frequency's controls instead: the same registration without
frequencies (--no-filter) and with each scan's frequencies shuffled among its points.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from gft_odom.bench.drives import (
    EDGE_DRIVES,
    NEVER_USED_DRIVES,
    RECORD_DRIVES,
    STRESS_DRIVES,
    TRAINING_DRIVES,
    default_cache_dir,
    ensure_drives,
)
from gft_odom.bench.record import Entry, run_record, write_record
from gft_odom.bench.report import machine_info

RESULTS = Path(__file__).resolve().parent / 'results'
# --drives: the drive set by name (its results go to <kind>_<name>.*).
DRIVE_SETS = {'record': RECORD_DRIVES, 'never-used': NEVER_USED_DRIVES, 'edge': EDGE_DRIVES,
              'stress': STRESS_DRIVES, 'training': TRAINING_DRIVES}

# The package as users run it, then every LiDAR-only peer with its own defaults (GenZ-ICP
# with its deskew and as it ships, deskew off), each stamped where its pose holds.
ENTRIES = (
    Entry('gft_odom', 'default+gft'),
    Entry('kiss-icp', 'kiss-icp'),
    Entry('GenZ-ICP', 'genz-icp'),
    Entry('GenZ-ICP, no deskew (as shipped)', 'genz-icp-no-deskew'),
    Entry('CT-ICP', 'ct-icp'),
    Entry('MAD-ICP', 'mad-icp'),
    Entry('FORM', 'form'),
    Entry('LOAM', 'loam'),
)
# The frequency's controls: the same registration without frequencies, and with each scan's
# frequencies shuffled among its points (three permutations: the control's spread).
ABLATION_ENTRIES = (
    Entry('gft_odom', 'default+gft'),
    Entry('no frequency (--no-filter)', 'default'),
) + tuple(Entry(f'shuffled frequency (seed {seed})', 'default+gft',
                (('pipeline.shuffle_frequencies', True), ('pipeline.shuffle_seed', seed)))
          for seed in (0, 1, 2))


def main(argv=None) -> int:
    """Simulate what is missing, run the record, write its results."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--drives', choices=tuple(DRIVE_SETS), default='record')
    p.add_argument('--cache', type=Path, default=None,
                   help=f'simulated drives (default {default_cache_dir()})')
    p.add_argument('--jobs', type=int, default=2, help='processes (simulation and methods)')
    p.add_argument('--only', nargs='*', default=None, help='entry labels to run')
    p.add_argument('--fresh', action='store_true',
                   help='measure every pair again (default: reuse results kept in the cache)')
    p.add_argument('--cached-only', action='store_true',
                   help='report the pairs already measured in the cache, measure nothing')
    p.add_argument('--ablation', action='store_true',
                   help="the frequency's controls instead of the record entries")
    p.add_argument('--names', nargs='*', default=None,
                   help='only these drives of the set (e.g. lawnmower-111 spiral-112)')
    p.add_argument('--out', type=Path, default=RESULTS)
    args = p.parse_args(argv)
    drives = [d for d in DRIVE_SETS[args.drives] if args.names is None or d.name in args.names]
    if not drives:
        p.error(f'no drive of {args.drives} matches --names {args.names}')
    pool = ABLATION_ENTRIES if args.ablation else ENTRIES
    entries = [e for e in pool if args.only is None or e.label in args.only]
    if not entries:
        p.error(f'no entry matches --only {args.only}; labels: {[e.label for e in pool]}')
    t0 = time.perf_counter()
    sequences = ensure_drives(drives, args.cache, jobs=args.jobs,
                              progress=lambda name: print(f'simulated {name}', flush=True))
    t_sim = time.perf_counter() - t0
    record = run_record(entries, sequences, jobs=args.jobs,
                        progress=lambda label, drive: print(f'{label} on {drive}', flush=True),
                        cache_dir=None if args.fresh else
                        (args.cache or default_cache_dir()) / 'record_runs',
                        cached_only=args.cached_only)
    settings = {'drives': args.drives, 'jobs': args.jobs, 'simulate_s': t_sim,
                'methods_s': time.perf_counter() - t0 - t_sim, 'machine': machine_info()}
    kind = 'ablation' if args.ablation else 'record'
    stem = f'{kind}_{args.drives}' + ('_' + '_'.join(args.names) if args.names else '')
    paths = write_record(record, args.out, settings, stem=stem)
    print(paths['markdown'].read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main())
