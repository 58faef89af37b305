"""`/diagnostics` status of the odometry: OK / WARN / ERROR from the recent counters.

Judged over a sliding window of the last `WINDOW_S` seconds, so a problem clears itself once it
stops: the share of scans that fell back to the motion prediction, the latency against the
sensor period, the share of sweeps missed or dropped as stale, and the scans rejected. Beside
them, not windowed: the weakest translation direction of the last match (WARN below
`node.weak_direction_warn_ratio`) and the motion bounds' message once it was told.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import Header

WINDOW_S = 10.0
FALLBACK_WARN, FALLBACK_ERROR = 0.2, 0.5
LOST_WARN, LOST_ERROR = 0.05, 0.5  # share of sweeps missed or stale
REJECTED = ('malformed', 'empty', 'degenerate', 'out_of_order', 'clock_jump', 'failed',
            'rejected')
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
# A stamp this far from the clock is not lag but a clock mismatch (a bag without --clock).
CLOCK_MISMATCH_S = 60.0


def stale_scan_text(age_s: float, use_sim_time: bool, max_scan_age_s: float) -> str:
    """Why a scan is too old: lag, or (far from now) a clock that does not match."""
    if abs(age_s) > CLOCK_MISMATCH_S:
        return (f'dropping scan stamped {age_s:.0f} s before the node clock: the stamps and '
                f'the clock disagree; ' + (
                    'use_sim_time is true: is /clock published (ros2 bag play --clock)?'
                    if use_sim_time else 'playing a bag? play it with --clock and start the '
                    'node with use_sim_time:=true'))
    return f'dropping scan {age_s:.2f} s old (processing lags; max_scan_age_s={max_scan_age_s})'


@dataclass
class Assessment:
    """One verdict: level, message and the values behind it."""
    level: bytes
    message: str
    values: dict[str, str]


class OdometryDiagnostics:
    """Keeps counter snapshots; `assess` compares now with the oldest one in the window."""

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self._snapshots: collections.deque = collections.deque()
        self._window_s = window_s

    def assess(self, now_s: float, counters, latencies_s, period_s: float,
               weak=None, weak_warn_ratio: float = 0.0,
               bounds_message: str | None = None, busy_s=None) -> Assessment:
        """OK / WARN / ERROR over the last window from counters and latencies; `busy_s`:
        each scan's latency with the map update after it (ERROR when their mean is over the
        period: the node cannot keep up); `weak`: the last match's `WeakDirection`
        (core.degeneracy), WARN when its ratio is below `weak_warn_ratio`;
        `bounds_message`: the motion bounds' line (WARN)."""
        current = dict(counters)
        self._snapshots.append((now_s, current))
        while self._snapshots and now_s - self._snapshots[0][0] > self._window_s:
            self._snapshots.popleft()
        old = self._snapshots[0][1]

        def delta(*kinds) -> int:
            return sum(current.get(k, 0) - old.get(k, 0) for k in kinds)

        processed = delta('processed')
        fallback = delta('fallback')
        lost = delta('missed', 'stale')
        rejected = delta(*REJECTED)
        lat = sorted(latencies_s)
        median_s = lat[len(lat) // 2] if lat else None
        p95_s = lat[min(len(lat) - 1, int(0.95 * len(lat)))] if lat else None
        problems: list[tuple[bytes, str]] = []
        if processed == 0:
            problems.append((WARN, f'no scan processed in the last {self._window_s:.0f} s'))
        else:
            share = fallback / processed
            if share >= FALLBACK_WARN:
                problems.append((ERROR if share >= FALLBACK_ERROR else WARN,
                                 f'{100 * share:.0f} % of scans fell back to the prediction'))
            lost_share = lost / (processed + lost)
            if lost_share >= LOST_WARN:
                problems.append((ERROR if lost_share >= LOST_ERROR else WARN,
                                 f'{100 * lost_share:.0f} % of sweeps missed or stale'))
        busy_mean_s = float(np.mean(busy_s)) if busy_s else None
        if busy_mean_s is not None and busy_mean_s > period_s:
            problems.append((ERROR, f'{1e3 * busy_mean_s:.0f} ms of work a scan (with the map '
                                    f'update) > the sensor period {1e3 * period_s:.0f} ms: '
                                    'scans queue up'))
        if median_s is not None and median_s > period_s:
            problems.append((ERROR, f'median latency {1e3 * median_s:.0f} ms > the sensor '
                                    f'period {1e3 * period_s:.0f} ms'))
        elif p95_s is not None and p95_s > period_s:
            problems.append((WARN, f'p95 latency {1e3 * p95_s:.0f} ms > the sensor period '
                                   f'{1e3 * period_s:.0f} ms'))
        if rejected:
            problems.append((WARN, f'{rejected} scan(s) rejected'))
        if weak is not None and weak.ratio < weak_warn_ratio:
            problems.append((WARN, f'weak: {weak.text} in the base frame '
                                   f"({100 * weak.ratio:.1f} % of the strongest direction's "
                                   'information; it leans on the motion prior)'))
        if bounds_message:
            problems.append((WARN, bounds_message))
        level = max((lvl for lvl, _ in problems), default=OK)
        message = '; '.join(text for _, text in problems) or 'tracking'
        values = {
            'window_s': f'{self._window_s:g}', 'processed': str(processed),
            'fallback': str(fallback), 'missed_or_stale': str(lost),
            'rejected': str(rejected), 'scan_period_s': f'{period_s:.4f}',
            'latency_median_ms': f'{1e3 * median_s:.1f}' if median_s is not None else 'n/a',
            'latency_p95_ms': f'{1e3 * p95_s:.1f}' if p95_s is not None else 'n/a',
            'busy_mean_ms': f'{1e3 * busy_mean_s:.1f}' if busy_mean_s is not None else 'n/a',
        }
        if weak is not None:
            values['weakest_direction'] = weak.text
            values['weakest_direction_ratio'] = f'{weak.ratio:.4f}'
        values.update({f'total_{k}': str(v) for k, v in sorted(current.items())})
        return Assessment(level, message, values)


def diagnostic_array(assessment: Assessment, stamp, name: str,
                     hardware_id: str) -> DiagnosticArray:
    """diagnostic_msgs/DiagnosticArray of one assessment."""
    status = DiagnosticStatus(level=assessment.level, name=name, message=assessment.message,
                              hardware_id=hardware_id,
                              values=[KeyValue(key=k, value=v)
                                      for k, v in assessment.values.items()])
    return DiagnosticArray(header=Header(stamp=stamp),
                           status=[status])
