"""`make demo` end to end, small: a varied drive, the package beside its peers, the paper's ICP
with and without its mask, the tables, the trajectories and the frequency colour map."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from gft_odom.io.tum import read_tum
from gft_odom.params_file import load_config, packaged_params_file, read_params_file
from gft_odom.tools.cli import main

pytestmark = pytest.mark.slow

PNG = b'\x89PNG\r\n\x1a\n'
SCANS = 12
# Coarse sweeps keep the test to seconds; the real demo runs the VLP-16's 0.2 deg.
ARGS = ['demo', '--scans', str(SCANS), '--azimuth-step-deg', '0.8', '--quiet']


@pytest.fixture(scope='module')
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp('demo') / 'out'
    for _ in range(2):  # a second run replaces the first one's data instead of failing
        assert main([*ARGS, '--out', str(out)]) == 0
    return out


def test_every_method_ran_on_the_same_drive(demo):
    results = json.loads((demo / 'results.json').read_text())
    expected = {'gft_odom', 'kiss-icp', 'paper', 'paper+mask'}
    if importlib.util.find_spec('genz_icp') is not None:
        expected.add('genz-icp')
    assert set(results) == expected
    for name, metrics in results.items():
        assert metrics['n_scans'] == SCANS, name
        assert metrics['sequence'] == 'uturn-7'
        # CitrusFarm's scoring beside the RMSE, from the same aligned errors.
        assert 0.0 <= metrics['ate_mean_m'] <= metrics['ate_rmse_m'] + 1e-12, name
        assert 0.0 <= metrics['end_error_m'] <= metrics['ate_max_m'] + 1e-12, name
        assert json.loads((demo / name / 'metrics.json').read_text()) == {
            k: v for k, v in metrics.items() if k != 'label'}
        traj = read_tum(demo / name / 'trajectory_tum.txt')
        assert len(traj) == SCANS
    # 12 sweeps from rest (about a metre): a working odometry is well within 0.5 m of the GPS
    # track; a pose copied from the ground truth would give exactly 0.
    assert 0.0 < results['gft_odom']['ate_rmse_m'] < 0.5


def test_our_runs_use_the_packaged_configs(demo):
    results = json.loads((demo / 'results.json').read_text())
    default = load_config(packaged_params_file('filter_odom.yaml'))
    ours = results['gft_odom']
    assert ours['registration_mode'] == default.registration.mode
    assert ours['use_spectral_filter'] is default.pipeline.use_spectral_filter
    written = read_params_file(demo / 'gft_odom' / 'config.yaml')
    assert written['registration.mode'] == default.registration.mode
    paper = load_config(packaged_params_file('paper_mode_gft.yaml'))
    masked = results['paper+mask']
    assert masked['registration_mode'] == results['paper']['registration_mode'] == 'paper'
    assert masked['use_spectral_filter'] is True and results['paper']['use_spectral_filter'] is (
        False)
    assert masked['band_mask'] == list(paper.spectral.band_mask)
    assert masked['n_bands'] == paper.spectral.n_bands
    # The mask drops points only where it is on.
    assert results['paper']['points_kept_fraction'] == pytest.approx(1.0, abs=0.02)
    assert masked['points_kept_fraction'] < 0.9
    # Peers are not ours: no config of ours is written beside their poses.
    assert not (demo / 'kiss-icp' / 'config.yaml').exists()
    assert results['kiss-icp']['registration_mode'] == 'kiss-icp'


def test_the_tables_are_printed_and_written(demo, capsys):
    out = demo.parent / 'printed'
    assert main([*ARGS, '--out', str(out)]) == 0
    printed = capsys.readouterr().out
    text = (out / 'results.md').read_text()
    assert printed.strip() == text.strip()
    assert 'SYNTHETIC' in text
    assert ('| method | ATE RMSE [m] | best stamp shift [ms] | ATE mean [m] | '
            'end-point error [m] | RPE drift [%] | latency median [ms] |') in text
    results = json.loads((out / 'results.json').read_text())
    main_table, paper_table = text.split("## The paper's method")
    for name, metrics in results.items():
        # Each method's stamp audit beside its ATE: the shift that would score best.
        shift = metrics['stamp_best_shift_ms']
        assert -100.0 <= shift <= 100.0 and shift % 5.0 == 0.0, (name, shift)
        row = (f'| {metrics["label"]} | {metrics["ate_rmse_m"]:.3f} | {shift:+.0f} | '
               f'{metrics["ate_mean_m"]:.3f} | {metrics["end_error_m"]:.3f} |')
        assert row in (paper_table if name.startswith('paper') else main_table), row
    assert main_table.index('gft_odom (package default') < main_table.index('kiss-icp')
    assert 'B=4 [3, 4]' in results['paper+mask']['label']


def test_figures_are_drawn(demo):
    for name in ('trajectories.png', 'frequency_map.png'):
        data = (demo / name).read_bytes()
        assert data[:8] == PNG and len(data) > 20_000, name
    text = (demo / 'results.md').read_text()
    shares = text.split('points per band of nu, 10 bands: ')[1].split(';')[0].split()
    percent = np.array([float(s.split(':')[1].rstrip('%')) for s in shares])
    assert len(percent) == 10 and abs(percent.sum() - 100.0) <= 6  # rounded to whole percent


def test_frequency_figure_counts_what_the_filter_computes(demo, tmp_path):
    from gft_odom.core.spectral import SpectralFilter
    from gft_odom.io.bags import ScanBagReader
    from gft_odom.tools.cmd_demo import frequency_figure

    config = load_config(packaged_params_file('filter_odom.yaml'))
    bag = demo / 'data' / 'base_uturn_7'
    gt = demo / 'data' / 'ground_truth' / 'gt_sensor_tum.txt'
    shares = frequency_figure(bag, gt, config, tmp_path / 'f.png', n_scans=2, every=5)
    spectral_filter = SpectralFilter.from_config(config.spectral)
    with ScanBagReader([bag]) as reader:
        scans = [scan for i, scan in enumerate(reader) if i in (0, 5)]
    nu = np.concatenate([spectral_filter.scan_frequencies(s).nu for s in scans])
    points = np.concatenate([s.points_xyz for s in scans])
    nu = nu[np.isfinite(points).all(axis=1)]
    has = np.isfinite(nu)
    assert shares['n_points'] == nu.size
    assert shares['no_spectrum_pct'] == pytest.approx(100.0 * (1.0 - has.mean()))
    counts = np.histogram(nu[has], bins=10, range=(0.0, 1.0))[0]
    np.testing.assert_allclose(shares['band_pct'], 100.0 * counts / has.sum())
    assert (tmp_path / 'f.png').read_bytes()[:8] == PNG
