"""The band search end to end on small simulated bags: cache, same loop as the pipeline,
dedupe, resume after a stop, executors, the decision against the identity, outputs and the
params file it writes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gft_odom.bands import executors
from gft_odom.bands.cache import SequenceCache, build_sequence_cache, load_or_build
from gft_odom.bands.evaluate import (
    BASELINE_KEY,
    evaluate_mask,
    run_sequence,
    score,
    shift_vector,
    split_shifted_key,
)
from gft_odom.bands.masks import exhaustive_masks, mask_key, parse_mask_key
from gft_odom.bands.run import run_band_search
from gft_odom.bands.search import BandSearch, BandSearchConfig, SequenceSpec, prepare_caches
from gft_odom.config import GftOdomConfig, with_values
from gft_odom.core.spectral.bands import BandMask
from gft_odom.errors import ConfigError
from gft_odom.params_file import load_config
from gft_odom.replay import run_replay
from gft_odom.sim.simulator import SimConfig

N_SCANS = 12
CONFIG = with_values(GftOdomConfig(), {'registration.mode': 'paper'})


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Two short drives in different orchards: (train spec, test spec)."""
    from gft_odom.sim.writer import simulate_to_bag
    specs = []
    for name, scenario, seed in (('train', 'row', 5), ('test', 'uturn', 6)):
        sim = simulate_to_bag(tmp_path_factory.mktemp(name), scenario=scenario,
                              n_scans=N_SCANS, seed=seed,
                              config=SimConfig(azimuth_step_deg=0.8), topdown_png=False)
        specs.append(SequenceSpec((str(sim.bag_path),), str(sim.gt_csv_path), name))
    return specs


@pytest.fixture(scope='module')
def train_cache(bags, tmp_path_factory):
    spec = bags[0]
    return build_sequence_cache(spec.bags, spec.gt_path, CONFIG, [2, 3], name='train')


def test_cache_round_trip_and_reuse(bags, train_cache, tmp_path):
    assert len(train_cache) == N_SCANS
    path = tmp_path / 'c.npz'
    spec = bags[0]
    first = load_or_build(path, spec.bags, spec.gt_path, CONFIG, [2, 3], name='train')
    assert path.exists()
    again = SequenceCache.load(path)
    assert again.key == first.key == train_cache.key
    for n in (2, 3):
        np.testing.assert_array_equal(again.bands[n], train_cache.bands[n])
    np.testing.assert_array_equal(again.points_xyz, train_cache.points_xyz)
    # Other spectral parameters: another key, so the stale file is not reused.
    other = with_values(CONFIG, {'spectral.tau_m': 0.3})
    rebuilt = load_or_build(path, spec.bags, spec.gt_path, other, [2, 3], name='train')
    assert rebuilt.key != first.key


def test_cached_evaluation_equals_a_plain_replay(bags, train_cache):
    """The search's per-mask run is the pipeline's loop: same trajectory error as a replay."""
    mask = BandMask(3, frozenset({2, 3}))
    spec = bags[0]
    cfg = with_values(CONFIG, {'spectral.n_bands': 3, 'spectral.band_mask': [2, 3]})
    replay = run_replay(spec.bags, cfg, gt_path=spec.gt_path)
    row = run_sequence(train_cache, CONFIG, mask)
    assert row['ate_rmse_m'] == pytest.approx(replay.metrics['ate_rmse_m'], rel=1e-9)
    assert row['points_kept_fraction'] == pytest.approx(replay.metrics['points_kept_fraction'])
    assert row['points_kept_fraction'] < 0.99


def test_all_pass_mask_equals_the_unfiltered_baseline(train_cache):
    all_pass = evaluate_mask([train_cache], CONFIG, BandMask.all_pass(2))
    baseline = evaluate_mask([train_cache], CONFIG, None)
    assert all_pass['ate_rmse_m'] == pytest.approx(baseline['ate_rmse_m'], rel=1e-9)
    assert baseline['key'] == BASELINE_KEY


def test_a_whole_voxel_shift_gives_the_same_error(train_cache):
    """The shifted runs map their poses back exactly: shifted by whole voxels of both grids
    (3 source voxels = 4 map voxels = 1.2 m) the paper mode's scan-to-scan ICP sees the same
    voxels and gives the same error; a third of a voxel moves it, a little."""
    mask = BandMask.all_pass(2)
    plain = evaluate_mask([train_cache], CONFIG, mask)['ate_rmse_m']
    whole = evaluate_mask([train_cache], CONFIG, mask, shift_vector(CONFIG, 3.0))['ate_rmse_m']
    third = evaluate_mask([train_cache], CONFIG, mask, shift_vector(CONFIG, 1 / 3))['ate_rmse_m']
    assert whole == pytest.approx(plain, rel=1e-6)
    assert third != pytest.approx(plain, rel=1e-6)
    assert abs(third - plain) < 0.1 * plain


