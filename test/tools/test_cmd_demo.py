"""`make demo` end to end, small: simulate, four replays, a table with every run."""

from __future__ import annotations

import json

import pytest

from gft_odom.params_file import load_config, packaged_params_file
from gft_odom.tools.cli import main

pytestmark = pytest.mark.slow


def test_demo_writes_a_table_and_every_run(tmp_path, capsys):
    out = tmp_path / 'demo'
    for _ in range(2):  # a second run replaces the first one's data instead of failing
        assert main(['demo', '--out', str(out), '--scans', '8', '--scenario', 'row',
                     '--quiet']) == 0
    text = (out / 'results.md').read_text()
    assert 'SYNTHETIC' in text
    results = json.loads((out / 'results.json').read_text())
    assert set(results) == {'paper', 'paper+gft', 'default', 'default+gft'}
    printed = capsys.readouterr().out
    for name, metrics in results.items():
        assert metrics['n_scans'] == 8
        # 8 scans (0.7 m) along a row: a working odometry stays within 0.5 m of the GPS track;
        # a pose copied from the ground truth would give exactly 0.
        assert 0.0 < metrics['ate_mean_m'] <= metrics['ate_rmse_m'] < 0.5, (name, metrics)
        assert json.loads((out / name / 'metrics.json').read_text())['ate_rmse_m'] == (
            metrics['ate_rmse_m'])
        assert (out / name / 'trajectory_tum.txt').is_file()
        assert (out / name / 'map.png').is_file()
        row = f'| {name} | {metrics["ate_rmse_m"]:.3f} | {metrics["ate_mean_m"]:.3f} |'
        assert row in text and row in printed
    # Each filtered run used the mask of its packaged params file, and only those runs.
    for name, params_name in (('paper+gft', 'paper_mode_gft.yaml'),
                              ('default+gft', 'default_mode_gft.yaml')):
        spectral = load_config(packaged_params_file(params_name)).spectral
        assert results[name]['mask_text'] == (
            f'B={spectral.n_bands} {sorted(spectral.band_mask)}')
    assert results['paper']['mask_text'] == results['default']['mask_text'] == 'off'
    # The filter drops points only where it is on: paper+gft keeps a fraction of them.
    assert results['paper']['points_kept_fraction'] == pytest.approx(1.0, abs=0.02)
    assert results['paper+gft']['points_kept_fraction'] < 0.9
