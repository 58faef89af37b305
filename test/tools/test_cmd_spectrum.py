"""`gft-odom spectrum` end to end: a simulated bag in, a frequency-coloured PNG out."""

from __future__ import annotations

import dataclasses

import pytest

from gft_odom.tools.cli import main


@pytest.fixture(scope='module')
def sim_run(tmp_path_factory):
    from gft_odom.sim import SimConfig, simulate_to_bag

    out = tmp_path_factory.mktemp('sim')
    config = dataclasses.replace(SimConfig(), azimuth_step_deg=1.0)
    return simulate_to_bag(out, 'row', 4, 0, config, topdown_png=False)


@pytest.mark.slow
def test_spectrum_writes_a_png(sim_run, tmp_path, capsys):
    out = tmp_path / 'fig' / 'spectrum.png'
    rc = main(['spectrum', str(sim_run.bag_path), '--gt', str(sim_run.gt_tum_path),
               '--out', str(out), '--scans', '3', '--set', 'spectral.tau_m=0.3'])
    assert rc == 0
    assert out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert out.stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert '3 scans' in printed and 'wrote' in printed


@pytest.mark.slow
def test_spectrum_reports_bad_inputs_as_exit_code_1(sim_run, tmp_path):
    missing = tmp_path / 'nope.txt'
    assert main(['spectrum', str(sim_run.bag_path), '--gt', str(missing),
                 '--out', str(tmp_path / 'a.png')]) == 1
    assert main(['spectrum', str(sim_run.bag_path), '--gt', str(sim_run.gt_tum_path),
                 '--out', str(tmp_path / 'b.png'), '--set', 'spectral.tau_m=-1.0']) == 1
    assert not (tmp_path / 'b.png').exists()
