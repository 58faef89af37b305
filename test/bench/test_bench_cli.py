"""`gft-odom bench` end to end, tiny: every method runs, JSON / Markdown / PNGs are written."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gft_odom.bench.kiss import KissIcpConfig
from gft_odom.bench.report import LATENCY_TARGET_P95_MS, check_targets, summarize_methods
from gft_odom.bench.runner import METHODS, method_config, run_bench, simulate_sequences
from gft_odom.config import GftOdomConfig
from gft_odom.errors import ConfigError
from gft_odom.sim.simulator import SimConfig
from gft_odom.tools.cli import main

N_SCANS = 10


@pytest.fixture(scope='module')
def bench_outputs(tmp_path_factory):
    out = tmp_path_factory.mktemp('bench')
    params = out / 'mask.yaml'
    from gft_odom.params_file import write_params_file
    write_params_file(params, GftOdomConfig().__class__(
        spectral=GftOdomConfig().spectral.__class__(n_bands=3, band_mask=(2, 3))))
    argv = ['bench', '--seeds', '7', '--scenarios', 'row', '--scans', str(N_SCANS),
            '--azimuth-step-deg', '0.8', '--config', str(params), '--quiet',
            '--json', str(out / 'results' / 'bench.json'),
            '--markdown', str(out / 'docs' / 'benchmarks.md'), '--profile-scans', '3',
            '--mask-provenance', 'test mask']
    assert main(argv) == 0
    return out


@pytest.mark.slow
def test_json_has_all_methods_with_sane_numbers(bench_outputs):
    doc = json.loads((bench_outputs / 'results' / 'bench.json').read_text())
    assert list(doc['summary']) == list(METHODS)
    assert len(doc['runs']) == len(METHODS)
    assert doc['settings']['band_mask'] == [2, 3] and doc['settings']['n_bands'] == 3
    for run in doc['runs']:
        assert run['n_scans'] == N_SCANS
        assert run['latency_median_ms'] > 0.0
        assert run['latency_p95_ms'] >= run['latency_median_ms']
        # 10 scans at ~1 m/s: an odometry that works is within a metre of the GPS track.
        assert 0.0 <= run['ate_rmse_m'] < 1.0, run
        assert run['ate_mean_m'] <= run['ate_rmse_m'] + 1e-12
        assert 0.0 <= run['end_error_m'] <= run['ate_max_m'] + 1e-12
        assert math.isclose(run['paper_mse_m2'], run['ate_rmse_m'] ** 2, rel_tol=1e-6)
        assert 0 < run['points_kept_mean'] <= run['points_in_mean']
    kept = {r['method']: r['points_kept_mean'] for r in doc['runs']}
    # The (2, 3) mask drops the low band: the filtered runs keep fewer points.
    assert kept['paper+gft'] < kept['paper'] and kept['default+gft'] < kept['default']
    # Every target's verdict follows from the summary's numbers.
    summary = doc['summary']
    met = {t['target']: t['met'] for t in doc['targets']}
    assert len(met) == 7
    for mode in ('paper', 'default'):
        cut = 1.0 - summary[f'{mode}+gft']['ate_rmse_m'] / summary[mode]['ate_rmse_m']
        assert met[f'GFT filter cuts ATE RMSE by >= 50 % ({mode} registration, held-out)'] is (
            cut >= 0.5)
    assert met['our default pipeline (default + GFT filter) ATE RMSE <= kiss-icp'] is (
        summary['default+gft']['ate_rmse_m'] <= summary['kiss-icp']['ate_rmse_m'])
    for method in ('default', 'default+gft'):
        assert met[f'{method}: median latency <= kiss-icp in the same run'] is (
            summary[method]['latency_median_ms'] <= summary['kiss-icp']['latency_median_ms'])
        assert met[f'{method}: p95 latency < {LATENCY_TARGET_P95_MS:.0f} ms'] is (
            summary[method]['latency_p95_ms'] < LATENCY_TARGET_P95_MS)
    assert set(doc['profiles']) == {'paper+gft', 'default+gft', 'kiss-icp'}


@pytest.mark.slow
def test_markdown_and_plots_written(bench_outputs):
    page = (bench_outputs / 'docs' / 'benchmarks.md').read_text()
    doc = json.loads((bench_outputs / 'results' / 'bench.json').read_text())
    for method in METHODS:
        assert f'| {method} |' in page
        # CitrusFarm's scoring beside the RMSE: ATE mean, then the end-point error.
        row = doc['summary'][method]
        assert (f"| {method} | {row['ate_rmse_m']:.3f} | {row['ate_mean_m']:.3f} | "
                f"{row['end_error_m']:.3f} |") in page
    assert '| ATE RMSE [m] | ATE mean [m] | end-point error [m] |' in page
    assert 'synthetic' in page and 'test mask' in page
    for name in ('bench_ate.png', 'bench_latency.png', 'bench_trajectories.png'):
        png = bench_outputs / 'docs' / name
        assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
        assert f']({name})' in page


def test_method_config_switches_mode_and_filter():
    base = GftOdomConfig()
    assert method_config(base, 'paper').registration.mode == 'paper'
    assert method_config(base, 'paper').pipeline.use_spectral_filter is False
    assert method_config(base, 'default+gft').pipeline.use_spectral_filter is True
    assert method_config(base, 'kiss-icp').pipeline.use_spectral_filter is False
    # 'loam' is an evalio peer now (PEER_METHODS); any other name is still refused.
    assert method_config(base, 'loam').pipeline.use_spectral_filter is False
    with pytest.raises(ConfigError, match='unknown bench method'):
        method_config(base, 'loam3d')


def test_default_bench_methods_stay_the_five():
    from gft_odom.bench.runner import ALL_METHODS, PEER_METHODS
    from gft_odom.tools.cli import build_parser
    assert list(METHODS) == ['paper', 'paper+gft', 'default', 'default+gft', 'kiss-icp']
    assert not set(PEER_METHODS) & set(METHODS)
    assert list(ALL_METHODS) == list(METHODS) + list(PEER_METHODS)
    assert {'genz-icp', 'genz-icp-no-deskew', 'ct-icp'} <= set(PEER_METHODS)
    args = build_parser('bench').parse_args(['bench'])
    assert args.methods == list(METHODS)
    assert build_parser('bench').parse_args(['bench', '--methods', 'loam']).methods == ['loam']


@pytest.mark.parametrize('field, value', [('voxel_size_m', 0.0), ('min_range_m', 200.0),
                                          ('max_num_threads', -1), ('max_range_m', math.nan)])
def test_kiss_config_refuses_bad_values(field, value):
    with pytest.raises(ConfigError, match=field):
        KissIcpConfig(**{field: value}).validate()


@pytest.mark.slow
def test_targets_follow_the_numbers(tmp_path):
    """Targets are computed from the measured runs, not hard-coded: doctor one run's ATE."""
    seqs = simulate_sequences(tmp_path, ['row'], [8], 6, SimConfig(azimuth_step_deg=0.8))
    bench = run_bench(seqs, GftOdomConfig(), ['default', 'default+gft'])
    run = next(r for r in bench.runs if r.method == 'default+gft')
    plain = next(r for r in bench.runs if r.method == 'default').metrics['ate_rmse_m']
    for factor, met in ((0.4, True), (0.6, False)):
        run.replay.metrics['ate_rmse_m'] = factor * plain
        target = check_targets(bench, summarize_methods(bench))[0]
        assert target['met'] is met
    summary = summarize_methods(bench)
    assert summary['default']['n_scans'] == 6
    assert np.isclose(summary['default']['latency_median_ms'],
                      1e3 * np.median(bench.runs[0].replay.latency_s))


