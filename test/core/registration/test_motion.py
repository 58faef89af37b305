"""The motion model on its own: capping, plausibility, loss of track and re-acquisition."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import make_transform
from gft_odom.core.registration import RegistrationConfig
from gft_odom.core.registration import motion as motion_module
from gft_odom.core.registration.motion import (
    MotionModel,
    delta_of_twist,
    scale_delta,
    transform_magnitude,
)

CONFIG = RegistrationConfig()  # 2 m/s, 4 rad/s, margin 0.5, gap 1 s
STEP_NS = 100_000_000


def test_capping_keeps_the_direction():
    model = MotionModel(CONFIG)
    capped = model.capped(np.array([0.0, 0.0, 10.0, 3.0, 4.0, 0.0]))
    np.testing.assert_allclose(capped[:3], [0.0, 0.0, CONFIG.max_yaw_rate_rps])
    np.testing.assert_allclose(capped[3:], [1.2, 1.6, 0.0])  # 2 m/s along (0.6, 0.8)
    slow = np.array([0.0, 0.0, 0.5, 1.0, 0.0, 0.0])
    np.testing.assert_array_equal(model.capped(slow), slow)


@pytest.mark.parametrize('T, plausible', [
    (make_transform(None, [0.29, 0.0, 0.0]), True),  # bound 2 m/s x 1.5 x 0.1 s = 0.3 m
    (make_transform(None, [0.31, 0.0, 0.0]), False),
    (make_transform(Rotation.from_rotvec([0.0, 0.0, 0.59]).as_matrix()), True),  # 0.6 rad
    (make_transform(Rotation.from_rotvec([0.0, 0.0, 0.61]).as_matrix()), False),
])
def test_a_motion_beyond_the_bounds_times_one_plus_margin_is_implausible(T, plausible):
    model = MotionModel(CONFIG)
    assert model.is_plausible(T, 0.1) is plausible
    speed, rate = model.last_implied_rates  # what a refusal reports
    assert speed == pytest.approx(np.linalg.norm(T[:3, 3]) / 0.1)
    assert rate == pytest.approx(Rotation.from_matrix(T[:3, :3]).magnitude() / 0.1)


def test_after_a_gap_the_velocity_is_dropped_and_reacquisition_is_pending():
    model = MotionModel(CONFIG)
    moving = np.array([0.0, 0.0, 0.3, 1.5, 0.0, 0.0])
    model.trust(0, np.eye(4), 'first')
    model.advance(0, np.eye(4))
    model.velocity = moving
    T_moved = delta_of_twist(moving, 0.1)
    dt_s, T_pred = model.predict(STEP_NS)  # a normal step: extrapolated
    np.testing.assert_allclose(T_pred, T_moved)
    model.trust(STEP_NS, T_moved, 'ok')
    model.advance(STEP_NS, T_moved)
    np.testing.assert_allclose(model.velocity, moving)

    dt_s, T_pred = model.predict(STEP_NS + 2_000_000_000)  # 2 s later: a gap
    assert dt_s == pytest.approx(2.0)
    assert model.recovering
    np.testing.assert_array_equal(model.velocity, np.zeros(6))
    np.testing.assert_array_equal(T_pred, T_moved)  # no velocity to extrapolate
    # Re-acquisition starts from the trusted pose: standing, the velocity before the loss,
    # and its straight-line part.
    guesses = model.reacquisition_guesses(STEP_NS + 2_000_000_000)
    velocities = np.array([velocity for velocity, _ in guesses])
    np.testing.assert_allclose(velocities, [np.zeros(6), moving, [0, 0, 0, 1.5, 0, 0]])
    np.testing.assert_array_equal(guesses[0][1], T_moved)
    # A recovered pose ends the loss with the velocity of the guess that won.
    model.trust(STEP_NS + 2_000_000_000, T_moved, 'recovered', moving)
    assert not model.recovering
    np.testing.assert_array_equal(model.velocity, moving)


def test_without_track_loss_a_gap_keeps_the_velocity():
    """Paper mode: no map to re-acquire against, so nothing is dropped."""
    model = MotionModel(CONFIG, track_loss=False)
    model.advance(0, np.eye(4))
    model.velocity = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    model.predict(2_000_000_000)
    assert not model.recovering and model.velocity[3] == 1.0


def test_turn_guesses_change_the_yaw_rate_either_way_capped():
    model = MotionModel(CONFIG)  # 2 guesses a side, 1 rad/s apart
    model.trust(0, np.eye(4), 'first')
    model.velocity = np.array([0.0, 0.0, 2.5, 1.0, 0.0, 0.0])
    guesses = model.turn_guesses(STEP_NS, retry=True)
    yaw_rates = [velocity[2] for velocity, _ in guesses]
    np.testing.assert_allclose(yaw_rates, [1.5, 3.5, 0.5, CONFIG.max_yaw_rate_rps])  # 4.5 capped
    velocity, T_init = guesses[0]
    np.testing.assert_allclose(T_init, delta_of_twist(velocity, 0.1))  # from the trusted pose
    # 30 ms after the trusted pose (a copy, or jitter) there is no turn to guess.
    assert model.turn_guesses(STEP_NS * 3 // 10, retry=True) == []


@pytest.mark.parametrize('second_reference', [False, True])
def test_a_slid_trusted_pose_can_be_passed_over_by_the_one_before_it(second_reference):
    """1.8 m/s along x; the second trusted pose slid 0.15 m back. The true third pose is
    0.33 m from it in 0.1 s (beyond 0.3 m) but 0.36 m from the first in 0.2 s (within 0.6).
    Without the trusted pose before (a model that forgets it), the true pose is refused."""
    model = MotionModel(CONFIG)
    model.trust(0, np.eye(4), 'first')
    model.advance(0, np.eye(4))
    slid = make_transform(None, [0.18 - 0.15, 0.0, 0.0])
    model.trust(STEP_NS, slid, 'ok')
    model.advance(STEP_NS, slid)
    if not second_reference:
        model.previous_trusted = None
    true_next = make_transform(None, [0.36, 0.0, 0.0])
    assert model.plausible_since_trusted(2 * STEP_NS, true_next) is second_reference
    assert model.last_implied_rates[0] == pytest.approx(3.3)  # from the last trusted pose
    velocity = model.implied_velocity(2 * STEP_NS, true_next)
    # From the first pose over 0.2 s: 1.8 m/s; from the slid one: 3.3 m/s, capped at 2.
    assert velocity[3] == pytest.approx(1.8 if second_reference else 2.0)
    # Far beyond the bounds from both: refused either way.
    assert not model.plausible_since_trusted(2 * STEP_NS, make_transform(None, [0.9, 0, 0]))


def test_prediction_is_per_second():
    model = MotionModel(CONFIG)
    model.velocity = np.array([0.0, 0.0, 0.5, 1.0, 0.0, 0.0])
    distance_m, angle_rad = transform_magnitude(model.predicted_delta(0.05))
    assert distance_m == pytest.approx(0.05) and angle_rad == pytest.approx(0.025)
    np.testing.assert_array_equal(model.predicted_delta(-0.1), np.eye(4))


def test_scale_delta_doubles_a_constant_twist():
    T = make_transform(Rotation.from_euler('z', 0.1).as_matrix(), [0.2, 0.0, 0.0])
    T2 = scale_delta(T, 2.0)
    assert transform_magnitude(T2)[1] == pytest.approx(0.2)
    np.testing.assert_allclose(T2[:3, 3], [0.4, 0.0, 0.0])
    np.testing.assert_allclose(scale_delta(T, 0.0), np.eye(4), atol=1e-15)


def test_deskew_assumes_the_recent_twist_weighted_by_its_span_and_planar():
    """The mean twist of the last two trusted scans, each weighted by the share of a period
    it spans; roll, pitch and climb left out (vibration on rough ground)."""
    model = MotionModel(CONFIG)
    assert motion_module.DESKEW_VELOCITY_WINDOW == 2
    np.testing.assert_array_equal(model.deskew_motion(0.1), np.eye(4))  # nothing known yet
    model.trust(0, np.eye(4), 'first')
    first = make_transform(Rotation.from_euler('xz', [0.02, 0.1]).as_matrix(), [0.1, 0.0, 0.01])
    model.trust(STEP_NS, first, 'ok')
    second = first @ make_transform(Rotation.from_euler('z', 0.3).as_matrix(), [0.15, 0.0, 0.0])
    model.trust(2 * STEP_NS, second, 'ok')
    motion = model.deskew_motion(0.1)
    distance_m, angle_rad = transform_magnitude(motion)
    assert distance_m == pytest.approx(0.125, abs=0.01)
    assert angle_rad == pytest.approx(0.2, abs=0.01)
    assert motion[2, 3] == 0.0 and abs(motion[2, 0]) < 1e-12  # planar
