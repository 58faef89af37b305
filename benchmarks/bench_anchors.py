"""A keyframe's map update against the number of anchors a long run has accumulated.

The local map keeps anchors (points of keyframes that left the window) for the whole run, up to
ANCHOR_MAX_POINTS (2M). This times `LocalMap.add_keyframe` (the merge, the crop and the map's
normals) in a synthetic window of
60 keyframes of 3 000 points on a line of poses, with N anchors spread over a 2 km x 200 m
farm, and the anchoring of a leaving keyframe apart. Median of the keyframes after the window
filled, per N. Same process, same machine: compare the rows, not other runs.

Prints a table and writes benchmarks/results/anchors.json.

Run: .venv/bin/python benchmarks/bench_anchors.py [--anchors 0 100000 500000 2000000]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from gft_odom.bench.report import machine_info
from gft_odom.core.registration.local_map import LocalMap
from gft_odom.core.registration.voxels import voxel_keys

RESULTS = Path(__file__).resolve().parent / 'results' / 'anchors.json'


def time_updates(n_anchors: int, keyframes: int = 80, seed: int = 0) -> dict:
    """Median / p95 ms of add_keyframe and of its anchoring, with `n_anchors` in the map."""
    rng = np.random.default_rng(seed)
    local_map = LocalMap(0.3, 40.0, 80_000, 60, 1.0)
    if n_anchors:
        farm = rng.uniform([-1000.0, -100.0, -1.0], [1000.0, 100.0, 3.0], (n_anchors, 3))
        keys, first = np.unique(voxel_keys(farm, 0.3), return_index=True)
        local_map._anchors.add(keys, farm[first], np.ones(first.shape[0]),
                               farm[first] + [0.0, 0.0, 1.0])
    total, anchoring = [], []
    anchor = local_map._anchor

    def timed_anchor(*args):
        t0 = time.perf_counter()
        anchor(*args)
        anchoring.append(time.perf_counter() - t0)

    local_map._anchor = timed_anchor
    for i in range(keyframes):
        T = np.eye(4)
        T[0, 3] = float(i)
        points = rng.uniform([-20.0, -20.0, -1.0], [20.0, 20.0, 3.0], (3000, 3)) + T[:3, 3]
        t0 = time.perf_counter()
        local_map.add_keyframe(points, T, rng.uniform(0.0, 1.0, 3000))
        total.append(time.perf_counter() - t0)
    steady = np.array(total[60:]) * 1e3
    return {'anchors': len(local_map._anchors), 'served_points': len(local_map),
            'update_median_ms': float(np.median(steady)),
            'update_p95_ms': float(np.percentile(steady, 95)),
            'anchoring_median_ms': float(np.median(anchoring) * 1e3) if anchoring else 0.0}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--anchors', type=int, nargs='*', default=[0, 100_000, 500_000, 2_000_000])
    p.add_argument('--out', type=Path, default=RESULTS)
    args = p.parse_args(argv)
    rows = [time_updates(n) for n in args.anchors]
    print('| anchors | map update median / p95 [ms] | of which anchoring [ms] |')
    print('|---:|---:|---:|')
    for r in rows:
        print(f"| {r['anchors']} | {r['update_median_ms']:.1f} / {r['update_p95_ms']:.1f} | "
              f"{r['anchoring_median_ms']:.1f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({'rows': rows, 'machine': machine_info()}, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
