"""`run_band_search`: caches, search, held-out scoring and every output file, in one call.

Output folder:
  results.jsonl           every evaluated mask (training bags), appended as they finish
  spread.jsonl            the identity and the best mask run on shifted scans (the spread)
  ranking.csv             all masks best first, with the baseline on top (in-sample)
  summary.json / .md      chosen mask: in-sample vs baseline, held-out vs baseline, and the
                          decision against the identity (both scores, the spread, why)
  best_mask.yaml          full effective config with the chosen mask (params-file format)
  fig6_top_masks.png, fig7_band_correlation.png, fig8_narrow_intervals.png
  cache/*.npz             per-point bands of every scan for B = min..max (reused on restart)
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Callable, Sequence

from gft_odom.bands.analysis import (
    correlation_table,
    interval_counts,
    ranked,
    write_ranking_csv,
)
from gft_odom.bands.choice import choose
from gft_odom.bands.evaluate import BASELINE_KEY, config_for_mask
from gft_odom.bands.masks import parse_mask_key
from gft_odom.bands.search import (
    HELD_OUT,
    IN_SAMPLE,
    BandSearch,
    BandSearchConfig,
    SearchStopped,
    SequenceSpec,
    band_counts_for,
    held_out,
    prepare_caches,
    summarise,
)
from gft_odom.config import GftOdomConfig
from gft_odom.params_file import write_params_file
from gft_odom.replay import write_json

log = logging.getLogger(__name__)


def run_band_search(train: Sequence[SequenceSpec], config: GftOdomConfig, out_dir: str | Path,
                    search_cfg: BandSearchConfig = BandSearchConfig(),
                    test: Sequence[SequenceSpec] = (), workers: int = 1,
                    ray_address: str | None = None, topic: str = '/velodyne_points',
                    max_scans: int | None = None, figures: bool = True,
                    progress: Callable[[str, int, int], None] | None = None,
                    max_new_results: int | None = None) -> dict:
    """Search masks on `train`, write the outputs, score the chosen mask on `test`.

    The chosen mask is the best in-sample one only when it beats the identity by more than
    the measured spread (`bands.choice`); else the identity, every band kept.
    `progress(stage, done, total)` reports the cache building and the mask evaluations.
    `max_new_results` stops after that many new evaluations (what a kill does; for tests and
    for spreading a long search over several runs); the summary is then not written.
    """
    search_cfg.validate()
    config.validate()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    counts = band_counts_for(search_cfg)

    def stage(name):
        return (lambda d, t: progress(name, d, t)) if progress else None

    train_caches, paths = prepare_caches(
        train, config, counts, out / 'cache', topic, max_scans,
        (lambda n, d, t: progress(f'frequencies {n}', d, t)) if progress else None)
    search = BandSearch(train_caches, config, out, paths, workers, ray_address)
    if max_new_results is not None:
        search.log.limit = max_new_results
    try:
        if search_cfg.strategy == 'exhaustive':
            rows = search.exhaustive(search_cfg.min_bands, search_cfg.max_bands,
                                     stage('masks'))
        else:
            rows = search.smart(search_cfg, stage('masks'))
        if BASELINE_KEY not in rows:
            rows[BASELINE_KEY] = search.evaluate([None])[BASELINE_KEY]
        chosen_row, decision = choose(search, rows, search_cfg.min_bands,
                                      search_cfg.spread_shifts)
    except SearchStopped:
        return {'stopped_after': max_new_results}
    finally:
        search.close()
    mode = config.registration.mode

    order = ranked(list(rows.values()))
    chosen = parse_mask_key(chosen_row['key'])
    held = None
    if test:
        test_caches, _ = prepare_caches(
            test, config, [chosen.n_bands], out / 'cache' / 'test', topic, max_scans,
            (lambda n, d, t: progress(f'frequencies {n} (test)', d, t)) if progress else None)
        held = held_out(test_caches, config, chosen)
        write_json(out / 'held_out.json', {'label': HELD_OUT, **held})
    summary = summarise(rows, held, mode, search_cfg.strategy, search.n_evaluated,
                        chosen_row, decision)
    summary['search'] = {'min_bands': search_cfg.min_bands, 'max_bands': search_cfg.max_bands,
                         'train': [c.name for c in train_caches],
                         'test': [s.label for s in test],
                         'scans_per_sequence': {c.name: len(c) for c in train_caches}}
    write_json(out / 'summary.json', _json_safe(summary))
    (out / 'summary.md').write_text(summary_markdown(summary))
    write_ranking_csv(out / 'ranking.csv', list(rows.values()),
                      f'in-sample: train bags {"+".join(c.name for c in train_caches)}')
    write_params_file(
        out / 'best_mask.yaml', config_for_mask(config, chosen),
        header=(f'Band mask chosen by gft-odom search-bands ({search_cfg.strategy}, '
                f'registration mode {mode}) on {", ".join(c.name for c in train_caches)}.\n'
                f'In-sample ATE RMSE {_m(chosen_row["ate_rmse_m"])} m, the '
                f'{decision["chosen"]}:\n{decision["reason"]}.\nHeld-out: see summary.json.\n'
                'Load with filter_odom_node --ros-args --params-file THIS or '
                'gft-odom replay --config THIS.'))
    if figures:
        from gft_odom.bands.plots import (
            plot_band_correlation,
            plot_interval_counts,
            plot_top_masks,
        )
        label = 'in-sample (train)'
        plot_top_masks(out / 'fig6_top_masks.png', order, rows.get(BASELINE_KEY), label,
                       search_cfg.top_k_figure)
        plot_band_correlation(out / 'fig7_band_correlation.png',
                              correlation_table(list(rows.values())), label)
        plot_interval_counts(out / 'fig8_narrow_intervals.png',
                             interval_counts(list(rows.values()), search_cfg.top_k_intervals,
                                             search_cfg.n_intervals),
                             search_cfg.top_k_intervals, label)
    return summary


def _m(value) -> str:
    return '-' if value is None else f'{value:.4f}'


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def summary_markdown(summary: dict) -> str:
    """Human-readable summary; every number says whether it is in-sample or held-out."""
    def line(name, block):
        def f(v, fmt='.4f'):
            return '-' if v is None else format(v, fmt)
        c, b = block['chosen'], block['baseline'] or {}
        change = block.get('change_vs_baseline_pct')
        return (f'| {name} | {f(c["ate_rmse_m"])} | {f(b.get("ate_rmse_m"))} | '
                f'{f(change, "+.1f")} % | {f(c["paper_mse_m2"])} | '
                f'{f(c["points_kept_fraction"], ".3f")} | {c["fallbacks"]} |')

    m, d = summary['chosen_mask'], summary['decision']
    lines = [
        f'# Band search ({summary["strategy"]}, registration mode '
        f'{summary["registration_mode"]})', '',
        f'Chosen mask: n_bands = {m["n_bands"]}, band_mask = {m["band_mask"]} '
        f'("{m["bitstring"]}"), the {d["chosen"]}: {d["reason"]}.', '',
        f'In-sample ATE RMSE: identity (every band, {d["identity_key"]}) '
        f'{_m(d["identity_ate_rmse_m"])} m, best mask {d["best_key"]} '
        f'{_m(d["best_ate_rmse_m"])} m, run-to-run spread {_m(d["spread_m"])} m '
        f'({d["spread_method"]}). A mask is chosen only when it beats the identity by more '
        'than the spread.', '',
        f'Masks considered {summary["masks_considered"]}, evaluated (after deduplication) '
        f'{summary["masks_evaluated"]}.', '',
        '| numbers | ATE RMSE m (mask) | ATE RMSE m (unfiltered) | change | paper MSE m^2 | '
        'points kept | fallbacks |', '|---|---|---|---|---|---|---|',
        line('in-sample (train)', summary['in_sample']),
    ]
    if 'held_out' in summary:
        lines.append(line('held-out (test)', summary['held_out']))
    lines += ['', f'- in-sample: {IN_SAMPLE}',
              f'- held-out: {HELD_OUT}' if 'held_out' in summary else
              '- no test bags given: there is no held-out number; the in-sample error is '
              'optimistic.', '']
    return '\n'.join(lines)
