"""benchmarks/bias_study.py: the oracle harness on a tiny simulated drive."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import load_script

from gft_odom.sim.simulator import ScanSimulator, SimConfig

SCRIPT = Path(__file__).resolve().parents[2] / 'benchmarks' / 'bias_study.py'


@pytest.fixture(scope='module')
def bias():
    yield load_script(SCRIPT, register=True)  # its dataclasses look their module up
    sys.modules.pop('bias_study', None)


@pytest.fixture(scope='module')
def quiet_row():
    """A 4 m straight row, coarse (1 deg columns), noise-free; with and without distortion."""
    def make(distortion: bool) -> ScanSimulator:
        cfg = SimConfig(azimuth_step_deg=1.0, motion_distortion=distortion).quiet()
        return ScanSimulator.for_drive(cfg, 'row', 5, n_scans=45)[0]
    return make


def test_pose_error_is_signed_in_the_track_axes(bias):
    T = np.eye(4)
    along, left = np.array([0.0, 1.0, 0.0]), np.array([-1.0, 0.0, 0.0])
    moved = T.copy()
    moved[:3, 3] = [0.02, 0.05, 0.0]  # 5 cm ahead, 2 cm to the right
    a, lat, yaw = bias.pose_error(moved, T, along, left)
    assert (a, lat, yaw) == pytest.approx((0.05, -0.02, 0.0))


def test_exact_deskew_undoes_the_motion_of_a_distorted_scan(bias, quiet_row):
    sim = quiet_row(True)
    s = sim.scan(30)
    deskewed = bias.exact_deskew(sim, s.scan.points_xyz, s.scan.time_offset_s, 30)
    # The same world points seen from the stamp pose: late points (the sweep's end, the
    # robot ~0.1 m further on) move by up to the distance driven in the sweep, early ones not.
    shift = np.linalg.norm(deskewed - s.scan.points_xyz, axis=1)
    late = s.scan.time_offset_s > 0.09
    early = s.scan.time_offset_s < 0.002
    assert np.median(shift[early]) < 0.005
    assert np.median(shift[late]) > 0.05


def test_undistorted_scans_registered_from_the_truth_stay_within_a_centimetre(bias, quiet_row):
    sim = quiet_row(False)
    variants = [bias.Variant('o3d'), bias.Variant('o3d_tight', 'o3d_tight'),
                bias.Variant('tight_from_+0.1', 'o3d_tight', offset_m=0.1)]
    run = bias.oracle_run(sim, 0, min(120, sim.n_scans_in_drive), 6, variants,
                          with_pulls=False)
    assert run['index'].size >= 10
    assert run['straight'].all()

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2)))
    assert rms(run['o3d']['along_m']) < 0.01
    assert rms(run['o3d']['lateral_m']) < 0.01
    assert np.degrees(rms(run['o3d']['yaw_rad'])) < 0.2
    # Run to convergence the minimum is ~1 cm off along the track even here (porous canopy,
    # the study's finding); a guess 10 cm ahead comes back to that same minimum.
    assert rms(run['o3d_tight']['along_m']) < 0.02
    back = run['tight_from_+0.1']['along_m'] - run['o3d_tight']['along_m']
    assert rms(back) < 0.005
    assert np.all(np.abs(run['since_keyframe_m']) < 1.2)


def test_nearest_ground_truth_charges_the_gps_phase(bias, quiet_row):
    sim = quiet_row(False)
    t = bias.timing_ate(sim, sim.n_scans_in_drive)
    # The perfect trajectory scores ~0 interpolated, but nearest pairs it with a GPS sample
    # 37 ms later: a lag that alignment absorbs on one straight row at constant speed, but
    # not where the robot starts and stops (or turns back, on the long drives: 4-5 cm).
    assert t['ate_interpolate_m'] < 0.001
    assert t['ate_nearest_m'] > 2.0 * t['ate_interpolate_m']
