"""`gft-odom replay` on a small simulated drive: CitrusFarm's scoring in metrics.json and in
the printed summary, beside the RMSE."""

from __future__ import annotations

import json

import pytest

from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag
from gft_odom.tables import accuracy_line
from gft_odom.tools.cli import main

pytestmark = pytest.mark.slow


def test_replay_writes_and_prints_mean_and_end_point_error(tmp_path, capsys):
    sim = simulate_to_bag(tmp_path / 'data', 'row', 12, seed=3,
                          config=SimConfig(azimuth_step_deg=0.8), topdown_png=False)
    out = tmp_path / 'out'
    assert main(['replay', str(sim.bag_path), '--gt', str(sim.gt_csv_path), '--out', str(out),
                 '--quiet', '--no-figures']) == 0
    metrics = json.loads((out / 'metrics.json').read_text())
    # A 1 m drive along a row: a working odometry is centimetres off, never exactly 0.
    assert 0.0 < metrics['ate_mean_m'] <= metrics['ate_rmse_m'] < 0.5
    assert 0.0 < metrics['end_error_m'] <= metrics['ate_max_m'] + 1e-12
    # The keyframes' map work is timed after the pose: in the busy time, not the latency.
    assert metrics['map_update_p95_ms'] > 0.0
    assert metrics['busy_mean_ms'] > 0.0 and metrics['busy_p95_ms'] >= metrics['latency_p95_ms']
    assert metrics['latency_at_rate_p95_ms'] >= metrics['latency_p95_ms'] - 1e-9
    printed = capsys.readouterr().out
    line = accuracy_line(metrics)
    assert line in printed.splitlines()
    assert f'ATE mean [m] {metrics["ate_mean_m"]:.3f}' in line
    assert f'end-point error [m] {metrics["end_error_m"]:.3f}' in line
    # Where the poses hold: the stamp shift that scores best, printed beside the errors.
    assert f'best stamp shift [ms] {metrics["stamp_best_shift_ms"]:+.0f}' in line
    assert len(metrics['stamp_audit']['shifts_ms']) == len(metrics['stamp_audit']['ate_rmse_m'])
