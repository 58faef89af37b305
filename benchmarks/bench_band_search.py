"""Band search throughput (masks per hour, 1 and N workers) and smart vs exhaustive.

Throughput: simulate one sequence of --scans scans, build its frequency cache (timed), then
evaluate the same --masks masks in-process (1 worker) and with a process pool of each
--workers count; masks/hour = masks / wall time * 3600 for that sequence length.

Smart vs exhaustive (--exhaustive-dir DIR, a finished `search-bands` folder): the smart
search is replayed on a copy of the folder, so every mask it asks for is looked up in the
exhaustive results; it reports how many masks it needed and how close its best is.

    .venv/bin/python benchmarks/bench_band_search.py --scans 300 --masks 6 --workers 1 2
    .venv/bin/python benchmarks/bench_band_search.py --exhaustive-dir OUT --smart-max-bands 6
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gft_odom.bands.cache import SequenceCache, build_sequence_cache
from gft_odom.bands.evaluate import BASELINE_KEY, score
from gft_odom.bands.executors import InProcessExecutor, ProcessPoolMaskExecutor
from gft_odom.bands.masks import exhaustive_masks, mask_key
from gft_odom.bands.search import BandSearch, BandSearchConfig
from gft_odom.config import GftOdomConfig, with_values
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag


def throughput(args) -> dict:
    config = with_values(GftOdomConfig(), {'registration.mode': args.mode})
    work = Path(tempfile.mkdtemp(prefix='bench_bands_'))
    try:
        t = time.perf_counter()
        sim = simulate_to_bag(work / 'sim', scenario=args.scenario, n_scans=args.scans,
                              seed=args.seed, config=SimConfig(azimuth_step_deg=args.azimuth),
                              topdown_png=False)
        sim_s = time.perf_counter() - t
        t = time.perf_counter()
        cache = build_sequence_cache([sim.bag_path], sim.gt_csv_path, config,
                                     range(args.min_bands, args.max_bands + 1), name='bench')
        cache_s = time.perf_counter() - t
        cache_path = cache.save(work / 'bench.npz')
        rng = np.random.default_rng(args.seed)
        masks = exhaustive_masks(args.min_bands, args.max_bands)
        pick = rng.choice(len(masks), size=min(args.masks, len(masks)), replace=False)
        keys = [mask_key(masks[i]) for i in pick]
        runs = []
        for workers in args.workers:
            executor = (InProcessExecutor([cache], config) if workers == 1 else
                        ProcessPoolMaskExecutor([cache_path], config, workers))
            t = time.perf_counter()
            rows = list(executor.run(keys))
            wall = time.perf_counter() - t
            executor.close()
            runs.append({'workers': workers, 'masks': len(rows), 'wall_s': round(wall, 2),
                         'masks_per_hour': round(len(rows) / wall * 3600.0, 1),
                         'mean_eval_s': round(float(np.mean([r['eval_s'] for r in rows])), 3),
                         'load_avg_1min_after': round(os.getloadavg()[0], 2)})
            print(json.dumps(runs[-1]), flush=True)
        return {'scans': len(cache), 'scenario': args.scenario, 'seed': args.seed,
                'azimuth_step_deg': args.azimuth, 'registration_mode': args.mode,
                'points_per_scan_mean': float(np.diff(cache.offsets).mean()),
                'simulate_s': round(sim_s, 1), 'frequency_cache_s': round(cache_s, 1),
                'frequency_cache_s_per_scan': round(cache_s / len(cache), 3),
                'band_counts_cached': [args.min_bands, args.max_bands], 'masks': keys,
                'runs': runs}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def smart_vs_exhaustive(args) -> dict:
    src = Path(args.exhaustive_dir)
    meta = json.loads((src / 'search.json').read_text())
    results = [json.loads(x) for x in (src / 'results.jsonl').read_text().splitlines()]
    exhaustive = {r['key']: r for r in results}
    mode = meta['registration_mode']
    config = with_values(GftOdomConfig(), {'registration.mode': mode})
    work = Path(tempfile.mkdtemp(prefix='bench_smart_'))
    try:
        shutil.copytree(src, work / 'copy')
        caches_dir = work / 'copy' / 'cache'
        # The copy's results are the exhaustive search's own: no key check against today's
        # defaults (a parameter added since then would refuse them).
        (work / 'copy' / 'search.json').unlink()
        caches = [SequenceCache.load(caches_dir / f'{n}.npz') for n in meta['train']]
        search = BandSearch(caches, config, work / 'copy', [caches_dir / f'{n}.npz'
                                                             for n in meta['train']])
        cfg = BandSearchConfig(min_bands=args.min_bands, max_bands=args.smart_max_bands,
                               strategy='smart', smart_seed_max_bands=args.seed_max_bands,
                               beam_width=args.beam_width)
        rows = search.smart(cfg)
        search.close()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    ex_masks = [r for r in exhaustive.values() if r['key'] != BASELINE_KEY
                and args.min_bands <= r['n_bands'] <= args.smart_max_bands]
    ex_best = min(ex_masks, key=score)
    sm_masks = [r for r in rows.values() if r['key'] != BASELINE_KEY]
    sm_best = min(sm_masks, key=score)
    return {'registration_mode': mode, 'train': meta['train'],
            'bands': [args.min_bands, args.smart_max_bands],
            'exhaustive_evaluations': len(ex_masks),
            'exhaustive_unique_evaluations': sum(1 for r in ex_masks
                                                 if not r.get('duplicate_of')),
            'exhaustive_best': ex_best['key'], 'exhaustive_best_ate_rmse_m': score(ex_best),
            'smart_evaluations': len(sm_masks),
            'smart_unique_evaluations': sum(1 for r in sm_masks if not r.get('duplicate_of')),
            'smart_best': sm_best['key'], 'smart_best_ate_rmse_m': score(sm_best),
            'smart_gap_pct': 100.0 * (score(sm_best) - score(ex_best)) / score(ex_best),
            'smart_rank_in_exhaustive': 1 + sum(score(r) < score(sm_best) for r in ex_masks
                                                if not r.get('duplicate_of')),
            'baseline_ate_rmse_m': score(exhaustive[BASELINE_KEY])}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--scans', type=int, default=300)
    p.add_argument('--masks', type=int, default=6)
    p.add_argument('--workers', type=int, nargs='+', default=[1, 2])
    p.add_argument('--mode', default='paper', choices=('paper', 'default'))
    p.add_argument('--scenario', default='row')
    p.add_argument('--seed', type=int, default=21)
    p.add_argument('--azimuth', type=float, default=0.2, help='sim azimuth step, deg')
    p.add_argument('--min-bands', type=int, default=2)
    p.add_argument('--max-bands', type=int, default=10)
    p.add_argument('--exhaustive-dir', help='finished search folder: run smart vs exhaustive')
    p.add_argument('--smart-max-bands', type=int, default=6)
    p.add_argument('--seed-max-bands', type=int, default=3)
    p.add_argument('--beam-width', type=int, default=2)
    p.add_argument('--out', default='benchmarks/results/band_search.json')
    args = p.parse_args(argv)
    out = Path(args.out)
    report = json.loads(out.read_text()) if out.exists() else {}
    report['machine'] = {'python': platform.python_version(), 'cpu_count': os.cpu_count()}
    if args.exhaustive_dir:
        result = smart_vs_exhaustive(args)
        report.setdefault('smart_vs_exhaustive', {})[result['registration_mode']] = result
    else:
        result = throughput(args)
        report.setdefault('throughput', {})[f'{args.mode}_{result["scans"]}scans'] = result
    print(json.dumps(result, indent=2))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
