"""Trajectory evaluation: ATE, the stamp audit, the paper's MSE and RPE drift.

Association in time and Umeyama alignment are in `alignment`.

CitrusFarm's own scoring (UCR-Robotics/Odometry-Benchmark) is here too: the *mean* position
error after a rigid (Horn/Umeyama, no scale) alignment of the positions, the estimate first moved
to the GPS antenna by the LiDAR -> GPS lever arm (done by the caller: `replay.
estimate_for_ground_truth`), i.e. `ate_mean_m` in 'position' mode; and the end-point error,
`end_error_m`, the distance between the aligned final positions. (Their evaluation.py stores
the norm of the estimate's final position, the gap back to its start: the same figure on a drive
that ends where it began. Ours compares with the ground truth's final position, for any drive.)

Pure numpy (checked against `evo` in the tests, never imported here). Conventions:

- `est` is the odometry, `ref` the ground truth; poses are `T_world_body`.
- Alignment maps the estimate's world into the reference's world:
  `p_ref ~ s R p_est + t`, stored as the 4x4 `T_ref_est = [[s R, t], [0, 1]]`.
- Modes: `'se3'` (rigid, also scores orientations), `'sim3'` (rigid + scale) and `'position'`
  (rigid, never reads orientations: GPS ground truth such as CitrusFarm's `/gps/fix/odometry`
  carries no meaningful orientation).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from gft_odom.core.alignment import (
    DEFAULT_MAX_DIFF_S,
    DEFAULT_MAX_GAP_S,
    MATCH_METHODS,
    MIN_MATCHED,
    Matched,
    check_sorted,
    interpolate_positions,
    match_trajectories,
    rotation_angles_rad,
    similarity_matrix,
    time_range,
    umeyama_alignment,
)
from gft_odom.core.constants import NS_PER_S
from gft_odom.core.geometry import invert_transform
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import ConfigError, GroundTruthError

logger = logging.getLogger(__name__)

ATE_MODES = ('se3', 'sim3', 'position')
DEFAULT_LENGTHS_M = (5.0, 10.0, 20.0, 50.0)
DEFAULT_MODE = 'position'
DEFAULT_MATCH = 'nearest'



@dataclass(frozen=True)
class MetricsConfig:
    """Evaluation settings shared by the offline tools (replay, band search, benchmarks)."""

    # 'position' by default: the CitrusFarm ground truth is a GPS antenna track, no orientation.
    mode: str = DEFAULT_MODE
    # Half a LiDAR period at 10 Hz: a ground-truth stamp further away belongs to another scan.
    max_diff_s: float = DEFAULT_MAX_DIFF_S
    # How an estimated pose finds its ground truth: 'interpolate' resamples the GPS track
    # linearly at the estimate's stamp; 'nearest' takes the closest sample within max_diff_s
    # and so charges v x (stamp difference) along the track (the simulator's GPS runs 37 ms
    # after the scans: 4-7 cm at 1-1.8 m/s, and it favoured poses that lag their stamps, as
    # an undeskewed scan's does). 'auto': interpolate positions, nearest when orientations
    # are compared (mode 'se3'). (The functions' own default stays 'nearest'.)
    match: str = 'auto'
    # With 'interpolate', no position is invented across a ground-truth gap longer than this.
    max_gap_s: float = DEFAULT_MAX_GAP_S
    # KITTI uses 100..800 m on cars; orchard rows are ~100 m, so shorter segments.
    lengths_m: tuple[float, ...] = DEFAULT_LENGTHS_M

    def validate(self) -> None:
        """Raise ConfigError naming the first value that cannot work."""
        _check_args(self.mode, self.max_diff_s, self.match, self.max_gap_s, self.lengths_m)


def _check_args(mode: str = DEFAULT_MODE, max_diff_s: float = DEFAULT_MAX_DIFF_S,
                match: str = DEFAULT_MATCH, max_gap_s: float = DEFAULT_MAX_GAP_S,
                lengths_m=DEFAULT_LENGTHS_M) -> None:
    """Raise ConfigError naming the first invalid evaluation argument."""
    if mode not in ATE_MODES:
        raise ConfigError(f'metrics mode must be one of {ATE_MODES}, got {mode!r}')
    if match not in MATCH_METHODS:
        raise ConfigError(f'metrics match must be one of {MATCH_METHODS}, got {match!r}')
    if not (math.isfinite(max_diff_s) and max_diff_s >= 0.0):
        raise ConfigError(f'max_diff_s must be a finite number >= 0, got {max_diff_s}')
    if not (math.isfinite(max_gap_s) and max_gap_s > 0.0):
        raise ConfigError(f'max_gap_s must be a finite number > 0, got {max_gap_s}')
    lengths = list(lengths_m)
    if not lengths or not all(math.isfinite(v) and v > 0.0 for v in lengths):
        raise ConfigError(f'lengths_m must be a non-empty list of numbers > 0, got {lengths}')


def _match(est: Trajectory, ref: Trajectory, max_diff_s: float, match: str, max_gap_s: float,
           need_orientation: bool) -> Matched:
    _check_args(max_diff_s=max_diff_s, match=match, max_gap_s=max_gap_s)
    return match_trajectories(est, ref, max_diff_s, match, max_gap_s, need_orientation)


# --- absolute trajectory error ---------------------------------------------------------------

@dataclass
class AteResult:
    """Absolute trajectory error after alignment (position errors in metres)."""

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    std_m: float
    n: int
    mode: str
    scale: float
    rotation_rmse_deg: float  # nan unless mode == 'se3'
    T_ref_est: np.ndarray  # (4, 4): p_ref ~ T_ref_est applied to p_est; [:3,:3] is s R
    # Per matched pose, and which est poses were matched (for plots); kept out of the repr.
    errors_m: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    est_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), repr=False)

    @property
    def end_error_m(self) -> float:
        """Distance between the aligned final positions (the last matched pair), in metres."""
        return float(self.errors_m[-1]) if self.errors_m.size else math.nan


def _ate_from_matched(m: Matched, mode: str) -> AteResult:
    rotation, translation, scale = umeyama_alignment(m.p_est, m.p_ref, with_scale=mode == 'sim3')
    p_aligned = scale * m.p_est @ rotation.T + translation
    errors = np.linalg.norm(p_aligned - m.p_ref, axis=1)
    rotation_rmse_deg = math.nan
    if mode == 'se3':
        # Error rotation R_ref^T (R_align R_est), as evo's APE on the aligned trajectory.
        r_err = np.swapaxes(m.poses_ref[:, :3, :3], -1, -2) @ (rotation @ m.poses_est[:, :3, :3])
        angles_deg = np.degrees(rotation_angles_rad(r_err))
        rotation_rmse_deg = float(np.sqrt(np.mean(angles_deg**2)))
    return AteResult(
        rmse_m=float(np.sqrt(np.mean(errors**2))), mean_m=float(errors.mean()),
        median_m=float(np.median(errors)), max_m=float(errors.max()), std_m=float(errors.std()),
        n=int(errors.shape[0]), mode=mode, scale=float(scale),
        rotation_rmse_deg=rotation_rmse_deg,
        T_ref_est=similarity_matrix(rotation, translation, scale),
        errors_m=errors, est_idx=m.est_idx)


def ate(est: Trajectory, ref: Trajectory, mode: str = 'se3',
        max_diff_s: float = DEFAULT_MAX_DIFF_S,
        match: str = DEFAULT_MATCH, max_gap_s: float = DEFAULT_MAX_GAP_S) -> AteResult:
    """Absolute trajectory error of `est` against `ref` after Umeyama alignment.

    The alignment uses the matched positions only (rigid for 'se3' and 'position', with scale
    for 'sim3'); the error is the position distance after alignment. 'se3' also reports the
    RMSE of the orientation error angle; 'position' never reads orientations.
    """
    _check_args(mode, max_diff_s, match, max_gap_s)
    m = _match(est, ref, max_diff_s, match, max_gap_s, need_orientation=mode == 'se3')
    return _ate_from_matched(m, mode)


# --- stamp audit -----------------------------------------------------------------------------

# The shifts the audit tries (-100..+100 ms in 5 ms steps) and how far from zero a correctly
# stamped method's best shift may be.
STAMP_AUDIT_SHIFTS_S = tuple(round(0.005 * k, 3) for k in range(-20, 21))
STAMP_AUDIT_TOLERANCE_S = 0.010


@dataclass(frozen=True)
class StampAudit:
    """Position ATE RMSE of one trajectory with its stamps shifted by each of `shifts_s`."""

    shifts_s: np.ndarray
    rmse_m: np.ndarray
    n: int  # poses scored at every shift

    @property
    def best_shift_s(self) -> float:
        """The shift that scores best: ~0 for a trajectory stamped where its poses hold."""
        return float(self.shifts_s[int(np.argmin(self.rmse_m))])

    @property
    def best_rmse_m(self) -> float:
        """The ATE RMSE at the best shift."""
        return float(np.min(self.rmse_m))

    @property
    def rmse_at_zero_m(self) -> float:
        """The ATE RMSE at the stamps as written."""
        return float(self.rmse_m[int(np.argmin(np.abs(self.shifts_s)))])

    def stamped_right(self, tolerance_s: float = STAMP_AUDIT_TOLERANCE_S) -> bool:
        """Whether the best shift is within `tolerance_s` of zero."""
        return abs(self.best_shift_s) <= tolerance_s + 1e-12


def stamp_audit(est: Trajectory, ref: Trajectory, shifts_s=STAMP_AUDIT_SHIFTS_S,
                max_gap_s: float = DEFAULT_MAX_GAP_S) -> StampAudit:
    """Score `est` against `ref` with every stamp moved by each of `shifts_s`.

    A pose stamped `delta` before the time it holds scores best at a shift of +`delta`: the
    audit finds where a method's poses hold, whatever its adapter claims. Positions only
    (rigid alignment, as `ate(mode='position')`), the reference interpolated at the shifted
    stamps; only the poses matched at every shift count, so each shift scores the same poses.
    """
    _check_args(max_gap_s=max_gap_s)
    check_sorted(est, 'estimated')
    shifts = np.asarray(shifts_s, dtype=float).reshape(-1)
    if shifts.size == 0 or not np.isfinite(shifts).all():
        raise ConfigError(f'stamp_audit needs finite shifts, got {list(shifts)}')
    shifts_ns = np.round(shifts * NS_PER_S).astype(np.int64)
    p_ref = np.stack([interpolate_positions(ref, est.stamps_ns + d, max_gap_s)
                      for d in shifts_ns])  # (S, N, 3)
    common = np.isfinite(p_ref).all(axis=(0, 2)) & np.isfinite(est.positions_xyz).all(axis=1)
    if int(common.sum()) < MIN_MATCHED:
        raise GroundTruthError(
            f'only {int(common.sum())} estimated stamps overlap the reference at every shift '
            f'of {shifts.min():+.3f}..{shifts.max():+.3f} s. Estimate: {time_range(est)}; '
            f'reference: {time_range(ref)}')
    p_est = est.positions_xyz[common]
    rmse = np.empty(shifts.size)
    for k in range(shifts.size):  # one alignment per shift, vectorised over the poses
        rotation, translation, _ = umeyama_alignment(p_est, p_ref[k, common])
        errors = np.linalg.norm(p_est @ rotation.T + translation - p_ref[k, common], axis=1)
        rmse[k] = float(np.sqrt(np.mean(errors ** 2)))
    return StampAudit(shifts, rmse, int(common.sum()))


def paper_mse(est: Trajectory, ref: Trajectory, max_diff_s: float = DEFAULT_MAX_DIFF_S,
              match: str = DEFAULT_MATCH, max_gap_s: float = DEFAULT_MAX_GAP_S) -> float:
    """The paper's "MSE": mean squared position error in m^2 after a rigid alignment.

    Alignment: rigid Umeyama (rotation + translation, no scale) on the matched positions, as
    `ate(mode='position')`; so `paper_mse == ate_rmse_m ** 2`. The paper's figures (4.37 m,
    1.22 m) are quoted in metres, so compare them with `ate_rmse_m`, i.e. sqrt of this value.
    """
    result = ate(est, ref, mode='position', max_diff_s=max_diff_s, match=match,
                 max_gap_s=max_gap_s)
    return float(np.mean(result.errors_m**2))


# --- relative error over distance (drift) ----------------------------------------------------

@dataclass
class RpeSegments:
    """Every segment of one length: start/end indices into `est`, errors per segment."""

    length_m: float
    first_idx: np.ndarray  # (K,) int, into est
    last_idx: np.ndarray  # (K,) int, into est
    error_pct: np.ndarray  # (K,) translation error / length * 100
    rot_error_deg_per_m: np.ndarray  # (K,) nan in the position-only variant


def _segment_pairs(p_ref: np.ndarray, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For every start i, the first j whose reference path distance from i exceeds length_m."""
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p_ref, axis=0), axis=1))])
    last = np.searchsorted(travelled, travelled + length_m, side='right')
    first = np.flatnonzero(last < travelled.shape[0])
    return first, last[first]


