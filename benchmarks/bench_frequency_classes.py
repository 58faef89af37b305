"""Does a point's graph frequency tell what it hit? Each definition the package keeps, labelled.

The simulator labels every return (ground / trunk / canopy / other: posts, pipes, sheds,
vehicles). For each frequency the package offers (a definition of `frequency.REGISTRY` on a
graph, with the scan-line graph's two edge weights) on varied orchards (`simulate --vary`),
on training seeds and on held-out ones, it reports:
- the mutual information between band and class, in bits, over all points and within each
  decile of range (a frequency that only reads the range tells the class through it);
- the correlation of nu with the log range;
- the balanced accuracy of the best threshold on nu for trunk + ground against canopy;
- the share of the most crowded band;
- milliseconds per scan (CPU time of the computing thread, median).

Writes benchmarks/results/frequency_classes.json and prints a table per seed split.

Run: .venv/bin/python benchmarks/bench_frequency_classes.py [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from pathlib import Path

import numpy as np

from gft_odom.core.spectral import SpectralConfig, SpectralFilter
from gft_odom.sim.simulator import ScanSimulator, SimConfig

RESULTS = Path(__file__).parent / 'results' / 'frequency_classes.json'
CLASSES = ('ground', 'trunk', 'canopy', 'other')
# (label, SpectralConfig changes): every frequency the package offers.
FREQUENCIES = (
    ('ldos_mean, scan-line, distance', {'method': 'ldos_mean', 'graph': 'scan_line',
                                        'scan_line_weight': 'distance'}),
    ('ldos_mean, scan-line, range_slope', {'method': 'ldos_mean', 'graph': 'scan_line',
                                           'scan_line_weight': 'range_slope'}),
    ('ldos_mean, slice', {'method': 'ldos_mean', 'graph': 'slice'}),
    ('signal, slice (the paper)', {'method': 'signal', 'graph': 'slice'}),
    ('signal, scan-line', {'method': 'signal', 'graph': 'scan_line'}),
)
RANGE_DECILES = 10


def surface_class(surface: np.ndarray) -> np.ndarray:
    """Simulator surface code -> 0 ground, 1 trunk, 2 canopy, 3 other."""
    surface = np.asarray(surface, dtype=np.int64)
    return np.where(surface <= 2, surface, 3)


def mutual_information_bits(band: np.ndarray, cls: np.ndarray) -> float:
    """I(band; class) from the joint histogram, in bits."""
    if band.size == 0:
        return 0.0
    _, b = np.unique(band, return_inverse=True)
    joint = np.zeros((b.max() + 1, len(CLASSES)))
    np.add.at(joint, (b, cls), 1.0)
    joint /= joint.sum()
    outer = joint.sum(axis=1, keepdims=True) @ joint.sum(axis=0, keepdims=True)
    nz = joint > 0
    return float(np.sum(joint[nz] * np.log2(joint[nz] / outer[nz])))


def mutual_information_within_range_bits(band: np.ndarray, cls: np.ndarray,
                                         range_m: np.ndarray) -> float:
    """I(band; class | range decile): the information left once the range is known."""
    edges = np.quantile(range_m, np.linspace(0.0, 1.0, RANGE_DECILES + 1))
    decile = np.clip(np.searchsorted(edges, range_m, side='right') - 1, 0, RANGE_DECILES - 1)
    return float(sum(np.mean(decile == d) * mutual_information_bits(band[decile == d],
                                                                     cls[decile == d])
                     for d in range(RANGE_DECILES)))


def best_threshold_balanced_accuracy(nu: np.ndarray, cls: np.ndarray) -> float:
    """Best balanced accuracy of `nu < t` (either direction) for trunk + ground vs canopy."""
    sel = np.isfinite(nu) & (cls <= 2)
    positive = cls[sel] <= 1
    values = nu[sel]
    if positive.all() or not positive.any():
        return float('nan')
    order = np.argsort(values, kind='stable')
    pos_sorted = positive[order]
    sorted_values = values[order]
    # Thresholds only between distinct values (ties fall on one side together), plus "none".
    cut = np.r_[np.flatnonzero(sorted_values[1:] != sorted_values[:-1]), len(values) - 1]
    tpr_below = np.r_[0.0, (np.cumsum(pos_sorted) / pos_sorted.sum())[cut]]
    tnr_above = np.r_[1.0, (1.0 - np.cumsum(~pos_sorted) / (~pos_sorted).sum())[cut]]
    bal = 0.5 * (tpr_below + tnr_above)
    return float(max(bal.max(), (1.0 - bal).max()))


def make_scans(routes, seeds, indices, azimuth_step_deg):
    """Labelled scans of varied drives, cropped as the pipeline crops them: (Scan, class)."""
    scans = []
    for seed in seeds:
        for route in routes:
            sim, _ = ScanSimulator.for_drive(SimConfig(azimuth_step_deg=azimuth_step_deg),
                                             route, seed, distance_m=120.0, vary=True)
            for k in indices:
                sim_scan = sim.scan(k)
                r = np.linalg.norm(sim_scan.scan.points_xyz, axis=1)
                keep = (r >= 0.5) & (r <= 60.0)
                scans.append((sim_scan.scan.select(keep), surface_class(sim_scan.surface[keep])))
    return scans


def evaluate(label: str, changes: dict, scans, n_bands: int) -> dict:
    """The figures of one frequency over `scans`."""
    filt = SpectralFilter(dataclasses.replace(SpectralConfig(), n_bands=n_bands, **changes))
    bands, nus, classes, ranges, cpu = [], [], [], [], []
    for scan, cls in scans:
        c = time.thread_time()
        freqs = filt.scan_frequencies(scan, n_bands)
        cpu.append(time.thread_time() - c)
        bands.append(freqs.band)
        nus.append(freqs.nu)
        classes.append(cls)
        ranges.append(np.linalg.norm(scan.points_xyz, axis=1))
    band, nu = np.concatenate(bands), np.concatenate(nus)
    cls, range_m = np.concatenate(classes), np.concatenate(ranges)
    has = np.isfinite(nu)
    return {
        'frequency': label, **changes,
        'mutual_information_bits': mutual_information_bits(band, cls),
        'mutual_information_within_range_bits': mutual_information_within_range_bits(
            band, cls, range_m),
        'correlation_with_log_range': float(np.corrcoef(nu[has], np.log(range_m[has]))[0, 1]),
        'balanced_accuracy_trunk_ground_vs_canopy': best_threshold_balanced_accuracy(nu, cls),
        'largest_band_share': float(np.bincount(band).max() / band.size),
        'no_spectrum_share': float(np.mean(band == 0)),
        'n_scans': len(scans),
        'cpu_ms_median': 1e3 * float(np.median(cpu)),
    }


def table(rows) -> str:
    """Markdown table of the headline figures."""
    lines = ['| frequency | MI [bits] | MI within range deciles [bits] | corr. with log range |'
             ' bal. acc. | largest band | CPU ms |',
             '|---|---:|---:|---:|---:|---:|---:|']
    for r in rows:
        lines.append(f"| {r['frequency']} | {r['mutual_information_bits']:.3f} | "
                     f"{r['mutual_information_within_range_bits']:.3f} | "
                     f"{r['correlation_with_log_range']:+.2f} | "
                     f"{r['balanced_accuracy_trunk_ground_vs_canopy']:.3f} | "
                     f"{100 * r['largest_band_share']:.0f} % | {r['cpu_ms_median']:.1f} |")
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--bands', type=int, default=SpectralConfig().n_bands)
    parser.add_argument('--train-seeds', type=int, nargs='+', default=[111, 112])
    parser.add_argument('--test-seeds', type=int, nargs='+', default=[201, 203, 212, 231])
    parser.add_argument('--routes', nargs='+',
                        default=['lawnmower', 'every_other_row', 'edge_lawnmower'])
    parser.add_argument('--indices', type=int, nargs='+', default=[30, 300, 700])
    parser.add_argument('--quick', action='store_true', help='a few coarse scans')
    parser.add_argument('--out', type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    azimuth = 0.2
    if args.quick:
        args.train_seeds, args.test_seeds = args.train_seeds[:1], args.test_seeds[:1]
        args.routes, args.indices, azimuth = ['lawnmower'], [30], 0.4
    results = {'machine': platform.platform(), 'n_bands': args.bands, 'routes': args.routes,
               'indices': args.indices, 'train_seeds': args.train_seeds,
               'test_seeds': args.test_seeds}
    for split, seeds in (('train', args.train_seeds), ('test', args.test_seeds)):
        t = time.perf_counter()
        scans = make_scans(args.routes, seeds, args.indices, azimuth)
        print(f'{split}: {len(scans)} scans simulated in {time.perf_counter() - t:.0f} s')
        rows = [evaluate(label, changes, scans, args.bands) for label, changes in FREQUENCIES]
        results[split] = rows
        print(f'\n{split} seeds {seeds}, routes {args.routes}:')
        print(table(rows))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1))
    print(f'\nwrote {args.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
