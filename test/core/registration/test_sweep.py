"""A scan's input as registration takes it: finite rows only, shapes that agree, smoothness."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.core.deferred import Deferred
from gft_odom.core.registration.sweep import (
    checked_input,
    map_smoothness,
    smoothness_from_nu,
)
from gft_odom.errors import RegistrationError


def test_non_finite_rows_are_dropped_with_their_times_and_frequencies():
    points = np.arange(12, dtype=float).reshape(4, 3)
    points[1, 2] = np.nan
    times = np.array([0.0, 0.01, np.inf, 0.03])
    nu = np.array([0.1, 0.2, 0.3, 0.4])
    kept, kept_times, kept_nu = checked_input(points, times, nu)
    np.testing.assert_array_equal(kept, points[[0, 3]])
    np.testing.assert_array_equal(kept_times, [0.0, 0.03])
    np.testing.assert_array_equal(kept_nu, [0.1, 0.4])


def test_deferred_frequencies_are_filtered_when_they_arrive():
    points = np.zeros((3, 3))
    points[2] = np.nan
    _, _, nu = checked_input(points, None, Deferred(lambda: np.array([1.0, 2.0, 3.0])))
    assert isinstance(nu, Deferred)
    np.testing.assert_array_equal(nu.get(), [1.0, 2.0])


@pytest.mark.parametrize('points, times, nu', [
    (np.zeros((4, 2)), None, None),
    (np.zeros((4, 3)), np.zeros(3), None),
    (np.zeros((4, 3)), None, np.zeros(5)),
])
def test_shapes_that_do_not_agree_raise(points, times, nu):
    with pytest.raises(RegistrationError):
        checked_input(points, times, nu)


def test_smoothness_is_the_frequency_scaled_and_clipped():
    nu = np.array([0.0, 0.2, 0.4, 0.8, np.nan])
    np.testing.assert_allclose(smoothness_from_nu(nu), [0.0, 0.5, 1.0, 1.0, np.nan])
    assert smoothness_from_nu(nu, unknown=0.0)[-1] == 0.0
    np.testing.assert_allclose(map_smoothness(nu, np.array([1, 2])), [0.5, 1.0])
