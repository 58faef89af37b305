"""The latency a robot would see at the sensor's rate, from a replay's per-scan times: a scan
waits while the work of the scans before it (pose and map update) overruns the period."""

from __future__ import annotations

import numpy as np

from gft_odom.core.trajectory import Trajectory
from gft_odom.replay import ReplayResult, latency_at_rate_s, timing_metrics

PERIOD_NS = 100_000_000


def test_work_within_the_period_never_waits():
    stamps = np.arange(5) * PERIOD_NS
    latency = np.full(5, 0.04)
    np.testing.assert_allclose(latency_at_rate_s(stamps, latency, latency + 0.05), latency)


def test_an_overrun_delays_the_next_scans_until_the_queue_drains():
    stamps = np.arange(4) * PERIOD_NS
    latency = np.full(4, 0.04)
    busy = np.array([0.25, 0.04, 0.04, 0.04])  # a keyframe's map update of 210 ms
    # Scan 1 arrives at 0.1 s and starts at 0.25 s; scan 2 arrives at 0.2 s and starts at
    # 0.29 s; scan 3 arrives at 0.3 s and starts at 0.33 s, when the queue has drained.
    np.testing.assert_allclose(latency_at_rate_s(stamps, latency, busy),
                               [0.04, 0.19, 0.13, 0.07])


def test_a_stamp_gap_empties_the_queue_and_a_clock_jump_back_does_not_crash():
    stamps = np.array([0, PERIOD_NS, 10 * PERIOD_NS, 2 * PERIOD_NS])
    latency = np.full(4, 0.03)
    out = latency_at_rate_s(stamps, latency, np.array([0.5, 0.03, 0.03, 0.03]))
    np.testing.assert_allclose(out[:3], [0.03, 0.43, 0.03])
    assert np.isfinite(out[3]) and out[3] >= 0.03


def _replay(latency_s, map_update_s=None, stamps_ns=None) -> ReplayResult:
    n = len(latency_s)
    trajectory = Trajectory(np.arange(n, dtype=np.int64) * PERIOD_NS,
                            np.repeat(np.eye(4)[None], n, axis=0))
    return ReplayResult(trajectory, trajectory, np.asarray(latency_s), {}, np.ones(n),
                        np.ones(n), ['ok'] * n,
                        map_update_s=None if map_update_s is None else np.asarray(map_update_s),
                        scan_stamps_ns=stamps_ns)


def test_timing_metrics_add_the_map_update_to_the_busy_time_not_to_the_latency():
    latency = [0.04] * 19 + [0.05]
    update = [0.0] * 9 + [0.15] + [0.0] * 10
    metrics = timing_metrics(_replay(latency, update, np.arange(20) * PERIOD_NS))
    assert metrics['latency_p95_ms'] < 50.1
    assert metrics['busy_p95_ms'] > 50.0 and metrics['map_update_p95_ms'] >= 0.0
    assert abs(metrics['busy_mean_ms'] - 1e3 * (np.mean(latency) + np.mean(update))) < 1e-9
    # The scan after the 190 ms one waits 90 ms.
    assert metrics['latency_at_rate_p95_ms'] > metrics['latency_p95_ms']
    # A peer that maps inside its call: busy is its latency; no stamps, no rate figure.
    peer = timing_metrics(_replay(latency))
    assert peer['busy_p95_ms'] == peer['latency_p95_ms']
    assert 'latency_at_rate_p95_ms' not in peer and 'map_update_p95_ms' not in peer
