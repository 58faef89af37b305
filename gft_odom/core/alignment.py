"""Matching an estimate to its reference in time, and aligning them in space.

Association by nearest stamp or by interpolating the reference's positions at the estimate's
stamps, and the Umeyama least-squares similarity: the steps every metric in `metrics` and the
stamp audit share.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gft_odom.core.constants import NS_PER_S, SCAN_PERIOD_S
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import ConfigError, GroundTruthError

DEFAULT_MAX_DIFF_S = SCAN_PERIOD_S / 2
DEFAULT_MAX_GAP_S = 1.0
MATCH_METHODS = ('auto', 'nearest', 'interpolate')
MIN_MATCHED = 3
# Umeyama needs a spread in two directions; below this ratio of the second to the first singular
# value of the centred points they are treated as collinear (the rotation about the line is
# then fixed by noise alone, not by the data).
_COLLINEAR_RTOL = 1e-9


def check_sorted(traj: Trajectory, name: str) -> None:
    """Raise GroundTruthError at the first stamp earlier than the one before."""
    if len(traj) > 1 and np.any(np.diff(traj.stamps_ns) < 0):
        first = int(np.flatnonzero(np.diff(traj.stamps_ns) < 0)[0])
        raise GroundTruthError(f'{name} trajectory stamps are not sorted in time '
                               f'(stamp {first + 1} is earlier than stamp {first})')


def time_range(traj: Trajectory) -> str:
    """The span of a trajectory, for error messages."""
    if len(traj) == 0:
        return 'empty'
    return f'{traj.stamps_s[0]:.3f}..{traj.stamps_s[-1]:.3f} s ({len(traj)} poses)'


# --- association -----------------------------------------------------------------------------

def associate(est: Trajectory, ref: Trajectory,
              max_diff_s: float = DEFAULT_MAX_DIFF_S) -> tuple[np.ndarray, np.ndarray]:
    """Pair each estimate stamp with the nearest reference stamp within `max_diff_s`.

    Each reference pose is used at most once (the estimate closest in time keeps it, the
    earlier one on a tie), so a slow reference is not counted several times. Returns two int
    arrays (est_idx, ref_idx), increasing, of equal length. Integer nanoseconds throughout, so
    no float rounding decides a match.
    """
    if not (math.isfinite(max_diff_s) and max_diff_s >= 0.0):
        raise ConfigError(f'max_diff_s must be a finite number >= 0, got {max_diff_s}')
    check_sorted(est, 'estimated')
    check_sorted(ref, 'reference')
    empty = np.zeros(0, dtype=np.int64)
    if len(est) == 0 or len(ref) == 0:
        return empty, empty.copy()
    max_diff_ns = int(round(max_diff_s * NS_PER_S))
    s_est, s_ref = est.stamps_ns, ref.stamps_ns
    upper = np.searchsorted(s_ref, s_est, side='left')
    right = np.minimum(upper, len(ref) - 1)
    left = np.maximum(upper - 1, 0)
    dt_right = np.abs(s_ref[right] - s_est)
    dt_left = np.abs(s_est - s_ref[left])
    nearest = np.where(dt_right < dt_left, right, left)
    dt = np.minimum(dt_right, dt_left)
    within = dt <= max_diff_ns
    est_idx = np.flatnonzero(within).astype(np.int64)
    ref_idx = nearest[within].astype(np.int64)
    dt = dt[within]
    # One estimate per reference pose: sort by (ref, dt, est) and keep the first of each ref.
    order = np.lexsort((est_idx, dt, ref_idx))
    _, first = np.unique(ref_idx[order], return_index=True)
    keep = np.sort(order[first])
    return est_idx[keep], ref_idx[keep]


def interpolate_positions(ref: Trajectory, stamps_ns: np.ndarray,
                          max_gap_s: float = DEFAULT_MAX_GAP_S) -> np.ndarray:
    """Reference positions linearly interpolated at `stamps_ns`, (M, 3).

    For a ground truth at another rate than the scans (GPS at 1-5 Hz). Rows are NaN outside the
    reference's time span and inside gaps longer than `max_gap_s` (a GPS dropout is not
    bridged by a straight line). Orientations are not interpolated: this serves the
    position-only metrics.
    """
    if not (math.isfinite(max_gap_s) and max_gap_s > 0.0):
        raise ConfigError(f'max_gap_s must be a finite number > 0, got {max_gap_s}')
    check_sorted(ref, 'reference')
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    out = np.full((stamps_ns.shape[0], 3), np.nan)
    if len(ref) == 0 or stamps_ns.shape[0] == 0:
        return out
    # Seconds relative to the first reference stamp keep float64 precision at the ns level.
    t_ref = (ref.stamps_ns - ref.stamps_ns[0]).astype(np.float64) * 1e-9
    t_query = (stamps_ns - ref.stamps_ns[0]).astype(np.float64) * 1e-9
    upper = np.searchsorted(ref.stamps_ns, stamps_ns, side='left')
    exact = (upper < len(ref)) & (ref.stamps_ns[np.minimum(upper, len(ref) - 1)] == stamps_ns)
    inside = (upper > 0) & (upper < len(ref))
    gap_s = np.full(stamps_ns.shape[0], np.inf)
    gap_s[inside] = t_ref[upper[inside]] - t_ref[upper[inside] - 1]
    valid = exact | (inside & (gap_s <= max_gap_s))
    positions = ref.positions_xyz
    for axis in range(3):  # three axes, not a loop over points
        out[valid, axis] = np.interp(t_query[valid], t_ref, positions[:, axis])
    return out


@dataclass
class Matched:
    """Poses of est and ref at matched instants (ref rotations only when they were read)."""

    est_idx: np.ndarray
    p_est: np.ndarray
    p_ref: np.ndarray
    poses_est: np.ndarray
    poses_ref: np.ndarray | None


def match_trajectories(est: Trajectory, ref: Trajectory, max_diff_s: float, match: str,
                       max_gap_s: float, need_orientation: bool) -> Matched:
    """Est and ref at matched instants: by nearest stamp, or ref interpolated at est's stamps."""
    at_ends = match == 'auto'
    if match == 'auto':
        match = 'nearest' if need_orientation else 'interpolate'
    if match == 'nearest':
        est_idx, ref_idx = associate(est, ref, max_diff_s)
        p_ref = ref.positions_xyz[ref_idx]
        poses_ref = ref.poses[ref_idx] if need_orientation else None
        how = f'within {max_diff_s} s'
    else:
        if need_orientation:
            raise ConfigError("match='interpolate' gives positions only; orientation metrics "
                              "(mode='se3', use_orientation=True) need match='nearest'")
        check_sorted(est, 'estimated')
        p_all = interpolate_positions(ref, est.stamps_ns, max_gap_s)
        if at_ends and len(ref):
            # 'auto': a pose just outside the reference's span (within max_diff_s of its first
            # or last sample) takes that sample, as 'nearest' would.
            limit_ns = max_diff_s * 1e9
            for end in (0, len(ref) - 1):
                near = (~np.isfinite(p_all).all(axis=1)) & (
                    np.abs(est.stamps_ns - ref.stamps_ns[end]) <= limit_ns)
                p_all[near] = ref.positions_xyz[end]
        est_idx = np.flatnonzero(np.isfinite(p_all).all(axis=1))
        p_ref = p_all[est_idx]
        poses_ref = None
        how = f'by interpolation (gaps <= {max_gap_s} s)'
    if est_idx.shape[0] < MIN_MATCHED:
        raise GroundTruthError(
            f'only {est_idx.shape[0]} estimated stamps overlap the reference {how}; need at '
            f'least {MIN_MATCHED}. Estimate: {time_range(est)}; reference: {time_range(ref)}')
    p_est = est.positions_xyz[est_idx]
    for name, p in (('estimated', p_est), ('reference', p_ref)):
        if not np.isfinite(p).all():
            raise GroundTruthError(f'{name} trajectory has non-finite positions at matched stamps')
    return Matched(est_idx, p_est, p_ref, est.poses[est_idx], poses_ref)


