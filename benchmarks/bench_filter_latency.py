"""What the spectral stage costs inside the pipeline, configurations interleaved scan by scan.

On a shared machine timings drift by factors within minutes, so every configuration processes
the same scan back to back (in rotating order) and each gets its own pipeline (its own
registration state). Per configuration: the median and p95 of the filter stage, the
registration stage and the whole pipeline (wall), the ratio filter / register, the points
kept, and the ATE of the run.

Default configurations: the unfiltered pipeline, the package default (frequencies on every
scan, all-pass mask), and the masks named with --mask (n_bands:band,band,...).

    .venv/bin/python benchmarks/bench_filter_latency.py BAG SENSOR_TUM [--mask 3:1 --scans 120]

SENSOR_TUM: the sensor's true poses (the simulator's ground_truth/gt_sensor_tum.txt).

Writes benchmarks/results/filter_latency.json.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np

from gft_odom.config import GftOdomConfig, with_values
from gft_odom.core.metrics import evaluate
from gft_odom.io.bags import ScanBagReader
from gft_odom.io.ground_truth import read_ground_truth
from gft_odom.pipeline import OdometryPipeline

RESULTS = Path(__file__).parent / 'results' / 'filter_latency.json'


def configurations(masks: list[str]) -> dict[str, GftOdomConfig]:
    """Name -> config: unfiltered, the default, and each `B:b1,b2` mask."""
    base = GftOdomConfig()
    out = {'unfiltered': with_values(base, {'pipeline.use_spectral_filter': False}),
           'default (all-pass, frequencies computed)': base}
    for spec in masks:
        n_bands, bands = spec.split(':')
        out[f'B={n_bands} {bands}'] = with_values(base, {
            'spectral.n_bands': int(n_bands),
            'spectral.band_mask': [int(b) for b in bands.split(',')]})
    return out


def stats(values_s: list[float]) -> dict:
    """Median and p95 in ms."""
    ms = 1e3 * np.asarray(values_s)
    return {'median_ms': float(np.median(ms)), 'p95_ms': float(np.percentile(ms, 95))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('bag')
    parser.add_argument('gt', help='TUM file of the true sensor poses')
    parser.add_argument('--mask', action='append', default=[], help='B:b1,b2,... (repeat)')
    parser.add_argument('--scans', type=int, default=120)
    parser.add_argument('--out', type=Path, default=RESULTS)
    args = parser.parse_args()
    with ScanBagReader(args.bag) as reader:
        scans = [s for _, s in zip(range(args.scans), reader)]
    configs = configurations(args.mask)
    pipelines = {name: OdometryPipeline(cfg) for name, cfg in configs.items()}
    names = list(pipelines)
    timings = {n: {'filter': [], 'register': [], 'pipeline': [], 'kept': []} for n in names}
    for k, scan in enumerate(scans):
        for name in names[k % len(names):] + names[:k % len(names)]:
            result = pipelines[name].register_frame(scan)
            pipelines[name].update_map()  # the frequencies, when they come after the pose
            t = timings[name]
            for stage in ('filter', 'register', 'pipeline'):
                t[stage].append(result.timings_s[stage])
            t['kept'].append(result.n_points_kept / max(result.n_points_in, 1))
    gt = read_ground_truth(args.gt)
    out = {'bag': str(args.bag), 'scans': len(scans), 'machine': platform.platform(),
           'configs': {}}
    for name in names:
        t = timings[name]
        ate_m = evaluate(pipelines[name].sensor_trajectory(), gt, mode='position')['ate_rmse_m']
        row = {stage: stats(t[stage]) for stage in ('filter', 'register', 'pipeline')}
        row['filter_over_register'] = (row['filter']['median_ms']
                                       / max(row['register']['median_ms'], 1e-9))
        row['points_kept'] = float(np.mean(t['kept']))
        row['ate_rmse_m'] = float(ate_m)
        out['configs'][name] = row
        print(f"{name:42s} filter {row['filter']['median_ms']:6.1f} ms, register "
              f"{row['register']['median_ms']:6.1f}, pipeline "
              f"{row['pipeline']['median_ms']:6.1f} / p95 "
              f"{row['pipeline']['p95_ms']:6.1f} ms  filter/register "
              f"{row['filter_over_register']:.2f}  kept {100 * row['points_kept']:.0f} %  "
              f"ATE {row['ate_rmse_m']:.4f} m")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    print(f'wrote {args.out}')


if __name__ == '__main__':
    main()
