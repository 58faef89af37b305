"""`gft-odom demo` (what `make demo` runs): simulate an orchard bag, replay it four ways.

Paper mode (scan-to-scan point-to-point ICP) and default mode (our registration), each with and
without the graph-frequency filter, on the same synthetic scans; a table of ATE, the paper's
MSE, RPE drift, latency and points kept; the figures of every run.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gft_odom.params_file import load_config
from gft_odom.replay import run_replay, write_json, write_results
from gft_odom.sim.writer import simulate_to_bag
from gft_odom.tools.cmd_replay import add_config_arguments
from gft_odom.tools.progress import progress_bar

VARIANTS = (
    ('paper', False), ('paper', True), ('default', False), ('default', True),
)
COLUMNS = (
    ('ATE RMSE [m]', 'ate_rmse_m', '{:.3f}'),
    ('ATE mean [m]', 'ate_mean_m', '{:.3f}'),
    ('paper MSE [m^2]', 'paper_mse_m2', '{:.4f}'),
    ('RPE drift [%]', 'rpe_drift_pct', '{:.2f}'),
    ('latency median [ms]', 'latency_median_ms', '{:.1f}'),
    ('latency p95 [ms]', 'latency_p95_ms', '{:.1f}'),
    ('points kept', 'points_kept_fraction', '{:.1%}'),
    ('fallbacks', 'fallbacks', '{:d}'),
)


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        'demo', help='simulate an orchard bag and replay it with and without the filter',
        description='The embedded default: a SYNTHETIC orchard (not real data) replayed in '
                    'paper and default registration modes, each with and without the filter.')
    p.add_argument('--out', default='demo_out', help='results folder (default: demo_out)')
    p.add_argument('--scenario', default='uturn', choices=('row', 'uturn', 'loop'))
    p.add_argument('--scans', type=int, default=150, help='number of scans to simulate')
    p.add_argument('--seed', type=int, default=7,
                   help='orchard seed (the band mask was not chosen on it)')
    add_config_arguments(p)
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    return p


def format_table(rows: list[tuple[str, dict]]) -> str:
    """A Markdown table, one run per row."""
    header = '| run | ' + ' | '.join(title for title, _, _ in COLUMNS) + ' |'
    lines = [header, '|' + '---|' * (len(COLUMNS) + 1)]
    for name, metrics in rows:
        cells = []
        for _, key, fmt in COLUMNS:
            value = metrics.get(key)
            cells.append('n/a' if value is None else fmt.format(value))
        lines.append(f'| {name} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    base_config = load_config(args.config, args.overrides)
    with progress_bar(args.scans, f'simulate {args.scenario} seed {args.seed}',
                      enabled=not args.quiet) as update:
        sim = simulate_to_bag(out / 'data', scenario=args.scenario, n_scans=args.scans,
                              seed=args.seed, progress=lambda i: update(i))
    rows = []
    for mode, use_filter in VARIANTS:
        name = f'{mode}{"+gft" if use_filter else ""}'
        config = load_config(args.config, [*args.overrides, f'registration.mode={mode}',
                                           f'pipeline.use_spectral_filter={str(use_filter).lower()}'])
        with progress_bar(None, f'replay {name}', enabled=not args.quiet) as update:
            replay = run_replay([sim.bag_path], config, gt_path=sim.gt_csv_path,
                                progress=update)
        write_results(replay, config, out / name)
        rows.append((name, replay.metrics))
    table = format_table(rows)
    mask = list(base_config.spectral.band_mask)
    text = (f'# gft-odom demo: SYNTHETIC orchard, scenario {args.scenario}, seed {args.seed}, '
            f'{args.scans} scans\n\n'
            f'Ground truth: the simulated GPS antenna track (`gt.csv`), rigid alignment on '
            f'positions. Filter: n_bands={base_config.spectral.n_bands}, band_mask={mask}. '
            f'`+gft` = with the graph-frequency filter, same registration.\n\n{table}\n')
    (out / 'results.md').write_text(text)
    write_json(out / 'results.json', {name: metrics for name, metrics in rows})
    print(text)
    print(f'figures and per-run results in {out}/<run>/, bag in {sim.bag_path}')
    return 0
