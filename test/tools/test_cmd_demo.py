"""`make demo` end to end, small: simulate, four replays, a table with every run."""

from __future__ import annotations

import json

import pytest

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
    for name, metrics in results.items():
        assert metrics['n_scans'] == 8
        assert metrics['ate_rmse_m'] is not None and metrics['ate_rmse_m'] >= 0.0
        assert (out / name / 'trajectory_tum.txt').is_file()
        assert (out / name / 'map.png').is_file()
    # Each filtered run really used its mask: paper+gft keeps a fraction of the points.
    assert results['paper']['points_kept_fraction'] == pytest.approx(1.0, abs=0.02)
    assert results['paper+gft']['points_kept_fraction'] < 0.9
    assert results['paper+gft']['mask_text'].startswith('B=4')
    assert results['default+gft']['mask_text'].startswith('B=5')
    assert '| paper+gft |' in capsys.readouterr().out
