"""Motion bounds that speak up: once, when well-fitting matches refused as implausible agree."""

from __future__ import annotations

import logging

import pytest

from gft_odom.core.bounds_watch import IMPLAUSIBLE_STATUS, BoundsWatch


def _feed(watch, outcomes):
    told = []
    for outcome in outcomes:
        line = watch.observe(*outcome) if outcome else watch.observe('ok', None, None)
        if line:
            told.append(line)
    return told


def test_agreeing_refusals_are_told_once_naming_the_parameter(caplog):
    watch = BoundsWatch(max_speed_mps=2.0, max_yaw_rate_rps=4.0)
    refusal = [(IMPLAUSIBLE_STATUS, 4.4 + 0.1 * (i % 3), 0.05) for i in range(12)]
    with caplog.at_level(logging.WARNING, logger='gft_odom.core.bounds_watch'):
        told = _feed(watch, [refusal[0], None, refusal[1], refusal[2], None, *refusal[3:]])
    assert len(told) == 1 and watch.message == told[0]
    assert 'registration.max_speed_mps' in told[0] and '4.5 m/s' in told[0]
    assert 'max_yaw_rate_rps' not in told[0]
    assert [r.getMessage() for r in caplog.records] == told  # logged once


def test_a_fast_turn_names_the_yaw_rate_bound():
    watch = BoundsWatch(max_speed_mps=2.0, max_yaw_rate_rps=1.0)
    told = _feed(watch, [(IMPLAUSIBLE_STATUS, 0.5, 1.8)] * 5)
    assert len(told) == 1 and 'registration.max_yaw_rate_rps' in told[0]
    assert '1.80 rad/s' in told[0] and 'max_speed_mps' not in told[0]


@pytest.mark.parametrize('speeds', [
    [3.5, 9.0, 4.0, 14.0, 6.0, 3.2, 25.0],  # wrong matches (jumps) scatter
    [4.4, 4.5, 4.3, 4.4],  # too few
])
def test_scattered_or_few_refusals_stay_silent(speeds):
    watch = BoundsWatch(max_speed_mps=2.0, max_yaw_rate_rps=4.0)
    assert _feed(watch, [(IMPLAUSIBLE_STATUS, s, 0.1) for s in speeds]) == []
    assert watch.message is None


def test_other_fallbacks_and_rateless_refusals_do_not_count():
    watch = BoundsWatch(max_speed_mps=2.0, max_yaw_rate_rps=4.0)
    outcomes = [('fallback_low_fitness', 4.4, 0.1), (IMPLAUSIBLE_STATUS, None, None)] * 10
    assert _feed(watch, outcomes) == []


@pytest.mark.slow
@pytest.mark.parametrize('max_speed_mps, told', [(2.0, True), (6.0, False)])
def test_a_drive_faster_than_the_bound_is_told(max_speed_mps, told):
    """A simulated row drive at 4 m/s: the default 2 m/s bound refuses its matches and the
    pipeline says so, naming the parameter and about the speed; a 6 m/s bound is quiet."""
    from gft_odom.config import GftOdomConfig, with_values
    from gft_odom.pipeline import OdometryPipeline
    from gft_odom.sim.simulator import ScanSimulator, SimConfig
    sim = ScanSimulator.from_config(SimConfig(azimuth_step_deg=0.4, speed_mps=4.0), 'row', 16,
                                    5)
    pipeline = OdometryPipeline(with_values(GftOdomConfig(),
                                            {'registration.max_speed_mps': max_speed_mps}))
    for i in range(16):
        pipeline.register_frame(sim.scan(i).scan)
    message = pipeline.bounds_watch.message
    if not told:
        assert message is None
        assert pipeline.status_counts[IMPLAUSIBLE_STATUS] == 0
        return
    assert pipeline.status_counts[IMPLAUSIBLE_STATUS] >= 5
    assert message is not None and 'registration.max_speed_mps = 2' in message
    seen_mps = float(message.split('agreeing on ')[1].split(' m/s')[0])
    assert 3.6 <= seen_mps <= 4.4


def test_a_few_agreeing_refusals_among_many_good_matches_are_not_told():
    """The paper's scan-to-scan ICP on a U-turn: 5 wrong matches in 66 scans agreed on 3.3 m/s;
    a platform beyond the bounds is refused again and again instead."""
    from gft_odom.core.bounds_watch import BoundsWatch
    watch = BoundsWatch(2.0, 4.0)
    for k in range(66):
        refused = k % 13 == 12  # 5 refusals, all at 3.3 m/s
        assert watch.observe('fallback_implausible' if refused else 'ok',
                             3.3 if refused else None, 0.1 if refused else None) is None
    assert watch.message is None


@pytest.mark.slow
def test_a_drive_beyond_the_bound_does_not_pay_for_turned_guesses(monkeypatch):
    """Its refused matches fit well (no missed turn): re-acquisition skips the turned guesses,
    so the drive runs exactly the ICPs it runs without them."""
    from gft_odom.config import GftOdomConfig
    from gft_odom.core.registration import motion
    from gft_odom.core.registration.matching import MapMatcher
    from gft_odom.pipeline import OdometryPipeline
    from gft_odom.sim.simulator import ScanSimulator, SimConfig
    sim = ScanSimulator.from_config(SimConfig(azimuth_step_deg=0.4, speed_mps=4.0), 'row', 16,
                                    5)
    scans = [sim.scan(i).scan for i in range(16)]
    calls = []
    match = MapMatcher.match
    monkeypatch.setattr(MapMatcher, 'match',
                        lambda self, *a, **k: calls.append(1) or match(self, *a, **k))
    counts = {}
    for guesses in (2, 0):
        calls.clear()
        monkeypatch.setattr(motion, 'TURN_GUESSES', guesses)
        pipeline = OdometryPipeline(GftOdomConfig())
        statuses = [pipeline.register_frame(scan).status for scan in scans]
        assert statuses.count(IMPLAUSIBLE_STATUS) >= 5
        counts[guesses] = len(calls)
    assert counts[2] == counts[0] > 16
