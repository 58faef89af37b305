"""Speed and agreement of the spectral filter's paper path (`signal` on the slice graph).

Prints the figures and writes them to benchmarks/results/spectral.json:
- median / p95 time per scan of the fast path (Chebyshev) and of the exact path (dense eigh on
  slices of up to EXACT_MAX_BLOCK_NODES graph nodes, Chebyshev above);
- agreement fast vs exact (fraction of points with the same band, on exact-sized slices) and
  how it varies with the Chebyshev order K;
- lambda_max: batched Lanczos vs ARPACK;
- points kept per band (single-band masks) and for a few masks.

The package default (`ldos_mean` on the scan-line graph: exact, no expansion) is measured by
bench_frequency_classes.py. Scans: the project simulator's `row` run (VLP-16 at 0.2 deg).

Run: .venv/bin/python benchmarks/bench_spectral.py [--scans 12] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from pathlib import Path

import numpy as np

from gft_odom.core.spectral import BandMask, SpectralConfig, SpectralFilter
from gft_odom.core.spectral.chebyshev import lambda_max_per_slice
from gft_odom.core.spectral.filter import LANCZOS_ITERATIONS, SLICE_NODE_M
from gft_odom.core.spectral.frequency import EXACT_MAX_BLOCK_NODES
from gft_odom.core.spectral.graph import gaussian_graph, laplacian
from gft_odom.core.spectral.slicing import slice_points, voxelise
from gft_odom.sim import ScanSimulator, SimConfig, generate_orchard, make_motion
from gft_odom.sim.motion import required_row_length_m

RESULTS = Path(__file__).parent / 'results' / 'spectral.json'


def load_scans(n_scans: int, stride: int = 10) -> tuple[list[np.ndarray], str]:
    """Every `stride`-th sweep of the project simulator's `row` run (VLP-16, 0.2 deg)."""
    config = SimConfig()
    duration_s = (n_scans * stride + 1) / config.scan_rate_hz
    orchard = generate_orchard(0, n_rows=config.n_rows, row_length_m=required_row_length_m(
        'row', duration_s * config.speed_mps))
    motion = make_motion(orchard, 'row', duration_s, config.speed_mps, 0,
                         config.lateral_wobble_m, config.yaw_wobble_rad)
    sim = ScanSimulator(orchard, motion, config, 0)
    scans = [sim.scan(k * stride).scan.points_xyz for k in range(n_scans)]
    return scans, f'gft_odom.sim ScanSimulator, row scenario, seed 0, every {stride}th sweep'


# -- measurements -----------------------------------------------------------------------------

def _stats_ms(times_s: list[float]) -> dict:
    t = np.asarray(times_s) * 1e3
    return {'median_ms': float(np.median(t)), 'p95_ms': float(np.percentile(t, 95)),
            'mean_ms': float(t.mean()), 'n': int(t.size)}


def time_path(scans, cfg: SpectralConfig, repeats: int = 1) -> tuple[dict, dict]:
    """Wall and CPU time per scan (the machine is shared: CPU time is the steadier figure)."""
    filt = SpectralFilter.from_config(cfg)
    filt.apply(scans[0])  # warm-up
    totals, cpu, stages = [], [], {}
    for _ in range(repeats):
        for pts in scans:
            c = time.process_time()
            res = filt.apply(pts)
            cpu.append(time.process_time() - c)
            totals.append(res.timings_s['total'])
            for k, v in res.timings_s.items():
                stages.setdefault(k, []).append(v)
    out = _stats_ms(totals)
    out['cpu'] = _stats_ms(cpu)
    return out, {k: float(np.median(v) * 1e3) for k, v in stages.items()}


def _exact_sized(p: np.ndarray, cfg: SpectralConfig) -> np.ndarray:
    """Points whose slice has at most EXACT_MAX_BLOCK_NODES graph nodes."""
    sl = slice_points(p[:, 2], cfg.slice_thickness_m, cfg.z_min_m, cfg.z_max_m)
    _, _, starts, _ = voxelise(p[sl.order, :2], sl.slice_of_point, sl.n_slices, SLICE_NODE_M)
    small = np.zeros(p.shape[0], dtype=bool)
    small[sl.order] = (np.diff(starts) <= EXACT_MAX_BLOCK_NODES)[sl.slice_of_point]
    return small


def agreement(scans, cfg: SpectralConfig, orders) -> dict:
    """Same-band fraction fast vs exact, on points of slices small enough for the exact path."""
    exact = SpectralFilter.from_config(dataclasses.replace(cfg, solver='exact'))
    out = {}
    exact_f = [exact.frequencies(p) for p in scans]
    masks = [_exact_sized(p, cfg) for p in scans]
    for k in orders:
        fast = SpectralFilter.from_config(dataclasses.replace(cfg, chebyshev_order=int(k)))
        same, total, dnu = 0, 0, []
        for p, ef, small in zip(scans, exact_f, masks):
            ff = fast.frequencies(p)
            sel = small & (ef.band > 0)
            same += int(np.sum(ff.band[sel] == ef.band[sel]))
            total += int(sel.sum())
            dnu.append(np.abs(ff.nu[sel] - ef.nu[sel]))
        dnu = np.concatenate(dnu)
        out[int(k)] = {'same_band_fraction': same / max(total, 1), 'points_compared': total,
                       'median_abs_dnu': float(np.median(dnu)),
                       'p95_abs_dnu': float(np.percentile(dnu, 95))}
        print(f'  K={k:3d}: same band {100 * same / max(total, 1):6.2f} % of {total} points, '
              f'|dnu| median {np.median(dnu):.4f} p95 {np.percentile(dnu, 95):.4f}')
    return out


