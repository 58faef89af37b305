"""The trust policy on its own: which check refuses a match's pose, and the fallback run."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import make_transform
from gft_odom.core.registration import RegistrationConfig
from gft_odom.core.registration.motion import MotionModel
from gft_odom.core.registration.trust import (
    MAX_CONSECUTIVE_FALLBACKS,
    MIN_FITNESS,
    MIN_RELATIVE_FITNESS,
    RECENT_FITNESS_MIN,
    TrustPolicy,
)

CONFIG = RegistrationConfig()  # 2 m/s x 1.5; the jump bounds 0.5 m / 0.25 rad
STEP_NS = 100_000_000


def _policy_trusting_the_origin() -> TrustPolicy:
    motion = MotionModel(CONFIG)
    motion.trust(0, np.eye(4), 'first')
    motion.advance(0, np.eye(4))
    return TrustPolicy(motion)


def _yawed(rad: float) -> np.ndarray:
    return make_transform(Rotation.from_rotvec([0.0, 0.0, rad]).as_matrix())


@pytest.mark.parametrize('T_est, fitness, T_pred, refusal', [
    (make_transform(None, [0.1, 0.0, 0.0]), 0.9, np.eye(4), None),
    (np.full((4, 4), np.nan), 0.9, np.eye(4), 'fallback_diverged'),
    (make_transform(None, [0.1, 0.0, 0.0]), 0.29, np.eye(4), 'fallback_low_fitness'),
    # 0.31 m in 0.1 s: beyond 2 m/s x (1 + margin 0.5)
    (make_transform(None, [0.31, 0.0, 0.0]), 0.9, np.eye(4), 'fallback_implausible'),
    # plausible (0.3 rad in 0.1 s), but 0.3 rad from the prediction: a jump (0.25 rad)
    (_yawed(0.3), 0.9, np.eye(4), 'fallback_diverged'),
    (_yawed(0.3), 0.9, _yawed(0.2), None),
])
def test_refusal_names_the_check_a_pose_fails(T_est, fitness, T_pred, refusal):
    assert _policy_trusting_the_origin().refusal(T_est, fitness, T_pred, STEP_NS) == refusal


def test_a_fitness_far_below_the_recent_matches_is_refused_once_there_are_enough():
    policy = _policy_trusting_the_origin()
    T_est = make_transform(None, [0.1, 0.0, 0.0])
    bound = MIN_RELATIVE_FITNESS * 0.95
    low, fine = max(0.9 * bound, MIN_FITNESS), 1.05 * bound
    assert MIN_FITNESS <= low < bound
    for _ in range(RECENT_FITNESS_MIN - 1):
        policy.trusted(0.95)
        assert policy.refusal(T_est, low, np.eye(4), STEP_NS) is None  # too few to judge
    policy.trusted(0.95)
    assert policy.refusal(T_est, low, np.eye(4), STEP_NS) == 'fallback_low_fitness'
    assert policy.refusal(T_est, fine, np.eye(4), STEP_NS) is None


def test_the_fallback_run_ends_tracking_and_a_trusted_pose_ends_the_run():
    policy = _policy_trusting_the_origin()
    runs = [policy.fell_back() for _ in range(MAX_CONSECUTIVE_FALLBACKS)]
    assert runs == [False] * (MAX_CONSECUTIVE_FALLBACKS - 1) + [True]
    policy.trusted(None)
    assert policy.consecutive_fallbacks == 0
    assert policy.n_fallbacks == MAX_CONSECUTIVE_FALLBACKS
    assert policy.fell_back() is False


def test_paper_mode_judges_fitness_by_the_absolute_bound_alone():
    motion = MotionModel(CONFIG)
    motion.trust(0, np.eye(4), 'first')
    policy = TrustPolicy(motion, relative_fitness=False)
    for _ in range(RECENT_FITNESS_MIN):
        policy.trusted(0.95)
    T_est = make_transform(None, [0.1, 0.0, 0.0])
    assert policy.refusal(T_est, 1.01 * MIN_FITNESS, np.eye(4), STEP_NS) is None