def _distinct_kept_sets(cache: SequenceCache, masks) -> int:
    flags = (CONFIG.spectral.keep_isolated,)
    return len({b''.join(np.packbits(cache.keep(i, m, *flags)).tobytes()
                         for i in range(len(cache))) for m in masks})


def test_search_outputs_and_params_file(bags, train_cache, tmp_path):
    out = tmp_path / 'search'
    summary = run_band_search([bags[0]], CONFIG, out, BandSearchConfig(2, 3),
                              test=[bags[1]])
    for name in ('results.jsonl', 'spread.jsonl', 'ranking.csv', 'summary.json', 'summary.md',
                 'best_mask.yaml', 'fig6_top_masks.png', 'fig7_band_correlation.png',
                 'fig8_narrow_intervals.png', 'cache/train.npz'):
        assert (out / name).exists(), name
    rows = [json.loads(line) for line in (out / 'results.jsonl').read_text().splitlines()]
    keys = {r['key'] for r in rows}
    assert len(keys) == len(rows) == 3 + 7 + 1  # B = 2, 3 and the baseline
    # The all-pass masks keep the same points at every B: evaluated once, the identity of
    # the smallest B standing for them.
    dup = {r['key']: r.get('duplicate_of') for r in rows}
    assert dup['B3:111'] == 'B2:11' and dup['B2:11'] is None
    # One evaluation per distinct set of kept points (the all-pass twin is one of the repeats).
    n_distinct = _distinct_kept_sets(train_cache, exhaustive_masks(2, 3))
    assert n_distinct < 10 and summary['masks_evaluated'] == n_distinct
    assert summary['masks_evaluated_this_run'] == n_distinct + 1  # and the baseline
    assert summary['masks_evaluated'] == sum(
        1 for r in rows if r['key'] != BASELINE_KEY and not r.get('duplicate_of'))
    # The decision: the best in-sample mask against the identity, with the spread measured
    # on shifted runs of both (resumable in spread.jsonl).
    by_key = {r['key']: r for r in rows}
    best = min((r for r in rows if r['key'] != BASELINE_KEY and not r.get('duplicate_of')),
               key=lambda r: (score(r), r['points_kept_fraction']))  # a lost mask: inf
    d = summary['decision']
    assert d['identity_key'] == 'B2:11' and d['best_key'] == best['key']
    assert d['identity_ate_rmse_m'] == by_key['B2:11']['ate_rmse_m']
    assert d['best_ate_rmse_m'] == best['ate_rmse_m'] and d['spread_m'] > 0.0
    beats = best['ate_rmse_m'] < d['identity_ate_rmse_m'] - d['spread_m']
    assert d['chosen'] == ('best' if beats else 'identity')
    chosen = by_key[d['chosen_key']]
    assert chosen['ate_rmse_m'] <= by_key['B2:11']['ate_rmse_m']
    spread_rows = [json.loads(x) for x in (out / 'spread.jsonl').read_text().splitlines()]
    assert {split_shifted_key(r['key'])[0] for r in spread_rows} == {'B2:11', best['key']}
    assert len(spread_rows) == 4
    # The chosen mask reloads unchanged as a config.
    cfg = load_config(out / 'best_mask.yaml')
    assert cfg.spectral.n_bands == chosen['n_bands']
    assert list(cfg.spectral.band_mask) == chosen['bands']
    assert summary['chosen_mask']['band_mask'] == chosen['bands']
    assert cfg.pipeline.use_spectral_filter and cfg.registration.mode == 'paper'
    assert summary['in_sample']['label'].startswith('in-sample')
    assert summary['held_out']['label'].startswith('held-out')
    assert summary['held_out']['baseline']['key'] == BASELINE_KEY
    assert set(summary['held_out']['chosen']['per_sequence']) == {'test'}
    text = (out / 'summary.md').read_text()
    assert 'in-sample (train)' in text and 'held-out (test)' in text
    assert 'run-to-run spread' in text and d['reason'] in text
    assert 'in-sample' in (out / 'ranking.csv').read_text().splitlines()[1]


