"""Markdown tables of run metrics: one title and one number format per metric, for every table.

The demo's table and the benchmark's summary show the same metrics; each picks its columns
here by key, so a metric reads the same wherever it appears.
"""

from __future__ import annotations

import math

# metric key -> (column title, format)
METRIC_COLUMNS = {
    'ate_rmse_m': ('ATE RMSE [m]', '{:.3f}'),
    'ate_mean_m': ('ATE mean [m]', '{:.3f}'),
    'end_error_m': ('end-point error [m]', '{:.3f}'),
    'paper_mse_m2': ('paper MSE [m^2]', '{:.4f}'),
    'rpe_drift_pct': ('RPE drift [%]', '{:.2f}'),
    'stamp_best_shift_ms': ('best stamp shift [ms]', '{:+.0f}'),
    'latency_median_ms': ('latency median [ms]', '{:.1f}'),
    'latency_p95_ms': ('latency p95 [ms]', '{:.1f}'),
    'points_kept_fraction': ('points kept', '{:.1%}'),
    'points_kept_mean': ('points kept', '{:.0f}'),
    'points_kept_pct': ('kept [%]', '{:.1f}'),
    'mask_text': ('band mask', '{}'),
    'fallbacks': ('fallbacks', '{:d}'),
}


def columns(*keys: str) -> tuple[tuple[str, str, str], ...]:
    """(title, key, format) of each metric key, in the order given."""
    return tuple((METRIC_COLUMNS[key][0], key, METRIC_COLUMNS[key][1]) for key in keys)


def cell(value, fmt: str) -> str:
    """One formatted value; 'n/a' when missing or not finite."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return 'n/a'
    return fmt.format(value)


def markdown_table(rows, cols: tuple[tuple[str, str, str], ...], first_title: str,
                   align_right: bool = False) -> str:
    """A Markdown table: one row per (name, metrics) pair, one column per (title, key, fmt)."""
    lines = [f'| {first_title} | ' + ' | '.join(title for title, _, _ in cols) + ' |',
             '|---|' + ('---:|' if align_right else '---|') * len(cols)]
    for name, metrics in rows:
        cells = [cell(metrics.get(key), fmt) for _, key, fmt in cols]
        lines.append(f'| {name} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def accuracy_line(metrics: dict) -> str:
    """One line of the accuracy figures of a run, e.g. for a command's printed summary."""
    parts = [f'{METRIC_COLUMNS[key][0]} {cell(metrics.get(key), METRIC_COLUMNS[key][1])}'
             for key in ('ate_rmse_m', 'ate_mean_m', 'end_error_m', 'rpe_drift_pct',
                         'stamp_best_shift_ms')]
    return ', '.join(parts)
