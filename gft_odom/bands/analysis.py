"""The paper's analysis of a finished search: ranking, per-band Pearson correlation with the
error (Figure 7) and narrow-interval counts in the best masks (Figure 8)."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from gft_odom.bands.evaluate import BASELINE_KEY, score
from gft_odom.bands.masks import narrow_interval_membership, parse_mask_key
from gft_odom.core.spectral.bands import BandMask, band_of_nu


def ranked(rows: Sequence[dict], unique: bool = True) -> list[dict]:
    """Mask rows best first (mean ATE RMSE, then fewer points kept, then key); the baseline and
    (with `unique`) rows that duplicate another mask's kept points are left out."""
    masks = [r for r in rows if r['key'] != BASELINE_KEY
             and not (unique and r.get('duplicate_of'))]
    return sorted(masks, key=lambda r: (score(r), r.get('points_kept_fraction') or 0.0,
                                        r['key']))


def band_correlation(rows: Sequence[dict], n_bands: int) -> np.ndarray:
    """(B,) Pearson r between band b's presence (0/1 dummy) and the ATE RMSE over all masks
    of `n_bands` bands; negative r: masks keeping band b tend to have a lower error. NaN when
    either has no variance or fewer than 3 masks were scored."""
    sub = [r for r in rows if r['key'] != BASELINE_KEY and r['n_bands'] == n_bands
           and math.isfinite(score(r))]
    out = np.full(n_bands, np.nan)
    if len(sub) < 3:
        return out
    err = np.array([score(r) for r in sub])
    present = np.array([[b in r['bands'] for b in range(1, n_bands + 1)] for r in sub],
                       dtype=np.float64)
    if err.std() == 0.0:
        return out
    for b in range(n_bands):
        x = present[:, b]
        if x.std() > 0.0:
            out[b] = float(np.corrcoef(x, err)[0, 1])
    return out


def correlation_table(rows: Sequence[dict]) -> dict[int, np.ndarray]:
    """Band correlation for every B present in `rows`."""
    counts = sorted({r['n_bands'] for r in rows if r['key'] != BASELINE_KEY})
    return {n: band_correlation(rows, n) for n in counts}


def interval_counts(rows: Sequence[dict], top_k: int = 20, n_intervals: int = 1000
                    ) -> np.ndarray:
    """How many of the `top_k` best masks cover each of `n_intervals` narrow nu intervals."""
    best = [parse_mask_key(r['key']) for r in ranked(rows)[:top_k]]
    return narrow_interval_membership(best, n_intervals)


def correlation_at_nu(table: dict[int, np.ndarray], nu: np.ndarray) -> np.ndarray:
    """Mean over B of the correlation of the band containing each nu (NaNs skipped)."""
    nu = np.asarray(nu, dtype=np.float64)
    values = [corr[band_of_nu(nu, n) - 1]
              for n, corr in table.items()]
    if not values:
        return np.full(nu.shape, np.nan)
    stacked = np.array(values)
    valid = ~np.isnan(stacked)
    total = np.where(valid, stacked, 0.0).sum(axis=0)
    count = valid.sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


CSV_COLUMNS = ('rank', 'key', 'n_bands', 'mask', 'bands', 'ate_rmse_m', 'ate_mean_m',
               'paper_mse_m2', 'points_kept_fraction', 'fallbacks', 'duplicate_of',
               'vs_baseline_pct', 'evaluated_on')


def write_ranking_csv(path: str | Path, rows: Sequence[dict], label: str) -> Path:
    """Every mask (duplicates included, after their representative), best first; one column
    per training sequence too. `label` says what the numbers are (in-sample on which bags)."""
    path = Path(path)
    all_rows = ranked(rows, unique=False)
    baseline = next((r for r in rows if r['key'] == BASELINE_KEY), None)
    base = score(baseline) if baseline is not None else math.nan
    seq_names = sorted({n for r in rows for n in r.get('per_sequence', {})})
    with path.open('w', newline='') as f:
        w = csv.writer(f)
        w.writerow([*CSV_COLUMNS, *(f'ate_rmse_m[{n}]' for n in seq_names)])
        ordered = ([baseline] if baseline is not None else []) + all_rows
        for rank, r in enumerate(ordered):
            err = score(r)
            vs = 100.0 * (err - base) / base if base and math.isfinite(err) else math.nan
            w.writerow([
                rank, r['key'], r['n_bands'], r['mask'], ' '.join(map(str, r['bands'])),
                _fmt(r['ate_rmse_m']), _fmt(r['ate_mean_m']), _fmt(r['paper_mse_m2']),
                _fmt(r['points_kept_fraction']), r['fallbacks'], r.get('duplicate_of') or '',
                _fmt(vs), label,
                *(_fmt(r['per_sequence'].get(n, {}).get('ate_rmse_m')) for n in seq_names)])
    return path


def _fmt(value) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ''
    return f'{value:.6g}' if isinstance(value, float) else str(value)


def best_mask(rows: Sequence[dict]) -> BandMask:
    """The best-ranked mask of `rows` (ValueError when there is none)."""
    best = ranked(rows)
    if not best:
        raise ValueError('no mask result to choose from')
    return parse_mask_key(best[0]['key'])
