"""Figures of the band search, after the paper's Figures 6, 7 and 8 (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from gft_odom.bands.evaluate import score
from gft_odom.bands.masks import parse_mask_key
from gft_odom.figures import pyplot, save_figure


def plot_top_masks(path: str | Path, ranked_rows: Sequence[dict], baseline: dict | None,
                   label: str, top_k: int = 10) -> Path:
    """Figure 6: the best masks as bars over the normalised spectrum, one row per mask."""
    plt = pyplot()
    rows = list(ranked_rows[:top_k])
    fig, ax = plt.subplots(figsize=(8, 0.45 * max(len(rows), 1) + 1.4))
    for i, row in enumerate(rows):
        mask = parse_mask_key(row['key'])
        width = 1.0 / mask.n_bands
        for b in range(1, mask.n_bands + 1):
            kept = b in mask.bands
            ax.barh(i, width, left=(b - 1) * width, height=0.8,
                    color='#1b4f9c' if kept else '#e6e6e6', edgecolor='white', linewidth=0.8)
        ax.text(1.01, i, f'{score(row):.3f} m  B={mask.n_bands} {mask.as_bitstring()}',
                va='center', fontsize=8)
    ax.set_yticks(range(len(rows)), [f'#{i + 1}' for i in range(len(rows))])
    ax.invert_yaxis()
    ax.set_xlim(0.0, 1.0)
    ax.set_xlabel('normalised graph frequency nu = lambda / lambda_max (kept bands dark)')
    base = f'; unfiltered {score(baseline):.3f} m' if baseline else ''
    ax.set_title(f'Top {len(rows)} band masks by ATE RMSE, {label}{base}', fontsize=9)
    return save_figure(fig, path)


def plot_band_correlation(path: str | Path, table: dict[int, np.ndarray], label: str) -> Path:
    """Figure 7: Pearson r of each band's presence with the error, one group per B."""
    plt = pyplot()
    counts = sorted(table)
    fig, axes = plt.subplots(1, len(counts), figsize=(2.0 * len(counts) + 1.5, 3.2),
                             sharey=True, squeeze=False)
    for ax, n in zip(axes[0], counts):
        corr = table[n]
        colours = ['#2a8fa8' if c < 0 else '#c0504d' for c in np.nan_to_num(corr)]
        ax.bar(np.arange(1, n + 1), np.nan_to_num(corr), color=colours)
        ax.axhline(0.0, color='black', linewidth=0.6)
        ax.set_title(f'B = {n}', fontsize=9)
        ax.set_xticks(np.arange(1, n + 1))
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel('Pearson r (band present, ATE RMSE)')
    fig.supxlabel('band b of B (1 = lowest graph frequency nu, B = highest)', fontsize=8)
    axes[0][0].set_ylim(-1.0, 1.0)
    fig.suptitle(f'Band presence vs error (negative: keeping the band lowers the error), '
                 f'{label}', fontsize=9)
    return save_figure(fig, path)


def plot_interval_counts(path: str | Path, counts: np.ndarray, top_k: int, label: str) -> Path:
    """Figure 8: how often each narrow nu interval lies in the best masks."""
    plt = pyplot()
    n = counts.size
    fig, ax = plt.subplots(figsize=(8, 3))
    ax.fill_between((np.arange(n) + 0.5) / n, counts, step='mid', color='#55c49a')
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0, top_k + 0.5)
    ax.set_xlabel(f'normalised graph frequency nu ({n} narrow intervals)')
    ax.set_ylabel(f'count in the {top_k} best masks')
    ax.set_title(f'Narrow intervals kept by the {top_k} best masks, {label}', fontsize=9)
    return save_figure(fig, path)
