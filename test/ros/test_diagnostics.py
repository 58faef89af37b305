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