def _fake_evaluation(scores: dict[str, float], shifted: dict[str, tuple[float, float]],
                     calls: list[str]):
    """An `evaluate_key` that gives each mask the score in `scores` (0.05 m for the rest)
    and each shifted run of a mask the value of its shift in `shifted` (else its score)."""
    def evaluate_key(sequences, config, key):
        calls.append(key)
        base, fraction = split_shifted_key(key)
        mask = None if base == BASELINE_KEY else parse_mask_key(base)
        value = scores.get(base, 0.05)
        if fraction is not None:
            value = shifted.get(base, (value, value))[round(fraction * 3) - 1]
        return {'key': key, 'n_bands': mask.n_bands if mask else 0,
                'mask': mask.as_bitstring() if mask else '',
                'bands': mask.as_list() if mask else [],
                'n_kept_bands': len(mask.bands) if mask else 0, 'ate_rmse_m': value,
                'ate_mean_m': value, 'paper_mse_m2': value ** 2, 'points_kept_fraction': 0.5,
                'fallbacks': 0, 'per_sequence': {}, 'eval_s': 0.0}
    return evaluate_key


@pytest.mark.parametrize('best_ate, chosen', [(0.0185, 'B2:11'), (0.0120, 'B2:01')])
def test_the_search_returns_a_mask_only_when_it_beats_the_identity(
        bags, tmp_path, monkeypatch, best_ate, chosen):
    """The identity scores 20 mm, its shifted runs 21 and 19.5; the best mask's shifted runs
    move by 3 mm: a 1.5 mm win is within the spread (the identity is returned), an 8 mm win
    is not (the mask is)."""
    best = 'B2:01'
    calls: list[str] = []
    monkeypatch.setattr(executors, 'evaluate_key', _fake_evaluation(
        {'B2:11': 0.0200, best: best_ate, 'B2:10': 0.0300},
        {'B2:11': (0.0210, 0.0195), best: (best_ate + 0.001, best_ate + 0.003)}, calls))
    out = tmp_path / 's'
    summary = run_band_search([bags[0]], CONFIG, out, BandSearchConfig(2, 2), figures=False)
    d = summary['decision']
    assert d['best_key'] == best and d['identity_key'] == 'B2:11'
    assert d['spread_m'] == pytest.approx(0.003)
    assert d['chosen_key'] == chosen
    assert summary['in_sample']['chosen']['key'] == chosen
    cfg = load_config(out / 'best_mask.yaml')
    assert mask_key(BandMask.parse(cfg.spectral.band_mask, cfg.spectral.n_bands)) == chosen
    written = json.loads((out / 'summary.json').read_text())['decision']
    assert written['chosen_key'] == chosen and written['spread_m'] == pytest.approx(0.003)
    assert summary['in_sample']['chosen']['ate_rmse_m'] <= d['identity_ate_rmse_m']
    # A second run reads every result back, the shifted runs too.
    calls.clear()
    again = run_band_search([bags[0]], CONFIG, out, BandSearchConfig(2, 2), figures=False)
    assert calls == [] and again['decision'] == d