def _segments_from_matched(m: Matched, length_m: float, use_orientation: bool,
                           p_est_aligned: np.ndarray | None) -> RpeSegments:
    first, last = _segment_pairs(m.p_ref, length_m)
    if use_orientation:
        # KITTI: E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j), error |t(E)| and angle(E) per metre.
        rel_ref = invert_transform(m.poses_ref[first]) @ m.poses_ref[last]
        rel_est = invert_transform(m.poses_est[first]) @ m.poses_est[last]
        error_pose = invert_transform(rel_ref) @ rel_est
        error_m = np.linalg.norm(error_pose[:, :3, 3], axis=1)
        rot_deg_per_m = np.degrees(rotation_angles_rad(error_pose[:, :3, :3])) / length_m
    else:
        # Displacements in the reference world after one rigid alignment of est.
        d_est = p_est_aligned[last] - p_est_aligned[first]
        d_ref = m.p_ref[last] - m.p_ref[first]
        error_m = np.linalg.norm(d_est - d_ref, axis=1)
        rot_deg_per_m = np.full(first.shape[0], np.nan)
    return RpeSegments(float(length_m), m.est_idx[first], m.est_idx[last],
                       error_m / length_m * 100.0, rot_deg_per_m)


def _aligned_positions(m: Matched) -> np.ndarray:
    rotation, translation, _ = umeyama_alignment(m.p_est, m.p_ref, with_scale=False)
    return m.p_est @ rotation.T + translation


