"""The robust kernel's scale from the motion model's prediction errors (adaptive_kernel_ratio;
the registration's use of it: test_registration.py)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import make_transform
from gft_odom.core.registration import RegistrationConfig
from gft_odom.core.threshold import AdaptiveThreshold, prediction_error_m
from gft_odom.errors import ConfigError


def test_the_prediction_error_is_the_translation_plus_the_rotations_chord_at_the_range():
    T_pred = make_transform(Rotation.from_euler('z', 0.7).as_matrix(), [3.0, -1.0, 0.2])
    shifted = T_pred @ make_transform(translation=[0.3, 0.0, -0.4])
    turned = T_pred @ make_transform(Rotation.from_euler('z', 0.01).as_matrix())
    assert prediction_error_m(T_pred, T_pred, 40.0) == pytest.approx(0.0, abs=1e-6)
    assert prediction_error_m(T_pred, shifted, 40.0) == pytest.approx(0.5)
    assert prediction_error_m(T_pred, turned, 40.0) == pytest.approx(80.0 * math.sin(0.005))
    assert prediction_error_m(T_pred, turned, 20.0) == pytest.approx(40.0 * math.sin(0.005))


def test_the_scale_is_the_rms_of_the_errors_counted_and_small_ones_are_not_counted():
    threshold = AdaptiveThreshold(initial_m=2.0, min_motion_m=0.1, range_m=40.0)
    T = np.eye(4)
    assert threshold.sigma_m == 2.0
    threshold.observe(T, make_transform(translation=[0.05, 0.0, 0.0]))  # under min_motion_m
    assert threshold.sigma_m == 2.0 and threshold.n_samples == 0
    threshold.observe(T, make_transform(translation=[0.3, 0.0, 0.0]))
    threshold.observe(T, make_transform(translation=[0.0, 0.4, 0.0]))
    assert threshold.n_samples == 2
    assert threshold.sigma_m == pytest.approx(math.sqrt((0.09 + 0.16) / 2))
    threshold.reset()
    assert threshold.sigma_m == 2.0 and threshold.n_samples == 0


@pytest.mark.parametrize('field, value', [('adaptive_kernel_ratio', -0.1),
                                          ('adaptive_min_motion_m', float('nan')),
                                          ('adaptive_window_scans', -1)])
def test_invalid_values_are_refused(field, value):
    with pytest.raises(ConfigError, match=field):
        dataclasses.replace(RegistrationConfig(), **{field: value}).validate()


@pytest.mark.parametrize('other', [{'mode': 'paper'}, {'robust_kernel': 'none'},
                                   {'adaptive_min_motion_m': 0.0}])
def test_a_kernel_without_a_scale_or_a_scale_without_a_floor_is_refused(other):
    with pytest.raises(ConfigError, match='adaptive_kernel_ratio'):
        dataclasses.replace(RegistrationConfig(), adaptive_kernel_ratio=0.3,
                            **other).validate()


def test_a_window_forgets_the_older_errors():
    threshold = AdaptiveThreshold(initial_m=2.0, min_motion_m=0.1, range_m=40.0, window=2)
    T = np.eye(4)
    for x_m in (3.0, 0.3, 0.4):
        threshold.observe(T, make_transform(translation=[x_m, 0.0, 0.0]))
    assert threshold.n_samples == 3
    assert threshold.sigma_m == pytest.approx(math.sqrt((0.09 + 0.16) / 2))
