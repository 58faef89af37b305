"""Fault injection on simulated drives: what one bad patch of data costs the odometry.

Each case takes the scans of a clean drive and breaks them the way a robot's data break:
impossible copies of a scan 30 ms after it (rotated, shifted, mirrored, random noise), gaps
with the robot moving or standing, a lone scan stamped an hour late, a clock that steps and
stays, a bag played in a loop, per-point time in another unit. Every scan carries the index of
the ground-truth pose it was taken at, or None for an injected fault, so the error is measured
on the valid scans only (ATE after rigid alignment, per run of the odometry when the clock
restarted it). Used by test/robustness/test_fault_injection.py and benchmarks/faults.py.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Callable

import numpy as np

from gft_odom.config import GftOdomConfig
from gft_odom.core.alignment import umeyama_alignment
from gft_odom.core.constants import NS_PER_S, ns_to_sec_nanosec
from gft_odom.core.types import Scan
from gft_odom.io.pointcloud2 import decode_scan, encode_cloud
from gft_odom.pipeline import FrameResult, OdometryPipeline

COPY_DELAY_NS = 30_000_000  # an impossible copy arrives this long after the valid scan
HOUR_NS = 3600 * NS_PER_S
COPY_EVERY = 7  # scans between two faulty copies


@dataclass(frozen=True)
class FaultyScan:
    """One scan of a faulted drive: `truth_index` is its ground-truth pose, None for a fault."""

    scan: Scan
    truth_index: int | None


@dataclass
class CaseResult:
    """What one case cost: ATE over the valid scans, and what happened to every scan."""

    name: str
    ate_m: float
    n_valid: int
    n_valid_registered: int
    statuses: Counter = field(default_factory=Counter)
    n_segments: int = 1
    results: list[FrameResult] = field(default_factory=list)


def _restamp(scan: Scan, stamp_ns: int) -> Scan:
    return Scan(int(stamp_ns), scan.points_xyz, scan.intensity, scan.ring, scan.time_offset_s,
                scan.frame_id)


def _with_points(scan: Scan, points_xyz: np.ndarray, stamp_ns: int) -> Scan:
    return Scan(int(stamp_ns), points_xyz, scan.intensity, scan.ring, scan.time_offset_s,
                scan.frame_id)


def rotated_copy(scan: Scan, yaw_rad: float = np.pi / 2) -> Scan:
    """The scan turned about z, 30 ms later."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return _with_points(scan, scan.points_xyz @ R.T, scan.stamp_ns + COPY_DELAY_NS)


def shifted_copy(scan: Scan, shift_m: float = 20.0) -> Scan:
    """The scan moved `shift_m` along x, 30 ms later."""
    return _with_points(scan, scan.points_xyz + [shift_m, 0.0, 0.0],
                        scan.stamp_ns + COPY_DELAY_NS)


def mirrored_copy(scan: Scan) -> Scan:
    """The scan mirrored left-right (y -> -y), 30 ms later."""
    return _with_points(scan, scan.points_xyz * [1.0, -1.0, 1.0],
                        scan.stamp_ns + COPY_DELAY_NS)


def noise_copy(scan: Scan, seed: int = 0) -> Scan:
    """As many uniform random points in the scan's bounding box, 30 ms later."""
    rng = np.random.default_rng(seed)
    low, high = scan.points_xyz.min(axis=0), scan.points_xyz.max(axis=0)
    return _with_points(scan, rng.uniform(low, high, scan.points_xyz.shape),
                        scan.stamp_ns + COPY_DELAY_NS)


def with_time_unit(scan: Scan, unit: str) -> Scan:
    """The scan through the PointCloud2 codec with its per-point time written in `unit`."""
    offsets_s = np.asarray(scan.time_offset_s, dtype=np.float64)
    values = {'s': offsets_s.astype(np.float32),
              'us': np.round(offsets_s * 1e6).astype(np.float64),
              'ns': np.round(offsets_s * 1e9).astype(np.uint32)}[unit]
    xyz = scan.points_xyz.astype(np.float32)
    blob = encode_cloud({'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2], 'time': values})
    sec, nanosec = ns_to_sec_nanosec(scan.stamp_ns)
    msg = SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec),
                               frame_id=scan.frame_id),
        height=blob.height, width=blob.width, fields=list(blob.fields),
        is_bigendian=blob.is_bigendian, point_step=blob.point_step, row_step=blob.row_step,
        data=blob.data, is_dense=blob.is_dense)
    return decode_scan(msg)


def _valid(scans: list[Scan]) -> list[FaultyScan]:
    return [FaultyScan(s, i) for i, s in enumerate(scans)]


def _insert_after(scans: list[Scan], k: int, fault: Callable[[Scan], Scan]):
    """A faulty copy after scan k and every COPY_EVERY-th scan after it (some of them land
    where the map takes a keyframe)."""
    items = []
    for i, scan in enumerate(scans):
        items.append(FaultyScan(scan, i))
        if i >= k and (i - k) % COPY_EVERY == 0 and i < len(scans) - 1:
            items.append(FaultyScan(fault(scan), None))
    return items