def rpe_segments(est: Trajectory, ref: Trajectory, length_m: float,
                 use_orientation: bool = False, max_diff_s: float = DEFAULT_MAX_DIFF_S,
                 match: str = DEFAULT_MATCH, max_gap_s: float = DEFAULT_MAX_GAP_S) -> RpeSegments:
    """All segments of one length with their errors (see `rpe_drift` for the definitions)."""
    _check_args(max_diff_s=max_diff_s, match=match, max_gap_s=max_gap_s, lengths_m=(length_m,))
    m = _match(est, ref, max_diff_s, match, max_gap_s, need_orientation=use_orientation)
    aligned = None if use_orientation else _aligned_positions(m)
    return _segments_from_matched(m, length_m, use_orientation, aligned)


def _drift_from_matched(m: Matched, lengths_m, use_orientation: bool) -> dict:
    aligned = None if use_orientation else _aligned_positions(m)
    segments = [_segments_from_matched(m, float(length), use_orientation, aligned)
                for length in lengths_m]
    errors = np.concatenate([s.error_pct for s in segments])
    rot = np.concatenate([s.rot_error_deg_per_m for s in segments])
    return {
        'lengths_m': [s.length_m for s in segments],
        'drift_pct_per_length': [float(s.error_pct.mean()) if s.error_pct.size else math.nan
                                 for s in segments],
        'count_per_length': [int(s.error_pct.size) for s in segments],
        'drift_pct': float(errors.mean()) if errors.size else math.nan,
        'rot_drift_deg_per_m': float(rot.mean()) if use_orientation and rot.size else math.nan,
        'use_orientation': bool(use_orientation),
    }