def test_a_paced_run_hands_each_scan_over_at_its_stamp(tmp_path):
    import time

    from gft_odom.bench.runner import BenchSequence, run_method
    from gft_odom.sim.writer import simulate_to_bag
    result = simulate_to_bag(tmp_path / 'drive', 'row', 8, seed=3,
                             config=SimConfig(azimuth_step_deg=0.8), topdown_png=False)
    sequence = BenchSequence('row', 3, 8, result.bag_path, result.gt_csv_path)
    config = GftOdomConfig()
    unpaced = run_method('default+gft', sequence, config)
    t0 = time.perf_counter()
    paced = run_method('default+gft', sequence, config, paced=True)
    stamps = paced.replay.sensor_trajectory.stamps_ns
    # The last scan is not handed over before its stamp's offset from the first.
    assert time.perf_counter() - t0 >= (stamps[-1] - stamps[0]) * 1e-9
    assert paced.metrics['paced'] and not unpaced.metrics['paced']
    # The latency is measured at the sensor's rate: no model of it on top, the same poses.
    assert 'latency_at_rate_p95_ms' in unpaced.metrics
    assert 'latency_at_rate_p95_ms' not in paced.metrics
    assert paced.metrics['latency_median_ms'] > 0.0
    np.testing.assert_array_equal(paced.replay.sensor_trajectory.poses,
                                  unpaced.replay.sensor_trajectory.poses)