def _gap_moving(scans: list[Scan], k: int, gap_s: float):
    """Scans lost for `gap_s` while the robot drove on."""
    dropped = int(round(gap_s / _period_s(scans))) - 1
    items = _valid(scans)
    return items[:k + 1] + items[k + 1 + dropped:]


def _gap_standing(scans: list[Scan], k: int, gap_s: float):
    """No scan for `gap_s` while the robot stood still: the next one continues the drive."""
    shift_ns = int(round((gap_s - _period_s(scans)) * NS_PER_S))
    return [FaultyScan(_restamp(s, s.stamp_ns + (shift_ns if i > k else 0)), i)
            for i, s in enumerate(scans)]


def _lone_late(scans: list[Scan], k: int):
    """One scan stamped an hour late (its geometry is right, its stamp is not)."""
    items = _valid(scans)
    items[k + 1] = FaultyScan(_restamp(scans[k + 1], scans[k + 1].stamp_ns + HOUR_NS), None)
    return items


def _clock_steps(scans: list[Scan], k: int):
    """The clock jumps an hour forward after scan k and stays there."""
    return [FaultyScan(_restamp(s, s.stamp_ns + (HOUR_NS if i > k else 0)), i)
            for i, s in enumerate(scans)]


def _bag_loop(scans: list[Scan], k: int):
    """The bag played twice: after the last scan the clock goes back to the first stamp."""
    return _valid(scans) + _valid(scans)[:max(k, len(scans) // 2)]


def _period_s(scans: list[Scan]) -> float:
    return float(np.median(np.diff([s.stamp_ns for s in scans]))) / NS_PER_S


CASES: dict[str, Callable[[list[Scan], int], list[FaultyScan]]] = {
    'clean': lambda scans, k: _valid(scans),
    'rotated_copy_90deg': lambda scans, k: _insert_after(scans, k, rotated_copy),
    'shifted_copy_20m': lambda scans, k: _insert_after(scans, k, shifted_copy),
    'mirrored_copy': lambda scans, k: _insert_after(scans, k, mirrored_copy),
    'random_noise_copy': lambda scans, k: _insert_after(scans, k, noise_copy),
    'gap_0.5s_moving': lambda scans, k: _gap_moving(scans, k, 0.5),
    'gap_2s_moving': lambda scans, k: _gap_moving(scans, k, 2.0),
    'gap_5s_moving': lambda scans, k: _gap_moving(scans, k, 5.0),
    'gap_0.5s_standing': lambda scans, k: _gap_standing(scans, k, 0.5),
    'gap_2s_standing': lambda scans, k: _gap_standing(scans, k, 2.0),
    'gap_5s_standing': lambda scans, k: _gap_standing(scans, k, 5.0),
    'one_scan_plus_1h': _lone_late,
    'clock_steps_forward_1h': _clock_steps,
    'clock_reset_to_start': _bag_loop,
    'time_in_s': lambda scans, k: [FaultyScan(with_time_unit(s, 's'), i)
                                   for i, s in enumerate(scans)],
    'time_in_us': lambda scans, k: [FaultyScan(with_time_unit(s, 'us'), i)
                                    for i, s in enumerate(scans)],
    'time_in_ns': lambda scans, k: [FaultyScan(with_time_unit(s, 'ns'), i)
                                    for i, s in enumerate(scans)],
}


def run_items(items: list[FaultyScan], config: GftOdomConfig
              ) -> tuple[list[FrameResult], list[int]]:
    """Every scan through one pipeline: the results and the odometry run each belongs to."""
    pipeline = OdometryPipeline(config, record_trajectory=False)
    results, segment = [], []
    for item in items:
        results.append(pipeline.register_frame(item.scan))
        segment.append(getattr(pipeline, 'n_resets', 0))
    return results, segment


def valid_ate_m(items: list[FaultyScan], results: list[FrameResult], segment: list[int],
                truth_poses: np.ndarray) -> float:
    """ATE RMSE [m] of the registered valid scans, each odometry run aligned on its own."""
    errors = []
    for seg in sorted(set(segment)):
        pick = [i for i, (item, result) in enumerate(zip(items, results))
                if segment[i] == seg and item.truth_index is not None
                and getattr(result, 'accepted', True)]
        if len(pick) < 3:
            continue
        est = np.array([results[i].T_world_sensor[:3, 3] for i in pick])
        ref = truth_poses[[items[i].truth_index for i in pick], :3, 3]
        R, t, _ = umeyama_alignment(est, ref)
        errors.append(np.linalg.norm(est @ R.T + t - ref, axis=1))
    if not errors:
        return float('inf')
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))


def run_case(name: str, scans: list[Scan], truth_poses: np.ndarray, config: GftOdomConfig,
             k: int) -> CaseResult:
    """Case `name` on the drive `scans` (ground truth `truth_poses`), faults after scan k."""
    items = CASES[name](scans, k)
    results, segment = run_items(items, config)
    valid = [(item, r) for item, r in zip(items, results) if item.truth_index is not None]
    return CaseResult(
        name=name, ate_m=valid_ate_m(items, results, segment, truth_poses),
        n_valid=len(valid),
        n_valid_registered=sum(getattr(r, 'accepted', True) for _, r in valid),
        statuses=Counter(r.status for r in results), n_segments=len(set(segment)),
        results=results)
