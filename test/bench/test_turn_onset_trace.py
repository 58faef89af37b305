"""benchmarks/turn_onset_trace.py: each traced match, capped, carried on and from the truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import load_script

from gft_odom.bench.drives import Drive
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag

SCRIPT = Path(__file__).resolve().parents[2] / 'benchmarks' / 'turn_onset_trace.py'


@pytest.fixture(scope='module')
def short_drive(tmp_path_factory):
    """10 coarse scans of a varied lawn-mower route, cached as the script expects."""
    cache = tmp_path_factory.mktemp('drives')
    drive = Drive('lawnmower', 111, 200.0)
    simulate_to_bag(cache / drive.name, drive.route, 10, drive.seed,
                    SimConfig(azimuth_step_deg=1.0), topdown_png=False,
                    distance_m=drive.distance_m, vary=True)
    return cache, drive


def test_the_trace_has_one_row_per_matched_scan_and_stops_after_the_last(short_drive, tmp_path):
    cache, drive = short_drive
    script = load_script(SCRIPT)
    assert script.main(['--drive', drive.name, '--scans', '3', '6', '--cache', str(cache),
                        '--out', str(tmp_path)]) == 0
    written = json.loads((tmp_path / f'turn_onset_{drive.name}.json').read_text())
    rows = written['rows']
    assert [r['scan'] for r in rows] == [3, 4, 5, 6]
    for r in rows:
        assert r['status'] == 'ok'
        assert 1 <= r['match_iterations'] <= 30 and r['carried_on_iterations'] >= 1
        # From the true heading a match on this straight start stays within a few mrad of it.
        assert abs(r['from_true_heading_rad']) < 0.01
        assert np.isfinite([r['prediction_rad'], r['match_rad'], r['carried_on_rad'],
                            r['final_rad']]).all()
    # Each scan's outcome, matched or not: on this straight start every one is trusted,
    # close to the truth and refused nothing.
    outcomes = written['outcomes']
    assert [o['scan'] for o in outcomes] == [3, 4, 5, 6]
    for o, r in zip(outcomes, rows):
        assert o['status'] == 'ok' and o['refused_speed_mps'] is None
        assert o['heading_rad'] == pytest.approx(r['final_rad'])
        assert o['position_m'] < 0.5 and 0.5 < o['fitness'] <= 1.0
