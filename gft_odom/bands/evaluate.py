"""Score one mask (or the unfiltered baseline) on cached sequences through the pipeline.

Each scan goes through `OdometryPipeline.register_frame(scan, freqs=...)`, the same loop the node
and the replay run, with the cached frequencies in place of a fresh spectral analysis: only the
keep-mask and the registration cost anything per mask.
"""

from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np

from gft_odom.bands.cache import SequenceCache
from gft_odom.bands.masks import mask_key
from gft_odom.config import GftOdomConfig, with_values
from gft_odom.core.metrics import TrajectoryEvaluator
from gft_odom.core.spectral.bands import BandMask
from gft_odom.errors import GroundTruthError
from gft_odom.pipeline import OdometryPipeline

BASELINE_KEY = 'baseline'
# Figures of a result that are averaged over sequences (the ranking uses the first).
AVERAGED = ('ate_rmse_m', 'ate_mean_m', 'paper_mse_m2', 'points_kept_fraction')


def config_for_mask(config: GftOdomConfig, mask: BandMask | None) -> GftOdomConfig:
    """`config` with the mask set (None: the unfiltered baseline, same registration)."""
    if mask is None:
        return with_values(config, {'pipeline.use_spectral_filter': False})
    return with_values(config, {'pipeline.use_spectral_filter': True,
                                'spectral.n_bands': mask.n_bands,
                                'spectral.band_mask': mask.as_list()})


def run_sequence(seq: SequenceCache, config: GftOdomConfig, mask: BandMask | None) -> dict:
    """Metrics of one mask on one cached sequence."""
    cfg = config_for_mask(config, mask)
    pipeline = OdometryPipeline(cfg)
    kept = in_total = 0
    for i in range(len(seq)):
        scan = seq.scan(i)
        freqs = seq.frequencies(i, mask.n_bands) if mask is not None else None
        result = pipeline.register_frame(scan, freqs=freqs)  # rejected scans keep nothing
        kept += result.n_points_kept
        in_total += int(seq.points_in[i])
    estimate = pipeline.sensor_trajectory()
    if seq.ground_truth_is_gps:
        estimate = estimate.with_body_offset(cfg.ground_truth.T_lidar_gps())
    out = {'points_kept_fraction': kept / max(in_total, 1),
           'fallbacks': int(sum(n for s, n in pipeline.status_counts.items()
                                if s.startswith('fallback'))),
           'n_scans': len(seq)}
    try:
        m = TrajectoryEvaluator.from_config(cfg.evaluation).evaluate(estimate, seq.ground_truth)
        out.update(ate_rmse_m=m['ate_rmse_m'], ate_mean_m=m['ate_mean_m'],
                   paper_mse_m2=m['paper_mse_m2'], rpe_drift_pct=m['rpe_drift_pct'])
    except GroundTruthError as exc:
        out.update(ate_rmse_m=None, ate_mean_m=None, paper_mse_m2=None, rpe_drift_pct=None,
                   error=str(exc))
    return out


def evaluate_mask(sequences: Sequence[SequenceCache], config: GftOdomConfig,
                  mask: BandMask | None) -> dict:
    """One result row: per-sequence metrics and their means (None mask: the baseline)."""
    t0 = time.perf_counter()
    per_seq = {seq.name: run_sequence(seq, config, mask) for seq in sequences}
    row: dict = {
        'key': BASELINE_KEY if mask is None else mask_key(mask),
        'n_bands': 0 if mask is None else mask.n_bands,
        'mask': '' if mask is None else mask.as_bitstring(),
        'bands': [] if mask is None else mask.as_list(),
        'n_kept_bands': 0 if mask is None else len(mask.bands),
    }
    for name in AVERAGED:
        values = [r[name] for r in per_seq.values()]
        row[name] = (None if any(v is None for v in values)
                     else float(np.mean(values)))
    row['fallbacks'] = int(sum(r['fallbacks'] for r in per_seq.values()))
    row['per_sequence'] = per_seq
    row['eval_s'] = time.perf_counter() - t0
    return row


def score(row: dict) -> float:
    """Ranking value of a result row: mean ATE RMSE, +inf when it could not be evaluated."""
    value = row.get('ate_rmse_m')
    return float(value) if value is not None and math.isfinite(value) else math.inf