def rpe_drift(est: Trajectory, ref: Trajectory, lengths_m=DEFAULT_LENGTHS_M,
              use_orientation: bool = False, max_diff_s: float = DEFAULT_MAX_DIFF_S,
              match: str = DEFAULT_MATCH,
              max_gap_s: float = DEFAULT_MAX_GAP_S) -> dict:
    """KITTI-style drift: relative translation error over travelled distance, in %.

    Segments: for every matched start frame i (step 1) and each length L, j is the first frame
    whose path distance along the reference from i exceeds L. Segment error, as % of L:

    - `use_orientation=False` (GPS ground truth): est is aligned to ref once (rigid Umeyama on
      positions), then `|(p_est[j] - p_est[i]) - (p_ref[j] - p_ref[i])| / L * 100`: the error of
      the displacement vector in the reference world. Reads no orientation; a heading error
      early in the run shows up as drift later, as it should for odometry.
    - `use_orientation=True` (full KITTI): `E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`, error
      `|t(E)| / L * 100`, and `angle(E) / L` in deg/m; invariant to any rigid motion of est,
      so no alignment.

    Returns a JSON-friendly dict: `lengths_m`, `drift_pct_per_length` (nan where a length
    exceeds the trajectory), `count_per_length` (0 there), `drift_pct` (mean over all segments
    of all lengths, pooled as the KITTI devkit does), `rot_drift_deg_per_m` (nan unless
    orientations are used), `use_orientation`.
    """
    _check_args(max_diff_s=max_diff_s, match=match, max_gap_s=max_gap_s, lengths_m=lengths_m)
    m = _match(est, ref, max_diff_s, match, max_gap_s, need_orientation=use_orientation)
    return _drift_from_matched(m, lengths_m, use_orientation)


