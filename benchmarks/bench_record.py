"""Benchmark of record: gft_odom against its peers on long, varied, held-out drives.

Usage:
  .venv/bin/python benchmarks/bench_record.py [--drives held-out|training] [--jobs N]
      [--cache DIR] [--only LABEL ...] [--out benchmarks/results]

Simulates the drives once into the cache (`~/.cache/gft_odom/drives` or $GFT_ODOM_DRIVES;
~0.09 s per full-resolution scan, so the 7 held-out drives, ~2.4 km / ~24k scans, take ~35 min
on one core), then runs every entry on every drive and writes record_<drives>.json / .md and
record_<drives>_ate_over_distance.png. The methods take ~1 h more on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from gft_odom.bench.drives import (
    HELD_OUT_DRIVES,
    TRAINING_DRIVES,
    default_cache_dir,
    ensure_drives,
)
from gft_odom.bench.record import Entry, run_record, write_record
from gft_odom.bench.report import machine_info

RESULTS = Path(__file__).resolve().parent / 'results'

# Our package as users run it (config/filter_odom.yaml = the dataclass defaults), then peers.
ENTRIES = (
    Entry('gft_odom', 'default+gft'),
    Entry('kiss-icp', 'kiss-icp'),
)

# The drift study (docs/benchmarks.md): candidate changes to the default, run on the TRAINING
# drives only; the held-out record then reports the one chosen against the old default.
_DESKEW = ('registration.deskew', True)
_LONG_MAP = (('registration.map_keyframes', 60), ('registration.map_max_points', 80000))
STUDY_ENTRIES = (
    Entry('default', 'default+gft'),
    Entry('deskew', 'default+gft', (_DESKEW,)),
    Entry('map 60 keyframes', 'default+gft', _LONG_MAP),
    Entry('deskew + map 60 keyframes', 'default+gft', (_DESKEW,) + _LONG_MAP),
    Entry('deskew + ldos B4 [1]', 'default+gft',
          (_DESKEW, ('spectral.n_bands', 4), ('spectral.band_mask', [1]))),
)


def main(argv=None) -> int:
    """Simulate what is missing, run the record, write its results."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--drives', choices=('held-out', 'training'), default='held-out')
    p.add_argument('--cache', type=Path, default=None,
                   help=f'simulated drives (default {default_cache_dir()})')
    p.add_argument('--jobs', type=int, default=2, help='processes (simulation and methods)')
    p.add_argument('--only', nargs='*', default=None, help='entry labels to run')
    p.add_argument('--study', action='store_true',
                   help='the drift-study candidates instead of the record entries')
    p.add_argument('--out', type=Path, default=RESULTS)
    args = p.parse_args(argv)
    drives = HELD_OUT_DRIVES if args.drives == 'held-out' else TRAINING_DRIVES
    pool = STUDY_ENTRIES if args.study else ENTRIES
    entries = [e for e in pool if args.only is None or e.label in args.only]
    if not entries:
        p.error(f'no entry matches --only {args.only}; labels: {[e.label for e in pool]}')
    t0 = time.perf_counter()
    sequences = ensure_drives(drives, args.cache, jobs=args.jobs,
                              progress=lambda name: print(f'simulated {name}', flush=True))
    t_sim = time.perf_counter() - t0
    record = run_record(entries, sequences, jobs=args.jobs,
                        progress=lambda label, drive: print(f'{label} on {drive}', flush=True))
    settings = {'drives': args.drives, 'jobs': args.jobs, 'simulate_s': t_sim,
                'methods_s': time.perf_counter() - t0 - t_sim, 'machine': machine_info()}
    stem = f'{"study" if args.study else "record"}_{args.drives}'
    paths = write_record(record, args.out, settings, stem=stem)
    print(paths['markdown'].read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main())