def test_killed_search_resumes_where_it_stopped(bags, tmp_path):
    search_cfg = BandSearchConfig(2, 3)
    full = tmp_path / 'full'
    run_band_search([bags[0]], CONFIG, full, search_cfg, figures=False)
    part = tmp_path / 'part'
    stopped = run_band_search([bags[0]], CONFIG, part, search_cfg, figures=False,
                              max_new_results=4)
    assert stopped == {'stopped_after': 4}
    lines = (part / 'results.jsonl').read_text().splitlines()
    assert len(lines) == 4
    # A kill in the middle of a write leaves half a line: it is dropped and redone.
    with (part / 'results.jsonl').open('a') as f:
        f.write(lines[-1][: len(lines[-1]) // 2])
    caches, paths = prepare_caches([bags[0]], CONFIG, [2, 3], part / 'cache')
    search = BandSearch(caches, CONFIG, part, paths)
    assert len(search.log.rows) == 4
    search.exhaustive(2, 3)
    # What the full run evaluated (duplicates of an earlier mask are not run), less what the
    # stopped run had already evaluated.
    def n_run(rows):
        return sum(not json.loads(x).get('duplicate_of') for x in rows)

    assert search.n_evaluated == n_run((full / 'results.jsonl').read_text().splitlines()) - (
        n_run(lines))
    done = {json.loads(x)['key']: json.loads(x)
            for x in (part / 'results.jsonl').read_text().splitlines()}
    want = {json.loads(x)['key']: json.loads(x)
            for x in (full / 'results.jsonl').read_text().splitlines()}
    assert done.keys() == want.keys()
    for key in want:
        assert score(done[key]) == pytest.approx(score(want[key]), rel=1e-9)  # lost: inf


def test_results_of_other_parameters_are_not_mixed(bags, tmp_path):
    out = tmp_path / 's'
    run_band_search([bags[0]], CONFIG, out, BandSearchConfig(2, 2), figures=False)
    other = with_values(CONFIG, {'registration.voxel_size_m': 0.5})
    with pytest.raises(ConfigError, match='another --out'):
        run_band_search([bags[0]], other, out, BandSearchConfig(2, 2), figures=False)


@pytest.mark.slow
def test_process_pool_equals_in_process(bags, tmp_path):
    local = run_band_search([bags[0]], CONFIG, tmp_path / 'one', BandSearchConfig(2, 3),
                            figures=False)
    pool = run_band_search([bags[0]], CONFIG, tmp_path / 'two', BandSearchConfig(2, 3),
                           workers=2, figures=False)
    assert pool['chosen_mask'] == local['chosen_mask']
    a = _rows(tmp_path / 'one')
    b = _rows(tmp_path / 'two')
    assert a.keys() == b.keys()
    for key in a:
        assert score(b[key]) == pytest.approx(score(a[key]), rel=1e-9)  # lost: inf


def test_smart_search_uses_fewer_evaluations(bags, tmp_path):
    caches, paths = prepare_caches([bags[0]], CONFIG, [2, 3, 4, 5], tmp_path / 'cache')
    search = BandSearch(caches, CONFIG, tmp_path / 'smart', paths)
    cfg = BandSearchConfig(2, 5, strategy='smart', smart_seed_max_bands=2, beam_width=1,
                           smart_max_rounds=2)
    rows = search.smart(cfg)
    n_exhaustive = 3 + 7 + 15 + 31
    assert BASELINE_KEY in rows
    # The identity of every band count it searches is a candidate.
    assert {'B2:11', 'B5:11111'} <= rows.keys()
    assert len(rows) - 1 < n_exhaustive / 2
    assert any(r['n_bands'] == 5 for r in rows.values())


def _rows(out):
    return {json.loads(x)['key']: json.loads(x)
            for x in (out / 'results.jsonl').read_text().splitlines()}


@pytest.fixture
def ray_head(monkeypatch):
    """A Ray head on this host, started as our own `ray start --block` process, with a
    per-test auth token (Ray 2.60 clusters require one); stopped by its pid afterwards."""
    import importlib.util
    import secrets
    import socket
    import subprocess
    import sys
    import time
    from pathlib import Path
    monkeypatch.setenv('RAY_AUTH_MODE', 'token')
    monkeypatch.setenv('RAY_AUTH_TOKEN', secrets.token_hex(32))
    # Set before ray is imported: it reads the auth mode when it loads.
    assert importlib.util.find_spec('ray') is not None, 'ray is a test dependency'
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen(
        [str(Path(sys.executable).parent / 'ray'), 'start', '--head', '--block',
         '--node-ip-address=127.0.0.1', f'--port={port}', '--num-cpus=2',
         '--include-dashboard=false', '--disable-usage-stats'],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120.0
        while True:
            try:
                socket.create_connection(('127.0.0.1', port), timeout=1.0).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f'ray head did not start (exit code {proc.poll()})')
                time.sleep(0.5)
        yield f'127.0.0.1:{port}'
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_ray_cluster_equals_local_executor(bags, tmp_path, ray_head):
    import ray
    local = run_band_search([bags[0]], CONFIG, tmp_path / 'local', BandSearchConfig(2, 2),
                            figures=False)
    on_ray = run_band_search([bags[0]], CONFIG, tmp_path / 'ray', BandSearchConfig(2, 2),
                             ray_address=ray_head, figures=False)
    assert not ray.is_initialized()  # the executor disconnected after the search
    assert on_ray['chosen_mask'] == local['chosen_mask']
    a, b = _rows(tmp_path / 'local'), _rows(tmp_path / 'ray')
    assert a.keys() == b.keys() and len(a) == 4
    for key in a:
        assert score(b[key]) == pytest.approx(score(a[key]), rel=1e-9)  # lost: inf

def test_cli_search_bands(bags, tmp_path, capsys):
    from gft_odom.tools.cli import main
    out = tmp_path / 'cli'
    train, test = bags
    code = main(['search-bands', *train.bags, '--gt', train.gt_path, '--out', str(out),
                 '--min-bands', '2', '--max-bands', '2', '--mode', 'paper', '--test',
                 *test.bags, '--test-gt', test.gt_path, '--no-figures', '--quiet'])
    assert code == 0
    printed = capsys.readouterr().out
    assert 'held-out (test)' in printed and 'in-sample (train)' in printed
    assert load_config(out / 'best_mask.yaml').spectral.n_bands == 2
    # One bag, two ground truths: refused with exit code 1, nothing run.
    bad = main(['search-bands', *train.bags, '--gt', train.gt_path, '--gt', test.gt_path,
                '--out', str(tmp_path / 'bad'), '--quiet'])
    assert bad == 1
    assert not (tmp_path / 'bad').exists()