def lambda_max_check(scans, cfg: SpectralConfig) -> dict:
    rel, t_l, t_a = [], [], []
    for p in scans:
        sl = slice_points(p[:, 2], cfg.slice_thickness_m, cfg.z_min_m, cfg.z_max_m)
        xy, node_slice, starts, _ = voxelise(p[sl.order, :2], sl.slice_of_point, sl.n_slices,
                                             SLICE_NODE_M)
        L = laplacian(gaussian_graph(xy, node_slice, cfg.tau_m, cfg.sigma_m))
        t = time.perf_counter()
        la = lambda_max_per_slice(L, starts, 'lanczos', LANCZOS_ITERATIONS)
        t_l.append(time.perf_counter() - t)
        t = time.perf_counter()
        ar = lambda_max_per_slice(L, starts, 'arpack')
        t_a.append(time.perf_counter() - t)
        ok = ar > 0
        rel.append(np.abs(la[ok] - ar[ok]) / ar[ok])
    rel = np.concatenate(rel)
    return {'lanczos': _stats_ms(t_l), 'arpack': _stats_ms(t_a),
            'rel_diff_median': float(np.median(rel)), 'rel_diff_max': float(rel.max())}


def kept_per_band(scans, cfg: SpectralConfig) -> dict:
    filt = SpectralFilter.from_config(cfg)
    freqs = [filt.frequencies(p) for p in scans]
    n_total = sum(len(f) for f in freqs)
    out = {'points_per_scan': n_total / len(scans),
           'band0_isolated': sum(int(f.isolated.sum()) for f in freqs) / n_total,
           'band0_out_of_range': sum(int((~f.in_range).sum()) for f in freqs) / n_total,
           'n_slices_mean': float(np.mean([f.n_slices for f in freqs]))}
    per_band = {}
    for b in range(1, cfg.n_bands + 1):
        per_band[b] = sum(int(np.sum(f.band == b)) for f in freqs) / n_total
    out['fraction_per_band'] = per_band
    masks = {}
    for spec in ('1111111111', '1000000011', '1100000000', '0000000011', '0011111100'):
        m = BandMask.parse(spec, cfg.n_bands)
        kept = sum(int(filt.keep_mask(f, m).sum()) for f in freqs)
        masks[spec] = kept / n_total
    out['kept_fraction_per_mask'] = masks
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scans', type=int, default=12)
    parser.add_argument('--quick', action='store_true', help='fewer scans and orders')
    args = parser.parse_args()
    n_scans = 3 if args.quick else args.scans
    # This benchmark measures the paper's path: `signal` on the slice graph (the package default,
    # `ldos_mean` on the scan-line graph, is measured by bench_frequency_classes.py).
    cfg = SpectralConfig(method='signal', graph='slice')
    scans, source = load_scans(n_scans)
    print(f'scans: {len(scans)} from {source}, '
          f'{np.mean([len(s) for s in scans]):.0f} points each on average')
    results: dict = {'source': source, 'config': dataclasses.asdict(cfg),
                     'machine': {'python': platform.python_version(),
                                 'processor': platform.processor() or platform.machine()}}

    fast, fast_stages = time_path(scans, cfg, repeats=2)
    print(f'fast path (chebyshev K={cfg.chebyshev_order}): median {fast["median_ms"]:.1f} ms, '
          f'p95 {fast["p95_ms"]:.1f} ms wall; cpu median {fast["cpu"]["median_ms"]:.1f} ms, '
          f'p95 {fast["cpu"]["p95_ms"]:.1f} ms; stages (median ms) '
          + ', '.join(f'{k} {v:.1f}' for k, v in fast_stages.items()))
    results['fast_path'] = {**fast, 'stages_median_ms': fast_stages}

    exact_scans = scans[:2]
    exact, exact_stages = time_path(exact_scans, dataclasses.replace(cfg, solver='exact'))
    print(f'exact path (eigh <= {EXACT_MAX_BLOCK_NODES} nodes/slice, Chebyshev above): '
          f'median {exact["median_ms"]:.0f} ms, p95 {exact["p95_ms"]:.0f} ms wall')
    results['exact_path'] = {**exact, 'stages_median_ms': exact_stages}

    print('agreement fast vs exact (signal, argmax assignment, same lambda_max):')
    orders = (10, 30) if args.quick else (5, 10, 20, 30, 40, 60)
    results['agreement_vs_order'] = agreement(exact_scans[:1] if args.quick else exact_scans,
                                              cfg, orders)

    lm = lambda_max_check(scans[:3], cfg)
    print(f'lambda_max: lanczos {lm["lanczos"]["median_ms"]:.1f} ms vs arpack '
          f'{lm["arpack"]["median_ms"]:.1f} ms per scan; relative difference median '
          f'{lm["rel_diff_median"]:.2e}, max {lm["rel_diff_max"]:.2e}')
    results['lambda_max'] = lm

    kept = kept_per_band(scans, cfg)
    print('fraction of points per band: '
          + ' '.join(f'{b}:{100 * f:.1f}%' for b, f in kept['fraction_per_band'].items()))
    print(f'band 0: isolated {100 * kept["band0_isolated"]:.2f} %, out of z range '
          f'{100 * kept["band0_out_of_range"]:.2f} %; slices per scan {kept["n_slices_mean"]:.1f}')
    print('kept per mask: ' + ', '.join(f'{m} {100 * f:.1f}%'
                                        for m, f in kept['kept_fraction_per_mask'].items()))
    results['kept'] = kept

    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2, default=str))
    print(f'wrote {RESULTS}')


if __name__ == '__main__':
    main()
