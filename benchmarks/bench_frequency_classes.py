"""Does a point's graph frequency tell what it hit? Every definition x graph x source, labelled.

The simulator labels every return (ground / trunk / canopy / other: posts, pipes, sheds,
vehicles). For each frequency definition (`gft_odom.core.spectral.frequency.REGISTRY`), each
graph (`scan_line`, `slice`) and each source (`scan`: the single scan; `local_map`: the merged
cloud of the last scans, frequencies passed to the scan's points by nearest neighbour), on
several seeds, scenarios and simulator variants, and for the one feature that is not a
frequency (`map_planarity`: the GenZ-ICP-style planarity of each point's neighbourhood in the
local map, issue 20's ablation), it reports:
- the band histogram per class (B = `--bands`, default 10);
- the mutual information between band and class, in bits;
- the balanced accuracy of the best threshold on nu for trunk + ground against canopy;
- the share of the most crowded band;
- milliseconds per scan, median: CPU time of the computing thread (steady on a shared machine)
  and wall time (what a node sees; inflated when other jobs load the machine);
- agreement with the exact reference where one exists (KPM against the exact LDOS band
  energies, by dense eigh per connected component of the scan-line graph).

Seeds are split: `--train-seeds` are the ones the defaults were chosen on, `--test-seeds` the
ones reported as held out; both are printed. Writes benchmarks/results/frequency_classes.json.

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
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from gft_odom.core.spectral import SpectralConfig, SpectralFilter
from gft_odom.core.spectral.bands import band_of_nu
from gft_odom.core.spectral.frequency import REGISTRY
from gft_odom.core.spectral.sources import make_source
from gft_odom.sim.simulator import ScanSimulator, SimConfig

RESULTS = Path(__file__).parent / 'results' / 'frequency_classes.json'
CLASSES = ('ground', 'trunk', 'canopy', 'other')
# Simulator variants: the frequencies must not depend on one set of canopy / noise settings.
SIM_VARIANTS = {
    'default': {},
    'dense_windy': {'canopy_mean_free_path_m': 0.2, 'wind_amplitude_m': 0.08},
    'sparse_noisy': {'canopy_mean_free_path_m': 0.7, 'range_noise_std_m': 0.035,
                     'dropout_probability': 0.05},
}
LOCAL_MAP_SCANS = 5  # scans merged into the local map (every other one, as keyframes)
LOCAL_MAP_VOXEL_M = 0.05


def surface_class(surface: np.ndarray) -> np.ndarray:
    """Simulator surface code -> 0 ground, 1 trunk, 2 canopy, 3 other."""
    surface = np.asarray(surface, dtype=np.int64)
    return np.where(surface <= 2, surface, 3)


def mutual_information_bits(band: np.ndarray, cls: np.ndarray) -> float:
    """I(band; class) from the joint histogram, in bits."""
    _, b = np.unique(band, return_inverse=True)
    joint = np.zeros((b.max() + 1, len(CLASSES)))
    np.add.at(joint, (b, cls), 1.0)
    joint /= joint.sum()
    outer = joint.sum(axis=1, keepdims=True) @ joint.sum(axis=0, keepdims=True)
    nz = joint > 0
    return float(np.sum(joint[nz] * np.log2(joint[nz] / outer[nz])))


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


def make_scans(scenarios, seeds, variants, indices, azimuth_step_deg):
    """Labelled simulated scans with the poses of the previous scans (for the local map)."""
    scans = []
    for variant in variants:
        cfg = dataclasses.replace(SimConfig(azimuth_step_deg=azimuth_step_deg),
                                  **SIM_VARIANTS[variant])
        for scenario in scenarios:
            for seed in seeds:
                sim = ScanSimulator.from_config(cfg, scenario=scenario,
                                                n_scans=max(indices) + 2, seed=seed)
                for k in indices:
                    history = [sim.scan(j) for j in range(k - 2 * LOCAL_MAP_SCANS, k, 2)
                               if j >= 0]
                    scans.append({'variant': variant, 'scenario': scenario, 'seed': seed,
                                  'index': k, 'scan': sim.scan(k), 'history': history})
    return scans


def cropped(sim_scan, min_range_m=0.5, max_range_m=60.0):
    """The pipeline's range crop of a simulated scan: (Scan, class per point)."""
    scan = sim_scan.scan
    r = np.linalg.norm(scan.points_xyz, axis=1)
    keep = (r >= min_range_m) & (r <= max_range_m)
    return scan.select(keep), surface_class(sim_scan.surface[keep])


