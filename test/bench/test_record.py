"""The benchmark of record: drives cache, pooled KITTI drift, one run, its files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gft_odom.bench import drives as drives_module
from gft_odom.bench.drives import (
    EDGE_DRIVES,
    EDGE_TUNED_SEEDS,
    NEVER_USED_DRIVES,
    RECORD_DRIVES,
    STRESS_DRIVES,
    TRAINING_DRIVES,
    Drive,
    ensure_drives,
)
from gft_odom.bench.record import (
    KITTI_LENGTHS_M,
    Entry,
    kitti_drift_pct,
    run_record,
    write_record,
)
from gft_odom.bench.runner import BenchSequence
from gft_odom.config import GftOdomConfig
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import ConfigError
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag


def test_kitti_drift_pools_segments_not_lengths():
    metrics = {'rpe_drift_pct_100m': 1.0, 'rpe_count_100m': 300,
               'rpe_drift_pct_200m': 4.0, 'rpe_count_200m': 100,
               'rpe_drift_pct_300m': None, 'rpe_count_300m': 0,
               'rpe_drift_pct_10m': 50.0, 'rpe_count_10m': 5000}
    # (1 * 300 + 4 * 100) / 400, and the 10 m segments are not KITTI's.
    assert kitti_drift_pct(metrics) == pytest.approx(1.75)
    assert math.isnan(kitti_drift_pct({}))
    assert KITTI_LENGTHS_M[0] == 100.0 and KITTI_LENGTHS_M[-1] == 800.0


def test_entry_overrides_are_checked():
    with pytest.raises(ConfigError, match='unknown parameter'):
        Entry('x', 'default+gft', (('registration.desk', True),)).config(GftOdomConfig())
    config = Entry('x', 'default+gft', (('registration.deskew', True),)).config(GftOdomConfig())
    assert config.registration.deskew and config.evaluation.lengths_m[0] == 10.0


def test_ensure_drives_reuses_complete_drives_and_redoes_interrupted_ones(tmp_path,
                                                                          monkeypatch):
    calls = []

    def fake_simulate(out_dir, route, n_scans, seed, config, **kwargs):
        calls.append((route, seed))
        out_dir.mkdir(parents=True)
        (out_dir / 'sim_metadata.json').write_text(json.dumps({'n_scans': 7}))

    monkeypatch.setattr(drives_module, 'simulate_to_bag', fake_simulate)
    done, interrupted = Drive('spiral', 1, 100.0), Drive('lawnmower', 2, 100.0)
    (tmp_path / done.name).mkdir()
    (tmp_path / done.name / 'sim_metadata.json').write_text(json.dumps({'n_scans': 5}))
    (tmp_path / f'{interrupted.name}.partial').mkdir()  # a killed run left this
    sequences = ensure_drives([done, interrupted], tmp_path)
    assert calls == [('lawnmower', 2)]
    assert [s.n_scans for s in sequences] == [5, 7]
    assert not (tmp_path / f'{interrupted.name}.partial').exists()
    assert sequences[1].bag_path.parent == tmp_path / interrupted.name


def test_drive_sets_share_no_seed_and_the_record_offers_each():
    from pathlib import Path

    from helpers import load_script
    sets = (TRAINING_DRIVES, RECORD_DRIVES, NEVER_USED_DRIVES, EDGE_DRIVES, STRESS_DRIVES)
    seeds = [d.seed for drives in sets for d in drives]
    assert len(seeds) == len(set(seeds))
    assert len(RECORD_DRIVES) == 10 and len(NEVER_USED_DRIVES) == 4 and len(EDGE_DRIVES) == 20
    routes = {'lawnmower', 'every_other_row', 'spiral', 'out_and_back'}
    assert {d.route for d in RECORD_DRIVES} == {d.route for d in NEVER_USED_DRIVES} == routes
    assert {d.route for d in EDGE_DRIVES} == {'edge_lawnmower'}
    assert set(EDGE_TUNED_SEEDS) < {d.seed for d in EDGE_DRIVES}
    assert all(d.distance_m == 280.0 for d in RECORD_DRIVES + NEVER_USED_DRIVES + EDGE_DRIVES)
    # The stress family: at least six drives and 1.5 km, every one drawn outside the ranges.
    assert len(STRESS_DRIVES) >= 6 and sum(d.distance_m for d in STRESS_DRIVES) >= 1500.0
    assert {d.family for d in STRESS_DRIVES} == {'stress'}
    assert {d.family for drives in sets[:-1] for d in drives} == {'varied'}
    record = load_script(Path(__file__).resolve().parents[2] / 'benchmarks' / 'bench_record.py')
    assert record.DRIVE_SETS == {'record': RECORD_DRIVES, 'never-used': NEVER_USED_DRIVES,
                                 'edge': EDGE_DRIVES, 'stress': STRESS_DRIVES,
                                 'training': TRAINING_DRIVES}


@pytest.mark.slow
def test_record_runs_every_entry_on_every_drive_and_writes_its_files(tmp_path):
    result = simulate_to_bag(tmp_path / 'drive', 'uturn', 60, seed=4,
                             config=SimConfig(azimuth_step_deg=0.5), topdown_png=False)
    sequence = BenchSequence('uturn', 4, 60, result.bag_path, result.gt_csv_path)
    entries = [Entry('ours', 'default+gft'), Entry('kiss', 'kiss-icp'),
               Entry('ours, 3 keyframes', 'default+gft', (('registration.map_keyframes', 3),))]
    record = run_record(entries, [sequence])
    assert set(record.metrics) == {(e.label, 'uturn-4') for e in entries}
    for entry in entries:
        m = record.metrics[(entry.label, 'uturn-4')]
        assert m['label'] == entry.label and m['n_scans'] == 60
        assert 0.0 < m['ate_rmse_m'] < 0.5  # a 6 m drive: a broken run is metres off
        assert m['rpe_10m_pct'] is None or m['rpe_10m_pct'] >= 0.0
        distance, error = record.error_curves[(entry.label, 'uturn-4')]
        assert distance.shape == error.shape and distance[-1] > 3.0
        assert np.sqrt(np.mean(error ** 2)) == pytest.approx(m['ate_rmse_m'], rel=1e-6)
        # CitrusFarm's scoring from the same aligned errors: their mean, the last one.
        assert np.mean(error) == pytest.approx(m['ate_mean_m'], rel=1e-6)
        assert error[-1] == pytest.approx(m['end_error_m'], rel=1e-6)
    paths = write_record(record, tmp_path / 'out', {'drives': 'test'})
    document = json.loads(paths['json'].read_text())
    assert set(document['summary']) == {e.label for e in entries}
    assert document['summary']['ours']['drives'] == 1
    text = paths['markdown'].read_text()
    assert 'uturn-4' in text and 'ours, 3 keyframes' in text
    summary = document['summary']['kiss']
    kiss = record.metrics[('kiss', 'uturn-4')]
    assert summary['ate_mean_m'] == kiss['ate_mean_m']
    assert summary['end_error_m'] == kiss['end_error_m']
    assert f"| {summary['ate_mean_m']:.3f} | {summary['end_error_m']:.3f} |" in text
    assert "## Mean position error per drive [m] (CitrusFarm's scoring)" in text
    assert paths['figure'].stat().st_size > 10_000


@pytest.fixture
def measured_labels(monkeypatch) -> list[str]:
    """The labels `run_record` measures (a fake, instant `run_entry`), in order."""
    from gft_odom.bench import record as record_module
    calls = []

    def fake_run_entry(entry, sequence, base):
        calls.append(entry.label)
        trajectory = Trajectory(np.array([0, 1]), np.tile(np.eye(4), (2, 1, 1)))
        return {'label': entry.label, 'ate_rmse_m': 0.5}, (np.zeros(2), np.ones(2)), trajectory

    monkeypatch.setattr(record_module, 'run_entry', fake_run_entry)
    return calls


def test_a_run_keeps_its_trajectory_for_later_study(tmp_path, measured_labels):
    from gft_odom.bench.record import cached_trajectory
    sequence = BenchSequence('spiral', 1, 2, tmp_path / 'bag', tmp_path / 'gt.csv')
    entry = Entry('a', 'default+gft')
    assert cached_trajectory(tmp_path / 'cache', entry, sequence) is None
    run_record([entry], [sequence], cache_dir=tmp_path / 'cache')
    kept = cached_trajectory(tmp_path / 'cache', entry, sequence)
    np.testing.assert_array_equal(kept.stamps_ns, [0, 1])
    assert kept.poses.shape == (2, 4, 4)


def test_cached_only_reports_what_was_measured_and_nothing_else(tmp_path, measured_labels):
    from gft_odom.bench import record as record_module
    calls = measured_labels
    sequence = BenchSequence('spiral', 1, 2, tmp_path / 'bag', tmp_path / 'gt.csv')
    a, b = Entry('a', 'default+gft'), Entry('b', 'kiss-icp')
    run_record([a], [sequence], cache_dir=tmp_path / 'cache')
    record = run_record([a, b], [sequence], cache_dir=tmp_path / 'cache', cached_only=True)
    assert calls == ['a']  # measured once, then read back; b never measured
    assert set(record.metrics) == {('a', 'spiral-1')}
    assert record_module.summarize_record(record)['b']['drives'] == 0
    # Nothing measured at all is still a record (its figure without a legend), not a crash.
    nothing = run_record([b], [sequence], cache_dir=tmp_path / 'cache', cached_only=True)
    paths = record_module.write_record(nothing, tmp_path / 'out', {}, stem='empty')
    assert paths['figure'].is_file() and not nothing.metrics


def test_a_changed_default_is_measured_again_and_a_peer_is_not(tmp_path, measured_labels):
    from gft_odom.config import with_values
    calls = measured_labels
    sequence = BenchSequence('spiral', 1, 2, tmp_path / 'bag', tmp_path / 'gt.csv')
    ours, peer = Entry('ours', 'default+gft'), Entry('kiss', 'kiss-icp')
    run_record([ours, peer], [sequence], cache_dir=tmp_path / 'cache')
    changed = with_values(GftOdomConfig(), {'registration.map_keyframes': 7})
    run_record([ours, peer], [sequence], base=changed, cache_dir=tmp_path / 'cache')
    assert sorted(calls) == ['kiss', 'ours', 'ours']


def test_summary_shows_mean_and_end_point_error_and_fills_old_cached_pairs(tmp_path,
                                                                           measured_labels):
    from gft_odom.bench import record as record_module
    sequence = BenchSequence('spiral', 1, 2, tmp_path / 'bag', tmp_path / 'gt.csv')
    entry = Entry('a', 'default+gft')
    # The fake run_entry's metrics have no end_error_m, as pairs cached before it existed.
    first = run_record([entry], [sequence], cache_dir=tmp_path / 'cache')
    assert 'end_error_m' not in first.metrics[('a', 'spiral-1')]
    record = run_record([entry], [sequence], cache_dir=tmp_path / 'cache', cached_only=True)
    # Read back: the error curve's last value (the fake's curve is all ones).
    assert record.metrics[('a', 'spiral-1')]['end_error_m'] == 1.0
    summary = record_module.summarize_record(record)
    assert summary['a']['end_error_m'] == 1.0 and summary['a']['ate_mean_m'] is None
    table = record_module.summary_markdown(summary)
    header, _, row = table.splitlines()
    assert 'mean error [m] | end-point error [m]' in header
    # ATE, best on its one drive, no stamp audit in the fake's metrics, then the errors.
    assert '| 0.500 | 1 | n/a | 0 | n/a | 1.000 |' in row


def test_the_ablation_rows_are_the_frequencys_controls():
    from pathlib import Path

    from helpers import load_script
    record = load_script(Path(__file__).resolve().parents[2] / 'benchmarks' / 'bench_record.py')
    base = GftOdomConfig()
    configs = {e.label: e.config(base) for e in record.ABLATION_ENTRIES}
    methods = {e.label: e.method for e in record.ABLATION_ENTRIES}
    assert methods['no frequency (--no-filter)'] == 'default'
    shuffled = [label for label in configs if label.startswith('shuffled')]
    assert len(shuffled) == 3
    assert len({configs[label].pipeline.shuffle_seed for label in shuffled}) == 3
    assert all(configs[label].pipeline.shuffle_frequencies for label in shuffled)
    assert {e.method for e in record.ENTRIES} >= {'default+gft', 'genz-icp', 'ct-icp'}


def test_a_peer_that_crashes_is_a_result_and_ours_crashing_is_a_bug(tmp_path, monkeypatch):
    from gft_odom.bench import record as record_module

    def crashing_run_method(method, *args, **kwargs):
        raise MemoryError('std::bad_alloc')

    monkeypatch.setattr(record_module, 'run_method', crashing_run_method)
    monkeypatch.setattr(record_module, 'read_ground_truth', lambda path: None)
    sequence = BenchSequence('spiral', 1, 2, tmp_path / 'bag', tmp_path / 'gt.csv')
    peer = Entry('GenZ', 'genz-icp')
    record = run_record([peer], [sequence], cache_dir=tmp_path / 'cache')
    assert record.metrics[('GenZ', 'spiral-1')]['crashed'] == 'MemoryError: std::bad_alloc'
    summary = record_module.summarize_record(record)['GenZ']
    assert summary['crashed'] == 1 and summary['ate_rmse_m'] is None
    assert '| spiral-1 | n/a | crashed |' in record_module.per_drive_markdown(record)
    assert '| GenZ | 1 (1 crashed) |' in record_module.summary_markdown(
        record_module.summarize_record(record))
    # Kept like any result: read back, not run again.
    again = run_record([peer], [sequence], cache_dir=tmp_path / 'cache', cached_only=True)
    assert again.metrics[('GenZ', 'spiral-1')]['crashed']
    paths = record_module.write_record(again, tmp_path / 'out', {}, stem='crashed')
    assert 'crashed' in paths['markdown'].read_text()
    with pytest.raises(MemoryError):
        run_record([Entry('ours', 'default+gft')], [sequence])