# --- everything at once ----------------------------------------------------------------------

@dataclass
class TrajectoryMetrics:
    """The accuracy figures of one run, flattened by `as_dict` for JSON results files."""

    ate_rmse_m: float
    ate_mean_m: float
    ate_median_m: float
    ate_max_m: float
    ate_std_m: float
    paper_mse_m2: float
    # Distance between the last matched positions after the rigid alignment (the paper's MSE
    # alignment, CitrusFarm's), whatever `mode` is; with ate_mean_m in 'position' mode this is
    # CitrusFarm's own scoring.
    end_error_m: float
    rpe_drift_pct: float
    n_matched: int
    path_length_m: float
    mode: str
    scale: float
    rotation_rmse_deg: float
    rpe_lengths_m: tuple[float, ...] = ()
    rpe_drift_pct_per_length: tuple[float, ...] = ()
    rpe_count_per_length: tuple[int, ...] = ()

    def as_dict(self) -> dict:
        """Flat dict of str/int/float/None; NaN becomes None (strict JSON has no NaN)."""
        out: dict = {}
        for name in ('ate_rmse_m', 'ate_mean_m', 'ate_median_m', 'ate_max_m', 'ate_std_m',
                     'paper_mse_m2', 'end_error_m', 'rpe_drift_pct', 'n_matched',
                     'path_length_m', 'mode', 'scale', 'rotation_rmse_deg'):
            out[name] = getattr(self, name)
        for length, drift, count in zip(self.rpe_lengths_m, self.rpe_drift_pct_per_length,
                                        self.rpe_count_per_length):
            out[f'rpe_drift_pct_{length:g}m'] = drift
            out[f'rpe_count_{length:g}m'] = count
        return {k: (None if isinstance(v, float) and math.isnan(v) else v)
                for k, v in out.items()}


