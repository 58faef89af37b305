"""Score one mask (or the unfiltered baseline) on cached sequences through the pipeline.

Each scan goes through `OdometryPipeline.register_frame(scan, freqs=...)`, the same loop the node
and the replay run, with the cached frequencies in place of a fresh spectral analysis: only the
keep-mask and the registration cost anything per mask.

A run can also be made with every scan shifted by a sub-voxel vector (`shift_m`): the voxel
grids then cut the same points elsewhere, a change that should not matter, and the poses are
mapped back to the sensor frame exactly, so what moves in the error is the search's own noise.
"""

from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np

from gft_odom.bands.cache import SequenceCache
from gft_odom.bands.masks import mask_key
from gft_odom.config import GftOdomConfig, with_values
from gft_odom.core.deskew import azimuth_time_offsets
from gft_odom.core.geometry import invert_transform
from gft_odom.core.metrics import TrajectoryEvaluator
from gft_odom.core.spectral.bands import BandMask
from gft_odom.core.trajectory import Trajectory
from gft_odom.core.types import Scan
from gft_odom.errors import GroundTruthError
from gft_odom.pipeline import OdometryPipeline

BASELINE_KEY = 'baseline'
# A shifted run's key: the mask's key, this, the shift as a fraction of the source voxel.
SHIFT_SEP = '@'
# Figures of a result that are averaged over sequences (the ranking uses the first).
AVERAGED = ('ate_rmse_m', 'ate_mean_m', 'paper_mse_m2', 'points_kept_fraction')


def config_for_mask(config: GftOdomConfig, mask: BandMask | None) -> GftOdomConfig:
    """`config` with the mask set (None: the unfiltered baseline, same registration)."""
    if mask is None:
        return with_values(config, {'pipeline.use_spectral_filter': False})
    return with_values(config, {'pipeline.use_spectral_filter': True,
                                'spectral.n_bands': mask.n_bands,
                                'spectral.band_mask': mask.as_list()})


def shifted_key(key: str, fraction: float) -> str:
    """Key of `key`'s run with the scans shifted by `fraction` of a source voxel."""
    return f'{key}{SHIFT_SEP}{fraction:.6g}'


def split_shifted_key(key: str) -> tuple[str, float | None]:
    """(mask key, voxel fraction or None) of a key made by `shifted_key` or a plain key."""
    base, sep, fraction = key.partition(SHIFT_SEP)
    return base, (float(fraction) if sep else None)


def shift_vector(config: GftOdomConfig, fraction: float) -> np.ndarray:
    """(3,) shift of `fraction` of a source voxel along each axis: every voxel grid the
    registration builds (source and map) moves against the points."""
    return np.full(3, fraction * config.registration.voxel_size_m)


def _shifted_scan(scan: Scan, shift_m: np.ndarray, config: GftOdomConfig) -> Scan:
    """`scan` moved by `shift_m`, with the per-point times of the unshifted points (azimuth
    times would otherwise move with the origin)."""
    times = scan.time_offset_s
    reg = config.registration
    if times is None and reg.deskew and reg.mode == 'default':
        times = azimuth_time_offsets(scan.points_xyz, reg.scan_period_s,
                                     reg.azimuth_stamp_at_sweep_end).astype(np.float32)
    return Scan(scan.stamp_ns, scan.points_xyz + shift_m, time_offset_s=times)


def _unshifted(estimate: Trajectory, shift_m: np.ndarray) -> Trajectory:
    """Poses of the sensor from those of the shifted frame S' (p' = p + shift), in the world
    the unshifted run would have had (its first pose is the same fixed start)."""
    to_sensor = np.eye(4)
    to_sensor[:3, 3] = shift_m  # T_S'_S
    if not len(estimate.poses):
        return estimate
    first = estimate.poses[0]
    world = first @ invert_transform(to_sensor) @ invert_transform(first)
    return Trajectory(estimate.stamps_ns.copy(), world @ estimate.poses @ to_sensor)


def run_sequence(seq: SequenceCache, config: GftOdomConfig, mask: BandMask | None,
                 shift_m: np.ndarray | None = None) -> dict:
    """Metrics of one mask on one cached sequence (`shift_m`: every scan moved by it)."""
    cfg = config_for_mask(config, mask)
    run_cfg = cfg
    if shift_m is not None:
        # The cached scans are cropped already: the crop must not cut them again elsewhere.
        run_cfg = with_values(cfg, {'pipeline.min_range_m': 0.0,
                                    'pipeline.max_range_m': math.inf})
    pipeline = OdometryPipeline(run_cfg)
    kept = in_total = 0
    for i in range(len(seq)):
        scan = seq.scan(i)
        if shift_m is not None:
            scan = _shifted_scan(scan, shift_m, cfg)
        freqs = seq.frequencies(i, mask.n_bands) if mask is not None else None
        result = pipeline.register_frame(scan, freqs=freqs)  # rejected scans keep nothing
        kept += result.n_points_kept
        in_total += int(seq.points_in[i])
    estimate = pipeline.sensor_trajectory()
    if shift_m is not None:
        estimate = _unshifted(estimate, shift_m)
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
                  mask: BandMask | None, shift_m: np.ndarray | None = None) -> dict:
    """One result row: per-sequence metrics and their means (None mask: the baseline)."""
    t0 = time.perf_counter()
    per_seq = {seq.name: run_sequence(seq, config, mask, shift_m) for seq in sequences}
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
