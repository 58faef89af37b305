"""benchmarks/bench_frequency_classes.py: its information measures, and a quick run end to end."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import load_script

SCRIPT = Path(__file__).resolve().parents[2] / 'benchmarks' / 'bench_frequency_classes.py'


@pytest.fixture(scope='module')
def bench():
    return load_script(SCRIPT)


def test_mutual_information_is_the_entropy_for_a_perfect_band_and_zero_for_noise(bench):
    rng = np.random.default_rng(0)
    cls = rng.integers(0, 4, 40000)
    p = np.bincount(cls) / cls.size
    entropy = float(-np.sum(p * np.log2(p)))
    assert bench.mutual_information_bits(cls + 1, cls) == pytest.approx(entropy, abs=1e-9)
    assert bench.mutual_information_bits(rng.integers(1, 11, cls.size), cls) < 0.01


def test_balanced_accuracy_of_a_separating_threshold(bench):
    cls = np.array([0, 1, 2, 2, 0, 2, 3])
    nu = np.array([0.1, 0.2, 0.8, 0.9, 0.15, 0.7, 0.5])
    assert bench.best_threshold_balanced_accuracy(nu, cls) == pytest.approx(1.0)
    assert bench.best_threshold_balanced_accuracy(1.0 - nu, cls) == pytest.approx(1.0)
    mixed = np.array([0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5])
    assert bench.best_threshold_balanced_accuracy(mixed, cls) == pytest.approx(0.5)


@pytest.mark.slow
def test_quick_run_writes_every_measure(tmp_path):
    out = tmp_path / 'fc.json'
    proc = subprocess.run([sys.executable, str(SCRIPT), '--quick', '--out', str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(out.read_text())
    rows = {(r['method'], r['graph'], r['source']): r for r in data['test']}
    default = rows[('ldos_mean', 'scan_line', 'scan')]
    assert 0.0 <= default['largest_band_share'] <= 1.0
    assert set(default['band_histogram_per_class']) == {'ground', 'trunk', 'canopy', 'other'}
    assert ('ldos_mean', 'slice', 'local_map') in rows
    planarity = rows[('planarity', 'map', 'map_planarity')]
    assert 0.0 <= planarity['mutual_information_bits'] <= 2.0
    assert planarity['no_spectrum_share'] < 0.5  # most points find the map within 0.3 m
