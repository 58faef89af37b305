"""The /diagnostics verdict from the counters (pure logic; over DDS in test_node_services)."""

from __future__ import annotations

import pytest

pytestmark = [pytest.mark.ros]


def _assess(counters_then, counters_now, latencies_s=(0.03,) * 20, period_s=0.1):
    from gft_odom.ros.diagnostics import OdometryDiagnostics
    diag = OdometryDiagnostics(window_s=10.0)
    diag.assess(0.0, counters_then, latencies_s, period_s)
    return diag.assess(5.0, counters_now, latencies_s, period_s)


def test_tracking_is_ok():
    from gft_odom.ros.diagnostics import OK
    result = _assess({'processed': 10}, {'processed': 60})
    assert result.level == OK and result.message == 'tracking'
    assert result.values['processed'] == '50'


def test_fallbacks_missed_and_latency_raise_the_level():
    from gft_odom.ros.diagnostics import ERROR, WARN
    warn = _assess({'processed': 0}, {'processed': 50, 'fallback': 15})
    assert warn.level == WARN and '30 % of scans fell back' in warn.message
    assert _assess({}, {'processed': 50, 'fallback': 40}).level == ERROR
    lost = _assess({}, {'processed': 40, 'missed': 10})
    assert lost.level == WARN and 'missed or stale' in lost.message
    slow = _assess({}, {'processed': 50}, latencies_s=[0.15] * 20)
    assert slow.level == ERROR and 'median latency 150 ms' in slow.message
    p95 = _assess({}, {'processed': 50}, latencies_s=[0.03] * 18 + [0.2] * 2)
    assert p95.level == WARN
    rejected = _assess({}, {'processed': 50, 'malformed': 2})
    assert rejected.level == WARN and '2 scan(s) rejected' in rejected.message


def test_old_problems_leave_the_window():
    from gft_odom.ros.diagnostics import OK, OdometryDiagnostics
    diag = OdometryDiagnostics(window_s=10.0)
    diag.assess(0.0, {'processed': 10, 'fallback': 10}, [0.03], 0.1)
    diag.assess(11.0, {'processed': 20, 'fallback': 10}, [0.03], 0.1)
    assert diag.assess(12.0, {'processed': 30, 'fallback': 10}, [0.03], 0.1).level == OK


def test_no_scans_is_a_warning():
    from gft_odom.ros.diagnostics import WARN
    assert _assess({'processed': 5}, {'processed': 5}).level == WARN


def test_a_weak_direction_below_the_threshold_warns_and_names_it():
    import numpy as np

    from gft_odom.core.degeneracy import weakest_translation
    from gft_odom.ros.diagnostics import OK, WARN, OdometryDiagnostics
    open_ground = weakest_translation(np.diag([2.0, 3.0, 2000.0, 50.0, 50.0, 50.0]))
    row = weakest_translation(np.diag([600.0, 1000.0, 2000.0, 50.0, 50.0, 50.0]))
    diag = OdometryDiagnostics(window_s=10.0)
    diag.assess(0.0, {'processed': 10}, [0.03], 0.1)
    warn = diag.assess(5.0, {'processed': 60}, [0.03], 0.1, weak=open_ground,
                       weak_warn_ratio=0.02)
    assert warn.level == WARN and 'weak: translation along x in the base frame' in warn.message
    assert warn.values['weakest_direction'] == 'translation along x'
    assert float(warn.values['weakest_direction_ratio']) == pytest.approx(0.001)
    ok = diag.assess(6.0, {'processed': 70}, [0.03], 0.1, weak=row, weak_warn_ratio=0.02)
    assert ok.level == OK and ok.values['weakest_direction'] == 'translation along x'
    never = diag.assess(7.0, {'processed': 80}, [0.03], 0.1, weak=open_ground,
                        weak_warn_ratio=0.0)
    assert never.level == OK


def test_the_motion_bounds_message_is_a_warning():
    from gft_odom.ros.diagnostics import WARN, OdometryDiagnostics
    diag = OdometryDiagnostics(window_s=10.0)
    diag.assess(0.0, {'processed': 10}, [0.03], 0.1)
    line = 'motion bounds: ... raise registration.max_speed_mps'
    result = diag.assess(5.0, {'processed': 60}, [0.03], 0.1, bounds_message=line)
    assert result.level == WARN and line in result.message


def test_work_beyond_the_period_with_the_map_update_is_an_error():
    """Odometry out in time but a map update that makes each scan's work overrun the period:
    the scans queue up, which the latency alone does not show."""
    from gft_odom.ros.diagnostics import ERROR, OK, OdometryDiagnostics
    diag = OdometryDiagnostics(window_s=10.0)
    latencies = [0.04] * 20
    diag.assess(0.0, {}, latencies, 0.1, busy_s=[0.06] * 20)
    fine = diag.assess(5.0, {'processed': 50}, latencies, 0.1, busy_s=[0.06] * 20)
    assert fine.level == OK and fine.values['busy_mean_ms'] == '60.0'
    over = diag.assess(6.0, {'processed': 60}, latencies, 0.1, busy_s=[0.04, 0.2] * 10)
    assert over.level == ERROR and 'scans queue up' in over.message
