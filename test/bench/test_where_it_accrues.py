"""where_it_accrues: a pivot's error lands in a `turn` piece, a row's in `row` pieces."""

from pathlib import Path

import numpy as np
import pytest
from helpers import load_script

from gft_odom.core.geometry import rpy_transform
from gft_odom.core.trajectory import Trajectory

ROOT = Path(__file__).resolve().parents[2]


def _script():
    return load_script(ROOT / 'benchmarks' / 'where_it_accrues.py')


def _pose(x, y, yaw):
    return rpy_transform((x, y, 0.0), (0.0, 0.0, yaw))


def _drive():
    """20 m straight east, a pivot on the spot (90 deg in 2 s), 20 m straight north; 10 Hz."""
    east = [(0.1 * i, 0.0, 0.0) for i in range(200)]
    pivot = [(20.0, 0.0, np.pi / 2 * i / 20) for i in range(1, 21)]
    north = [(20.0, 0.1 * i, np.pi / 2) for i in range(1, 201)]
    states = east + pivot + north
    stamps = np.arange(len(states), dtype=np.int64) * 100_000_000
    truth = Trajectory(stamps, np.array([_pose(*s) for s in states]))
    labels = np.array(['row'] * 200 + ['turn'] * 20 + ['row'] * 200)
    return truth, labels


def test_a_heading_error_in_a_pivot_is_charged_to_the_turn():
    script = _script()
    truth, labels = _drive()
    wrong = truth.poses.copy()
    # The estimate over-turns the pivot by 2 degrees and keeps that heading afterwards.
    extra = np.deg2rad(2.0) * np.clip((np.arange(len(wrong)) - 200) / 20, 0, 1)
    for i, angle in enumerate(extra):
        wrong[i] = wrong[i] @ _pose(0.0, 0.0, angle)
    out = script.accrual(Trajectory(truth.stamps_ns, wrong), truth, labels)
    # The pivot's 2 degrees, all of them in the (one or two) pieces that hold the pivot.
    assert 1 <= out['turn']['pieces'] <= 2
    assert out['turn']['pieces'] * out['turn']['heading_deg'] == pytest.approx(2.0, abs=0.05)
    assert out['row']['heading_deg'] < 0.05
    exact = script.accrual(truth, truth, labels)
    assert exact['turn']['heading_deg'] < 1e-9 and exact['row']['drift_pct'] < 1e-9
