"""Speed and agreement of the spectral filter on VLP-16-like orchard scans.

Prints the figures and writes them to benchmarks/results/spectral.json:
- median / p95 time per scan of the fast path (Chebyshev) and of the exact path (dense eigh on
  slices up to `exact_max_slice_points`, Chebyshev above);
- agreement fast vs exact (fraction of points with the same band, on exact-sized slices) and
  how it varies with the Chebyshev order K;
- lambda_max: batched Lanczos vs ARPACK;
- points kept per band (single-band masks) and for a few masks;
- the graph builder variants (query_pairs vs sparse_distance_matrix).

Scans come from the project simulator `gft_odom.sim` (VLP-16 at 0.2 deg, ~29 k points), else
from the small ray caster below (16 rings at -15..+15 deg, 1800 azimuths, trunks, porous
canopies, ground at -0.7 m).

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
from scipy.spatial import cKDTree

from gft_odom.core.spectral import BandMask, SpectralConfig, SpectralFilter
from gft_odom.core.spectral.chebyshev import lambda_max_per_slice
from gft_odom.core.spectral.graph import gaussian_graph, laplacian
from gft_odom.core.spectral.slicing import slice_points, voxelise

RESULTS = Path(__file__).parent / 'results' / 'spectral.json'


# -- a VLP-16 in an orchard -----------------------------------------------------------------

def _orchard(rng: np.random.Generator, row_spacing_m: float = 6.0, tree_spacing_m: float = 3.5,
             n_rows: int = 6, length_m: float = 120.0, ground_z_m: float = -0.7):
    """Trunk cylinders and canopy spheres of a citrus block (rows along x)."""
    rows_y = (np.arange(n_rows) - (n_rows - 1) / 2.0) * row_spacing_m
    xs = np.arange(-length_m / 2, length_m / 2, tree_spacing_m)
    tx, ty = np.meshgrid(xs, rows_y)
    tx = tx.ravel() + rng.normal(0, 0.15, tx.size)
    ty = ty.ravel() + rng.normal(0, 0.1, ty.size)
    trunk_r = rng.uniform(0.07, 0.14, tx.size)
    trunk_top = ground_z_m + rng.uniform(0.5, 0.8, tx.size)
    canopy_r = rng.uniform(1.2, 1.8, tx.size)
    canopy_z = trunk_top + canopy_r * 0.8
    return tx, ty, trunk_r, trunk_top, canopy_r, canopy_z


def vlp16_orchard_scan(seed: int = 0, sensor_x_m: float = 0.0, ground_z_m: float = -0.7,
                       max_range_m: float = 60.0) -> np.ndarray:
    """Ray-cast one VLP-16 sweep (16 x 1800 rays) from the middle of an orchard lane."""
    rng = np.random.default_rng(seed)
    tx, ty, trunk_r, trunk_top, canopy_r, canopy_z = _orchard(np.random.default_rng(1234))
    tx = tx - sensor_x_m
    ty = ty - 3.0  # the lane between rows at y = 0 and y = 6 in the orchard frame
    elev = np.deg2rad(np.arange(-15.0, 16.0, 2.0))
    azim = np.deg2rad(np.arange(1800) * 0.2)
    el, az = np.meshgrid(elev, azim, indexing='ij')
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    d = d.reshape(-1, 3)
    n_rays = d.shape[0]
    best = np.full(n_rays, np.inf)

    # Ground plane (slightly uneven through noise on the hit height).
    down = d[:, 2] < -1e-6
    t_ground = np.where(down, ground_z_m / np.where(down, d[:, 2], -1.0), np.inf)
    best = np.minimum(best, t_ground)

    near = np.hypot(tx, ty) < max_range_m + 2.0
    tx, ty, trunk_r, trunk_top = tx[near], ty[near], trunk_r[near], trunk_top[near]
    canopy_r, canopy_z = canopy_r[near], canopy_z[near]
    # Trunks: 2-D circle intersection, then height check.
    dxy = d[:, :2]
    a = np.sum(dxy * dxy, axis=1)[:, None]
    b = -2.0 * (dxy[:, 0:1] * tx[None] + dxy[:, 1:2] * ty[None])
    c = (tx * tx + ty * ty - trunk_r * trunk_r)[None]
    disc = b * b - 4 * a * c
    t_trunk = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    z_hit = t_trunk * d[:, 2:3]
    t_trunk = np.where((t_trunk > 0) & (z_hit >= ground_z_m) & (z_hit <= trunk_top[None]),
                       t_trunk, np.inf)
    best = np.minimum(best, t_trunk.min(axis=1))
    # Canopies: porous spheres; a ray that enters stops at a random depth or passes (15 %).
    centre = np.stack([tx, ty, canopy_z], -1)
    proj = d @ centre.T
    dist2 = np.sum(centre * centre, axis=1)[None] - proj * proj
    inside = dist2 < canopy_r[None] ** 2
    half = np.sqrt(np.maximum(canopy_r[None] ** 2 - dist2, 0.0))
    depth = rng.exponential(0.25, size=proj.shape)
    t_can = proj - half + np.minimum(depth, 2 * half)
    hit = inside & (proj - half > 0) & (rng.random(proj.shape) > 0.15)
    t_can = np.where(hit, t_can, np.inf)
    best = np.minimum(best, t_can.min(axis=1))

    ok = np.isfinite(best) & (best < max_range_m) & (best > 0.5)
    r = best[ok] + rng.normal(0.0, 0.03, int(ok.sum()))
    pts = d[ok] * r[:, None]
    return pts


def load_scans(n_scans: int, stride: int = 10) -> tuple[list[np.ndarray], str]:
    """Every `stride`-th sweep of the project simulator's `row` run (VLP-16, 0.2 deg), or the
    ray caster above when the simulator is not importable."""
    try:
        from gft_odom.sim import ScanSimulator, SimConfig, generate_orchard, make_motion
        from gft_odom.sim.motion import required_row_length_m
    except ImportError:
        return ([vlp16_orchard_scan(seed=i, sensor_x_m=0.5 * i) for i in range(n_scans)],
                'benchmarks/bench_spectral.py ray caster (16 rings x 1800 azimuths)')
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
    """Points whose slice has at most exact_max_slice_points graph nodes."""
    sl = slice_points(p[:, 2], cfg.slice_thickness_m, cfg.z_min_m, cfg.z_max_m)
    _, _, starts, _ = voxelise(p[sl.order, :2], sl.slice_of_point, sl.n_slices,
                               cfg.voxel_size_m)
    small = np.zeros(p.shape[0], dtype=bool)
    small[sl.order] = (np.diff(starts) <= cfg.exact_max_slice_points)[sl.slice_of_point]
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


def variants(scans, cfg: SpectralConfig) -> dict:
    """Speed and band agreement of parameter variants against the unmerged (voxel 0) graph."""
    reference = SpectralFilter.from_config(dataclasses.replace(cfg, voxel_size_m=0.0))
    ref = [reference.frequencies(p) for p in scans]
    out = {}
    for name, change in (('default', {}), ('voxel_size_m=0', {'voxel_size_m': 0.0}),
                         ('voxel_size_m=0.08', {'voxel_size_m': 0.08}),
                         ('tau_m=0.3,sigma_m=0.15', {'tau_m': 0.3, 'sigma_m': 0.15}),
                         ('chebyshev_order=20', {'chebyshev_order': 20}),
                         ('lanczos_iterations=12', {'lanczos_iterations': 12})):
        vcfg = dataclasses.replace(cfg, **change)
        timing, _ = time_path(scans, vcfg)
        filt = SpectralFilter.from_config(vcfg)
        same, total = 0, 0
        if 'tau_m' not in change:
            for p, rf in zip(scans, ref):
                f = filt.frequencies(p)
                sel = (rf.band > 0) & (f.band > 0)
                same += int(np.sum(f.band[sel] == rf.band[sel]))
                total += int(sel.sum())
        out[name] = {'median_ms': timing['median_ms'], 'cpu_median_ms': timing['cpu']['median_ms'],
                     'same_band_as_unmerged': same / total if total else None}
        agree = '' if not total else f', same band as unmerged {100 * same / total:.2f} %'
        cpu_ms = timing['cpu']['median_ms']
        print(f'  {name}: median {timing["median_ms"]:.1f} ms (cpu {cpu_ms:.1f} ms){agree}')
    return out


def dominant_bands(scans, cfg: SpectralConfig) -> list[float]:
    """Band fractions under the `dominant` definition (exact-sized slices only)."""
    filt = SpectralFilter.from_config(dataclasses.replace(cfg, method='dominant', solver='exact'))
    bands = []
    for p in scans:
        f = filt.frequencies(p)
        bands.append(f.band[_exact_sized(p, cfg) & (f.band > 0)])
    bands = np.concatenate(bands)
    return [float(x) for x in np.bincount(bands, minlength=cfg.n_bands + 1)[1:] / bands.size]


def lambda_max_check(scans, cfg: SpectralConfig) -> dict:
    rel, t_l, t_a = [], [], []
    for p in scans:
        sl = slice_points(p[:, 2], cfg.slice_thickness_m, cfg.z_min_m, cfg.z_max_m)
        xy, node_slice, starts, _ = voxelise(p[sl.order, :2], sl.slice_of_point, sl.n_slices,
                                             cfg.voxel_size_m)
        L = laplacian(gaussian_graph(xy, node_slice, cfg.tau_m, cfg.sigma_m))
        t = time.perf_counter()
        la = lambda_max_per_slice(L, starts, 'lanczos', cfg.lanczos_iterations)
        t_l.append(time.perf_counter() - t)
        t = time.perf_counter()
        ar = lambda_max_per_slice(L, starts, 'arpack')
        t_a.append(time.perf_counter() - t)
        ok = ar > 0
        rel.append(np.abs(la[ok] - ar[ok]) / ar[ok])
    rel = np.concatenate(rel)
    return {'lanczos': _stats_ms(t_l), 'arpack': _stats_ms(t_a),
            'rel_diff_median': float(np.median(rel)), 'rel_diff_max': float(rel.max())}


def graph_builders(pts: np.ndarray, cfg: SpectralConfig) -> dict:
    sl = slice_points(pts[:, 2], cfg.slice_thickness_m, cfg.z_min_m, cfg.z_max_m)
    xy = pts[sl.order, :2]
    lifted = np.column_stack([xy, sl.slice_of_point * 3.0 * cfg.tau_m])
    out = {}

    def run(name, fn, n=5):
        ts = []
        for _ in range(n):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
        out[name] = float(np.median(ts) * 1e3)

    run('gaussian_graph (query_pairs, full W)',
        lambda: gaussian_graph(xy, sl.slice_of_point, cfg.tau_m, cfg.sigma_m))
    tree = cKDTree(lifted)
    run('cKDTree build', lambda: cKDTree(lifted, balanced_tree=False, compact_nodes=False))
    run('query_pairs ndarray', lambda: tree.query_pairs(cfg.tau_m, output_type='ndarray'))
    run('sparse_distance_matrix coo',
        lambda: tree.sparse_distance_matrix(tree, cfg.tau_m, output_type='coo_matrix'))
    return out


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


def centring_effect(scans, cfg: SpectralConfig) -> dict:
    out = {}
    for centring in ('component', 'slice'):
        filt = SpectralFilter.from_config(dataclasses.replace(cfg, centring=centring))
        bands = np.concatenate([filt.frequencies(p).band for p in scans])
        valid = bands > 0
        frac = np.bincount(bands[valid], minlength=cfg.n_bands + 1)[1:] / valid.sum()
        out[centring] = [float(f) for f in frac]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scans', type=int, default=12)
    parser.add_argument('--quick', action='store_true', help='fewer scans and orders')
    args = parser.parse_args()
    n_scans = 3 if args.quick else args.scans
    # This benchmark measures the paper's path: `signal` on the slice graph (the package default,
    # `ldos_mean` on the scan-line graph, is measured by bench_frequency_classes.py).
    cfg = SpectralConfig(method='signal', graph='slice', lanczos_iterations=30)
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
    print(f'exact path (eigh <= {cfg.exact_max_slice_points} nodes/slice, Chebyshev above): '
          f'median {exact["median_ms"]:.0f} ms, p95 {exact["p95_ms"]:.0f} ms wall')
    results['exact_path'] = {**exact, 'stages_median_ms': exact_stages}

    print('agreement fast vs exact (signal, argmax assignment, same lambda_max):')
    orders = (10, 30) if args.quick else (5, 10, 20, 30, 40, 60)
    results['agreement_vs_order'] = agreement(exact_scans[:1] if args.quick else exact_scans,
                                              cfg, orders)
    print('agreement fast vs exact (signal, relative assignment):')
    results['agreement_vs_order_relative'] = agreement(
        exact_scans[:1], dataclasses.replace(cfg, band_assignment='relative'), orders)

    print('variants (time on all scans; band agreement with the unmerged graph):')
    results['variants'] = variants(scans[:4], cfg)

    lm = lambda_max_check(scans[:3], cfg)
    print(f'lambda_max: lanczos {lm["lanczos"]["median_ms"]:.1f} ms vs arpack '
          f'{lm["arpack"]["median_ms"]:.1f} ms per scan; relative difference median '
          f'{lm["rel_diff_median"]:.2e}, max {lm["rel_diff_max"]:.2e}')
    results['lambda_max'] = lm

    gb = graph_builders(scans[0], cfg)
    print('graph builders (ms): ' + ', '.join(f'{k} {v:.1f}' for k, v in gb.items()))
    results['graph_builders_ms'] = gb

    kept = kept_per_band(scans, cfg)
    print('fraction of points per band: '
          + ' '.join(f'{b}:{100 * f:.1f}%' for b, f in kept['fraction_per_band'].items()))
    print(f'band 0: isolated {100 * kept["band0_isolated"]:.2f} %, out of z range '
          f'{100 * kept["band0_out_of_range"]:.2f} %; slices per scan {kept["n_slices_mean"]:.1f}')
    print('kept per mask: ' + ', '.join(f'{m} {100 * f:.1f}%'
                                        for m, f in kept['kept_fraction_per_mask'].items()))
    results['kept'] = kept

    ce = centring_effect(scans[:3], cfg)
    for k, v in ce.items():
        print(f'centring per {k}: band fractions ' + ' '.join(f'{100 * f:.1f}' for f in v))
    results['centring_band_fractions'] = ce
    rel = centring_effect(scans[:3], dataclasses.replace(cfg, band_assignment='relative'))
    print('relative assignment, centring per component: band fractions '
          + ' '.join(f'{100 * f:.1f}' for f in rel['component']))
    results['relative_assignment_band_fractions'] = rel['component']
    dom = dominant_bands(scans[:1], cfg)
    print('dominant definition (exact-sized slices): band fractions '
          + ' '.join(f'{100 * f:.1f}' for f in dom))
    results['dominant_band_fractions'] = dom

    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2, default=str))
    print(f'wrote {RESULTS}')


if __name__ == '__main__':
    main()