def local_map_frequencies(filt: SpectralFilter, item, n_bands: int):
    """Frequencies of the merged last scans (world frame, true poses), passed to the current
    scan by nearest neighbour: the `local_map` source as the paper computed them."""
    scan = item['scan']
    clouds = [h.T_world_sensor[:3, :3] @ cropped(h)[0].points_xyz.T
              + h.T_world_sensor[:3, 3:4] for h in item['history'] + [scan]]
    merged = np.concatenate([c.T for c in clouds])
    key = np.floor(merged / LOCAL_MAP_VOXEL_M).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    merged = merged[np.sort(first)]
    # Slices are horizontal layers of the map in the current sensor's frame (same z axis).
    T = np.linalg.inv(scan.T_world_sensor)
    merged_sensor = (T[:3, :3] @ merged.T + T[:3, 3:4]).T
    t = time.perf_counter()
    freqs = filt.frequencies(merged_sensor, n_bands)
    t_map = time.perf_counter() - t
    pts, _ = cropped(scan)
    t = time.perf_counter()
    _, nearest = cKDTree(merged_sensor).query(pts.points_xyz, k=1)
    t_query = time.perf_counter() - t
    return freqs.nu[nearest], freqs.band[nearest], t_map, t_query


def map_planarity_values(item, n_bands: int):
    """The `map_planarity` source on the last scans as keyframes (true poses), read at the
    current scan's true pose: (nu, band), and the seconds it took (map and lookup)."""
    history = item['history']
    cfg = dataclasses.replace(SpectralConfig(), frequency_source='map_planarity',
                              n_bands=n_bands, local_map_keyframes=len(history) + 1,
                              local_map_keyframe_distance_m=1e-6)
    source = make_source(SpectralFilter(cfg))
    for h in history:
        source.observe(cropped(h)[0], h.T_world_sensor)
    pts, _ = cropped(item['scan'])
    # An empty keyframe at the current pose: the lookup uses that pose, the map is unchanged.
    source.observe(pts.select(np.zeros(len(pts), dtype=bool)), item['scan'].T_world_sensor)
    t = time.perf_counter()
    freqs = source.frequencies(pts, n_bands)
    return freqs.nu, freqs.band, time.perf_counter() - t


def exact_ldos_bands(filt: SpectralFilter, scan, n_bands: int, max_component: int = 3000):
    """Exact LDOS band energies by eigh per connected component (scan-line graph only):
    argmax band per point, -1 where the component is too large."""
    graph = filt.graph(scan.points_xyz, scan.ring)
    n_comp, labels = connected_components(graph.L.W, directed=False)
    lmax = float(graph.lmax[0])
    out = np.full(graph.n_nodes, -1, dtype=np.int64)
    order = np.argsort(labels, kind='stable')
    bounds = np.r_[0, np.cumsum(np.bincount(labels, minlength=n_comp))]
    W = graph.L.W.tocsr()
    for c in range(n_comp):
        nodes = order[bounds[c]:bounds[c + 1]]
        if nodes.size > max_component:
            continue
        if nodes.size == 1:
            out[nodes] = 1  # lambda = 0: band 1
            continue
        Wc = W[nodes][:, nodes].toarray()
        lam, U = np.linalg.eigh(np.diag(Wc.sum(axis=1)) - Wc)
        eig_band = band_of_nu(np.clip(lam / lmax, 0.0, 1.0), n_bands)
        energy = np.zeros((nodes.size, n_bands))
        for b in np.unique(eig_band):
            energy[:, b - 1] = np.sum(U[:, eig_band == b] ** 2, axis=1)
        out[nodes] = np.argmax(energy, axis=1) + 1
    point_band = np.full(graph.n_points, -1, dtype=np.int64)
    point_band[graph.sl.order] = out[graph.node_of_point]
    return point_band


def evaluate(combo, scans, n_bands):
    """Figures of one definition x graph x source over `scans`."""
    method, graph, source = combo
    if source != 'map_planarity':
        cfg = dataclasses.replace(SpectralConfig(), method=method, graph=graph,
                                  n_bands=n_bands,
                                  solver='exact' if method == 'dominant' else 'chebyshev')
        filt = SpectralFilter(cfg)
    if method == 'dominant':
        scans = scans[::6]  # dense eigh of every slice: seconds a scan, so a subsample
    bands, nus, classes, times, cpu_times, agree = [], [], [], [], [], []
    for item in scans:
        pts, cls = cropped(item['scan'])
        if source == 'map_planarity':
            c = time.thread_time()
            nu, band, t_all = map_planarity_values(item, n_bands)
            times.append(t_all)  # the map's covariances for every scan (per keyframe online)
            cpu_times.append(time.thread_time() - c)
        elif source == 'local_map':
            c = time.thread_time()
            nu, band, t_map, t_query = local_map_frequencies(filt, item, n_bands)
            # Amortised: the map's frequencies are recomputed once per keyframe (every other
            # scan here), the nearest-neighbour transfer runs every scan.
            times.append(t_map / 2.0 + t_query)
            cpu_times.append((time.thread_time() - c) * (t_map / 2.0 + t_query)
                             / max(t_map + t_query, 1e-9))
        else:
            t, c = time.perf_counter(), time.thread_time()
            freqs = filt.scan_frequencies(pts, n_bands)
            times.append(time.perf_counter() - t)
            cpu_times.append(time.thread_time() - c)
            nu, band = freqs.nu, freqs.band
            if method == 'kpm' and graph == 'scan_line':
                exact = exact_ldos_bands(filt, pts, n_bands)
                ok = (exact > 0) & (band > 0)
                agree.append(float(np.mean(band[ok] == exact[ok])))
        bands.append(band)
        nus.append(nu)
        classes.append(cls)
    band = np.concatenate(bands)
    nu = np.concatenate(nus)
    cls = np.concatenate(classes)
    hist = {CLASSES[c]: (np.bincount(band[cls == c], minlength=n_bands + 1)
                         / max(1, np.sum(cls == c))).round(4).tolist()
            for c in range(len(CLASSES))}
    per_scan_mi = [mutual_information_bits(b, c) for b, c in zip(bands, classes)]
    return {
        'method': method, 'graph': graph, 'source': source,
        'mutual_information_bits': mutual_information_bits(band, cls),
        'mutual_information_bits_per_scan_min': float(np.min(per_scan_mi)),
        'balanced_accuracy_trunk_ground_vs_canopy': best_threshold_balanced_accuracy(nu, cls),
        'largest_band_share': float(np.bincount(band).max() / band.size),
        'largest_band_share_per_scan_max': float(max(np.bincount(b).max() / b.size
                                                     for b in bands)),
        'no_spectrum_share': float(np.mean(band == 0)),
        'n_scans': len(scans),
        'cpu_ms_median': 1e3 * float(np.median(cpu_times)),
        'wall_ms_median': 1e3 * float(np.median(times)),
        'agreement_with_exact': float(np.mean(agree)) if agree else None,
        'band_histogram_per_class': hist,
    }


