"""Motion compensation of one sweep: per-point times from the time field or the azimuth, and
each point moved by its share of the sweep's motion; where an undeskewed sweep's pose holds."""

from __future__ import annotations

import numpy as np
import pytest
from registration_scenes import SCAN_PERIOD_S, constant_motion, make_orchard, scan_scene
from scipy.spatial.transform import Rotation

from gft_odom.core.deskew import azimuth_time_offsets, deskew_points, sweep_middle_offset_s
from gft_odom.core.geometry import invert_transform, make_transform


@pytest.fixture(scope='module')
def orchard() -> dict:
    return make_orchard()


@pytest.fixture(scope='module')
def fast_scan(orchard) -> tuple[dict, np.ndarray]:
    """A sweep at 2 m/s and 0.8 rad/s (the Jackal's limits) and its true per-scan delta."""
    pose_at = constant_motion(speed_mps=2.0, yaw_rate_rps=0.8)
    scan = scan_scene(orchard, pose_at, 0.0, noise_m=0.0)
    T0, T1 = pose_at(np.array([0.0, SCAN_PERIOD_S]))
    return scan, invert_transform(T0) @ T1


def test_deskew_with_the_time_field_undoes_a_known_distortion(fast_scan):
    scan, delta = fast_scan
    before = np.linalg.norm(scan['points'] - scan['undistorted'], axis=1)
    fixed = deskew_points(scan['points'], scan['time'], delta, SCAN_PERIOD_S)
    after = np.linalg.norm(fixed - scan['undistorted'], axis=1)
    assert before.max() > 0.15
    assert after.max() < 1e-3, after.max()


def test_deskew_from_the_azimuth_undoes_a_known_distortion(fast_scan):
    scan, delta = fast_scan
    offsets = azimuth_time_offsets(scan['points'], SCAN_PERIOD_S)
    np.testing.assert_allclose(offsets, scan['time'], atol=1e-6)
    fixed = deskew_points(scan['points'], offsets, delta, SCAN_PERIOD_S)
    assert np.linalg.norm(fixed - scan['undistorted'], axis=1).max() < 1e-3


def test_azimuth_offsets_follow_clockwise_spin_and_stamp_choice():
    azimuth = np.deg2rad([10.0, 0.0, -90.0, -170.0, 100.0, 20.0, 12.0])  # clockwise, wraps
    points = np.c_[np.cos(azimuth), np.sin(azimuth), np.zeros(azimuth.size)]
    offsets = azimuth_time_offsets(points, 0.1)
    expected = np.array([0.0, 10.0, 100.0, 180.0, 270.0, 350.0, 358.0]) / 360.0 * 0.1
    np.testing.assert_allclose(offsets, expected, atol=1e-12)
    assert np.all(np.diff(offsets) > 0.0)
    np.testing.assert_allclose(azimuth_time_offsets(points, 0.1, stamp_at_sweep_end=True),
                               expected - 0.1, atol=1e-12)
    # Past a full turn (the driver cuts on packet boundaries): the last points stay late.
    over = np.r_[points, [[np.cos(np.deg2rad(8.0)), np.sin(np.deg2rad(8.0)), 0.0]]]
    assert azimuth_time_offsets(over, 0.1)[-1] == pytest.approx(0.1 * 362.0 / 360.0)


def test_deskew_turns_each_point_by_its_share_of_a_3d_twist():
    """The vectorised Rodrigues form agrees with each point's own rotation matrix, for a twist
    with roll and pitch as well as yaw (a robot on a slope)."""
    rng = np.random.default_rng(3)
    points = rng.normal(0.0, 10.0, (500, 3))
    offsets_s = rng.uniform(-SCAN_PERIOD_S, 0.0, 500)
    omega_rps, velocity_mps = np.array([0.3, -0.2, 1.1]), np.array([1.5, 0.1, -0.05])
    delta = make_transform(Rotation.from_rotvec(omega_rps * SCAN_PERIOD_S).as_matrix(),
                           velocity_mps * SCAN_PERIOD_S)
    expected = (Rotation.from_rotvec(offsets_s[:, None] * omega_rps).apply(points)
                + offsets_s[:, None] * velocity_mps)
    np.testing.assert_allclose(deskew_points(points, offsets_s, delta, SCAN_PERIOD_S),
                               expected, atol=1e-9)


def test_deskew_without_motion_is_the_identity(fast_scan):
    scan, _ = fast_scan
    out = deskew_points(scan['points'], scan['time'], np.eye(4), SCAN_PERIOD_S)
    np.testing.assert_array_equal(out, scan['points'])


def test_an_undeskewed_sweep_holds_at_the_middle_of_its_times():
    assert sweep_middle_offset_s(np.array([0.0, 0.02, 0.099]), 0.1) == pytest.approx(0.0495)
    assert sweep_middle_offset_s(np.array([-0.1, np.nan, 0.0]), 0.1) == pytest.approx(-0.05)
    # Without per-point times: half a period from the stamp (back from a sweep-end stamp).
    assert sweep_middle_offset_s(None, 0.1) == pytest.approx(0.05)
    assert sweep_middle_offset_s(np.array([np.nan]), 0.1, True) == pytest.approx(-0.05)
