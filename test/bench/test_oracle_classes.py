"""benchmarks/oracle_classes.py: the simulator's labels in place of the frequency."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import load_script

from gft_odom.bench.drives import Drive
from gft_odom.core.residuals import smoothness_from_nu
from gft_odom.sim.orchard import CANOPY, GROUND, TRUNK
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag

SCRIPT = Path(__file__).resolve().parents[2] / 'benchmarks' / 'oracle_classes.py'
COARSE = SimConfig(azimuth_step_deg=1.0)


@pytest.fixture(scope='module')
def oracle():
    return load_script(SCRIPT)


@pytest.fixture(scope='module')
def short_drive(tmp_path_factory):
    """12 coarse scans of a varied lawn-mower route, cached as the study expects."""
    cache = tmp_path_factory.mktemp('drives')
    drive = Drive('lawnmower', 111, 200.0)
    simulate_to_bag(cache / drive.name, drive.route, 12, drive.seed, COARSE, topdown_png=False,
                    distance_m=drive.distance_m, vary=True)
    return cache, drive


def test_oracle_smoothness_follows_the_labels(oracle):
    surface = np.array([GROUND, TRUNK, CANOPY, 3, CANOPY])
    smooth = smoothness_from_nu(oracle.oracle_nu(surface, 0.4), 0.4)
    assert smooth.tolist() == [1.0, 1.0, 0.0, 1.0, 0.0]


def test_curvature_source_reorders_the_scans_own_values_by_flatness(oracle):
    """A flat wall and a zig-zag on one ring: the wall gets the scan's highest values."""
    y = np.linspace(-2.0, 2.0, 41)
    wall = np.column_stack([np.full_like(y, 5.0), y, np.zeros_like(y)])
    az = np.linspace(1.0, 2.0, 41)
    radius = 5.0 + 0.3 * (-1.0) ** np.arange(az.size)
    zigzag = np.column_stack([radius * np.cos(az), radius * np.sin(az), np.zeros_like(az)])
    xyz = np.vstack([wall, zigzag])
    ring = np.zeros(len(xyz), dtype=np.uint16)
    c = oracle.loam_curvature(xyz, ring)
    assert np.isnan(c[:5]).all() and np.isnan(c[-5:]).all()  # windows leave the ring's ends
    inner_wall, inner_zigzag = c[5:36], c[46:77]
    assert np.nanmax(inner_wall) < 1e-6 < np.nanmin(inner_zigzag)
    nu = np.random.default_rng(0).uniform(0.0, 1.0, len(xyz))
    ranked = oracle.curvature_ranked_nu(nu, xyz, ring)
    assert np.sort(ranked).tolist() == np.sort(nu).tolist()  # the same values
    assert ranked[5:36].min() > ranked[46:77].max()


def test_labels_follow_each_scan_through_the_pipeline(oracle, short_drive):
    cache, drive = short_drive
    surface, counts = oracle.drive_labels(cache, drive, COARSE)
    assert counts.size == 12 and surface.size == counts.sum()
    assert (cache / drive.name / oracle.LABELS_FILE).is_file()
    assert 0.1 < np.mean(surface == CANOPY) < 0.9  # a route between trees
    runs = {source: oracle.run_drive(cache, drive, source, [], COARSE)
            for source in ('oracle', 'oracle_shuffled', 'frequency', 'curvature', 'none')}
    # The registration sees the labels' smooth share (every return is kept by default)...
    assert runs['oracle']['smooth_share_median'] == pytest.approx(
        np.mean(surface != CANOPY), abs=0.1)
    assert runs['oracle']['smooth_share_median'] != pytest.approx(
        runs['frequency']['smooth_share_median'], abs=1e-6)
    # ...and its control the same share, at random.
    assert runs['oracle_shuffled']['smooth_share_median'] == pytest.approx(
        runs['oracle']['smooth_share_median'], abs=1e-9)
    # The curvature source reorders the frequency's own values: the same share.
    assert runs['curvature']['smooth_share_median'] == pytest.approx(
        runs['frequency']['smooth_share_median'], abs=1e-9)
    assert runs['none']['smooth_share_median'] is None
    for run in runs.values():
        assert np.isfinite(run['ate_rmse_m'])


def test_a_bag_that_is_not_the_labels_drive_is_refused(oracle, short_drive, tmp_path):
    cache, drive = short_drive
    other = Drive('lawnmower', 112, 200.0)
    simulate_to_bag(tmp_path / other.name, other.route, 3, other.seed, COARSE,
                    topdown_png=False, distance_m=other.distance_m, vary=True)
    # The labels of drive 111 beside drive 112's bag: the point counts differ.
    (tmp_path / other.name / oracle.LABELS_FILE).write_bytes(
        (cache / drive.name / oracle.LABELS_FILE).read_bytes())
    with pytest.raises(RuntimeError, match='points, its labels'):
        oracle.run_drive(tmp_path, other, 'oracle', [], COARSE)