def combos(quick: bool):
    """(definition, graph, source) to measure; `dominant` only where eigh is affordable."""
    out = []
    for method in sorted(REGISTRY):
        for graph in ('scan_line', 'slice'):
            if method == 'dominant' and graph == 'scan_line':
                continue  # one block of the whole scan: far beyond dense eigh
            out.append((method, graph, 'scan'))
    for method in ('ldos_mean', 'ldos_spread', 'signal'):
        out.append((method, 'slice', 'local_map'))
    if quick:
        out = [c for c in out if c[0] in ('ldos_mean', 'signal')]
    return out + [('planarity', 'map', 'map_planarity')]  # not a frequency: the ablation


def table(rows) -> str:
    """Markdown table of the headline figures."""
    lines = ['| definition | graph | source | MI [bits] | min MI / scan | bal. acc. | '
             'largest band | CPU ms | wall ms | vs exact |',
             '|---|---|---|---:|---:|---:|---:|---:|---:|---:|']
    for r in rows:
        exact = '' if r['agreement_with_exact'] is None else f"{r['agreement_with_exact']:.2f}"
        lines.append(f"| {r['method']} | {r['graph']} | {r['source']} | "
                     f"{r['mutual_information_bits']:.3f} | "
                     f"{r['mutual_information_bits_per_scan_min']:.3f} | "
                     f"{r['balanced_accuracy_trunk_ground_vs_canopy']:.3f} | "
                     f"{100 * r['largest_band_share']:.0f} % | {r['cpu_ms_median']:.1f} | "
                     f"{r['wall_ms_median']:.1f} | "
                     f"{exact} |")
    return '\n'.join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--bands', type=int, default=SpectralConfig().n_bands)
    parser.add_argument('--train-seeds', type=int, nargs='+', default=[1, 2])
    parser.add_argument('--test-seeds', type=int, nargs='+', default=[21, 22])
    parser.add_argument('--scenarios', nargs='+', default=['row', 'uturn', 'loop'])
    parser.add_argument('--indices', type=int, nargs='+', default=[12, 40])
    parser.add_argument('--quick', action='store_true', help='few scans, two definitions')
    parser.add_argument('--out', type=Path, default=RESULTS)
    args = parser.parse_args()
    variants = list(SIM_VARIANTS)
    azimuth = 0.2
    if args.quick:
        args.train_seeds, args.test_seeds = args.train_seeds[:1], args.test_seeds[:1]
        args.scenarios, args.indices, variants, azimuth = ['row'], [12], ['default'], 0.4
    results = {'machine': platform.platform(), 'n_bands': args.bands,
               'train_seeds': args.train_seeds, 'test_seeds': args.test_seeds,
               'scenarios': args.scenarios, 'sim_variants': {v: SIM_VARIANTS[v]
                                                             for v in variants}}
    for split, seeds in (('train', args.train_seeds), ('test', args.test_seeds)):
        t = time.perf_counter()
        scans = make_scans(args.scenarios, seeds, variants, args.indices, azimuth)
        print(f'{split}: {len(scans)} scans simulated in {time.perf_counter() - t:.0f} s')
        rows = [evaluate(c, scans, args.bands) for c in combos(args.quick)]
        results[split] = rows
        results[f'{split}_per_variant'] = {
            v: [evaluate(('ldos_mean', 'scan_line', 'scan'),
                         [s for s in scans if s['variant'] == v], args.bands)]
            for v in variants}
        print(f'\n{split} seeds {seeds}, scenarios {args.scenarios}, variants {variants}:')
        print(table(rows))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1))
    print(f'\nwrote {args.out}')


if __name__ == '__main__':
    main()