# --- alignment -------------------------------------------------------------------------------

def umeyama_alignment(src: np.ndarray, dst: np.ndarray,
                      with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (R, t, s) minimising sum |dst - (s R src + t)|^2 (Umeyama 1991).

    R is a proper rotation even when a reflection would fit better (the sign of the smallest
    singular direction is flipped), so planar trajectories align correctly. s is 1.0 unless
    `with_scale`. Fewer than 3 points, non-finite values or collinear point sets raise
    GroundTruthError: there the rotation is not determined by the data.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise GroundTruthError(f'alignment needs two (N, 3) point sets of equal shape, got '
                               f'{src.shape} and {dst.shape}')
    n = src.shape[0]
    if n < MIN_MATCHED:
        raise GroundTruthError(f'alignment needs at least {MIN_MATCHED} point pairs, got {n}')
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise GroundTruthError('alignment got non-finite (NaN/Inf) points')
    mean_src = src.mean(axis=0)
    mean_dst = dst.mean(axis=0)
    centred_src = src - mean_src
    centred_dst = dst - mean_dst
    for name, centred in (('estimated', centred_src), ('reference', centred_dst)):
        spread = np.linalg.svd(centred, compute_uv=False)
        if not spread[1] > _COLLINEAR_RTOL * spread[0]:
            raise GroundTruthError(
                f'alignment is degenerate: the {name} positions are collinear or identical '
                f'(spread singular values {spread[0]:.3g}, {spread[1]:.3g} m); the rotation '
                'about the line is not determined')
    covariance = centred_dst.T @ centred_src / n
    u, d, vt = np.linalg.svd(covariance)
    if not d[1] > _COLLINEAR_RTOL**2 * d[0]:
        raise GroundTruthError('alignment is degenerate: the cross-covariance of the positions '
                               f'has rank < 2 (singular values {d})')
    signs = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        signs[2] = -1.0  # best proper rotation instead of a reflection
    rotation = (u * signs) @ vt
    scale = 1.0
    if with_scale:
        variance_src = float((centred_src**2).sum()) / n
        scale = float((d * signs).sum()) / variance_src
    translation = mean_dst - scale * rotation @ mean_src
    return rotation, translation, scale


def similarity_matrix(rotation: np.ndarray, translation: np.ndarray,
                      scale: float) -> np.ndarray:
    """[[s R, t], [0, 1]]."""
    T = np.eye(4)
    T[:3, :3] = scale * rotation
    T[:3, 3] = translation
    return T


def rotation_angles_rad(rotations: np.ndarray) -> np.ndarray:
    """Angles of a stack of rotation matrices, accurate near 0 (atan2, not arccos)."""
    trace = np.trace(rotations, axis1=-2, axis2=-1)
    skew = np.stack([rotations[..., 2, 1] - rotations[..., 1, 2],
                     rotations[..., 0, 2] - rotations[..., 2, 0],
                     rotations[..., 1, 0] - rotations[..., 0, 1]], axis=-1)
    return np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (trace - 1.0))
