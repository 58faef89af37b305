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


def test_the_information_within_range_deciles_is_what_range_does_not_tell(bench):
    """A band that is the range decile tells the class only through the range."""
    rng = np.random.default_rng(1)
    range_m = rng.uniform(1.0, 50.0, 20000)
    cls = (range_m > 25.0).astype(int) * 2  # near: ground, far: canopy
    by_range = np.digitize(range_m, [10.0, 25.0, 40.0]) + 1
    assert bench.mutual_information_bits(by_range, cls) > 0.9
    assert bench.mutual_information_within_range_bits(by_range, cls, range_m) < 0.05


@pytest.mark.slow
def test_quick_run_writes_every_measure(tmp_path):
    out = tmp_path / 'fc.json'
    proc = subprocess.run([sys.executable, str(SCRIPT), '--quick', '--out', str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(out.read_text())
    rows = {r['frequency']: r for r in data['test']}
    assert set(rows) == {label for label, _ in load_script(SCRIPT).FREQUENCIES}
    for row in rows.values():
        assert 0.0 <= row['largest_band_share'] <= 1.0
        assert 0.0 <= row['mutual_information_within_range_bits'] <= 2.0
        assert -1.0 <= row['correlation_with_log_range'] <= 1.0