class TrajectoryEvaluator:
    """ATE, paper MSE and RPE drift from one association and one alignment."""

    def __init__(self, mode: str = DEFAULT_MODE, max_diff_s: float = DEFAULT_MAX_DIFF_S,
                 lengths_m: tuple[float, ...] = DEFAULT_LENGTHS_M, match: str = DEFAULT_MATCH,
                 max_gap_s: float = DEFAULT_MAX_GAP_S) -> None:
        _check_args(mode, max_diff_s, match, max_gap_s, lengths_m)
        self.mode = mode
        self.max_diff_s = float(max_diff_s)
        self.lengths_m = tuple(float(v) for v in lengths_m)
        self.match = match
        self.max_gap_s = float(max_gap_s)

    @classmethod
    def from_config(cls, cfg: MetricsConfig) -> 'TrajectoryEvaluator':
        """An evaluator with the settings of `cfg` (validated)."""
        cfg.validate()
        return cls(cfg.mode, cfg.max_diff_s, cfg.lengths_m, cfg.match, cfg.max_gap_s)

    def metrics(self, est: Trajectory, ref: Trajectory) -> TrajectoryMetrics:
        """All figures; RPE uses orientations only in 'se3' mode."""
        use_orientation = self.mode == 'se3'
        m = _match(est, ref, self.max_diff_s, self.match, self.max_gap_s,
                   need_orientation=use_orientation)
        ate_result = _ate_from_matched(m, self.mode)
        # se3 and position share the rigid alignment the paper's MSE uses; sim3 does not.
        rigid = ate_result if self.mode != 'sim3' else _ate_from_matched(m, 'position')
        mse = float(np.mean(rigid.errors_m**2))
        drift = _drift_from_matched(m, self.lengths_m, use_orientation)
        path_length_m = float(np.linalg.norm(np.diff(m.p_ref, axis=0), axis=1).sum())
        return TrajectoryMetrics(
            ate_rmse_m=ate_result.rmse_m, ate_mean_m=ate_result.mean_m,
            ate_median_m=ate_result.median_m, ate_max_m=ate_result.max_m,
            ate_std_m=ate_result.std_m, paper_mse_m2=mse, end_error_m=rigid.end_error_m,
            rpe_drift_pct=drift['drift_pct'],
            n_matched=ate_result.n, path_length_m=path_length_m, mode=self.mode,
            scale=ate_result.scale, rotation_rmse_deg=ate_result.rotation_rmse_deg,
            rpe_lengths_m=tuple(drift['lengths_m']),
            rpe_drift_pct_per_length=tuple(drift['drift_pct_per_length']),
            rpe_count_per_length=tuple(drift['count_per_length']))

    def evaluate(self, est: Trajectory, ref: Trajectory) -> dict:
        """The metrics of `est` against `ref` as a JSON-ready dict."""
        return self.metrics(est, ref).as_dict()


def evaluate(est: Trajectory, ref: Trajectory, mode: str = DEFAULT_MODE,
             lengths_m: tuple[float, ...] = DEFAULT_LENGTHS_M,
             max_diff_s: float = DEFAULT_MAX_DIFF_S,
             match: str = DEFAULT_MATCH, max_gap_s: float = DEFAULT_MAX_GAP_S) -> dict:
    """JSON-friendly flat dict: ate_rmse_m, ate_mean_m, ate_median_m, ate_max_m, ate_std_m,
    paper_mse_m2, end_error_m (rigidly aligned final positions), rpe_drift_pct, n_matched,
    path_length_m (reference path over the matched span), mode, scale, rotation_rmse_deg and
    `rpe_drift_pct_<L>m` / `rpe_count_<L>m` per length. NaN values (e.g. a length longer than
    the run) are written as None.
    """
    return TrajectoryEvaluator(mode, max_diff_s, lengths_m, match, max_gap_s).evaluate(est, ref)
