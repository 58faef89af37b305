"""Residual-and-weight models: rows, weights, groups, and the smoothness sources."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.core.residuals import (
    Correspondences,
    PlaneResidual,
    SmoothnessResidual,
    Term,
    beam_information,
    linearise,
    make_residual_model,
    normal_equations,
    smoothness_from_covariances,
    smoothness_from_nu,
)
from gft_odom.errors import ConfigError


def pairs(m: int = 20, seed: int = 0, smoothness=None) -> Correspondences:
    rng = np.random.default_rng(seed)
    lever = rng.normal(0.0, 5.0, (m, 3))
    sensor = np.array([10.0, -3.0, 0.5])
    normal = rng.normal(size=(m, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    target = sensor + lever + rng.normal(0.0, 0.05, (m, 3))
    return Correspondences(sensor + lever, lever, target, normal, smoothness)


def numeric_jacobian(c: Correspondences, rows) -> np.ndarray:
    """d r / d (translation, rotation about the sensor) by central differences."""
    from scipy.spatial.transform import Rotation
    sensor = c.source_world - c.lever
    cols = []
    for k in range(6):
        out = []
        for sign in (1.0, -1.0):
            dx = np.zeros(6)
            dx[k] = sign * 1e-6
            R = Rotation.from_rotvec(dx[3:]).as_matrix()
            lever = c.lever @ R.T
            moved = Correspondences(sensor + lever + dx[:3], lever, c.target, c.normal,
                                    c.smoothness)
            out.append(rows(moved)[1])
        cols.append((out[0] - out[1]) / 2e-6)
    return np.column_stack(cols)


def test_plane_rows_have_the_analytic_jacobian():
    c = pairs()
    rows = lambda c: linearise(PlaneResidual(), c)  # noqa: E731
    J, r, w, group = rows(c)
    np.testing.assert_allclose(J, numeric_jacobian(c, rows), atol=1e-5)
    np.testing.assert_allclose(r, np.einsum('ij,ij->i', c.normal, c.source_world - c.target))
    assert np.all(w == 1.0) and np.array_equal(group, np.arange(20))


def test_rough_rows_have_the_analytic_jacobian_and_ignore_the_beam():
    c = pairs(smoothness=np.zeros(20))
    model = SmoothnessResidual('frequency', 'beam_perpendicular')
    rows = lambda c: linearise(model, c)  # noqa: E731
    J, r, w, group = rows(c)
    # Gauss-Newton holds the projection fixed: exact where the residual vanishes.
    at_zero = Correspondences(c.source_world, c.lever, c.source_world.copy(), c.normal,
                              c.smoothness)
    np.testing.assert_allclose(J, numeric_jacobian(at_zero, rows), atol=1e-5)
    # A move along each pair's own beam changes none of its rough residuals.
    rough = J[20:].reshape(20, 3, 6)
    beam = c.lever / np.linalg.norm(c.lever, axis=1, keepdims=True)
    along = np.einsum('nij,nj->ni', rough[:, :, :3], beam)
    np.testing.assert_allclose(along, 0.0, atol=1e-12)
    # Plane rows weigh s = 0, rough rows 1 - s = 1; groups: i for planes, m + i for rough.
    np.testing.assert_allclose(w[:20], 0.0)
    np.testing.assert_allclose(w[20:], 1.0)
    np.testing.assert_array_equal(group[20:], 20 + np.repeat(np.arange(20), 3))


def test_full_point_rows_constrain_every_direction():
    c = pairs(smoothness=np.zeros(20))
    J, _, _, _ = linearise(SmoothnessResidual('planarity', 'point'), c)
    np.testing.assert_allclose(J[20:23, :3], np.eye(3))


def test_without_smoothness_the_model_is_the_plane_model():
    c = pairs()
    plain = linearise(PlaneResidual(), c)
    same = linearise(SmoothnessResidual('frequency'), c)
    for a, b in zip(plain, same):
        np.testing.assert_array_equal(a, b)


def test_smooth_pairs_get_no_rough_rows_and_weights_follow_smoothness():
    s = np.linspace(0.0, 1.0, 20)
    J, r, w, group = linearise(SmoothnessResidual('frequency', rough_weight=0.5),
                               pairs(smoothness=s))
    n_rough = int(np.sum(s < 1.0))
    assert J.shape[0] == 20 + 3 * n_rough
    np.testing.assert_allclose(w[:20], s)
    np.testing.assert_allclose(w[20:], np.repeat(0.5 * (1.0 - s[s < 1.0]), 3))


def test_smoothness_from_nu_is_clipped_and_nan_is_rough():
    s = smoothness_from_nu(np.array([np.nan, 0.0, 0.2, 0.4, 0.6]), 0.4)
    np.testing.assert_allclose(s, [0.0, 0.0, 0.5, 1.0, 1.0])


def test_smoothness_from_covariances_tells_a_plane_from_a_blob():
    plane = np.diag([1.0, 1.0, 1e-6])
    blob = np.eye(3)
    s = smoothness_from_covariances(np.stack([plane, blob]), 0.1)
    assert s[0] > 0.99 and s[1] == 0.0


def test_unknown_models_are_refused():
    with pytest.raises(ConfigError, match='residual model'):
        make_residual_model('volume')
    with pytest.raises(ConfigError, match='rough residual'):
        make_residual_model('frequency', 'along_beam')


@pytest.mark.parametrize('kind', ['plane', 'beam_perpendicular', 'point', 'beam_covariance'])
def test_closed_form_normal_equations_equal_the_explicit_rows(kind):
    c = pairs(smoothness=np.zeros(20))
    c.target_beam = np.random.default_rng(5).normal(size=(20, 3))
    term = Term(kind, np.arange(3, 17), np.linspace(0.2, 1.0, 14), depth_ratio=4.0)
    kernel = lambda e: 1.0 / (1.0 + (e / 0.1) ** 2)  # noqa: E731
    H, g = normal_equations(c, term, kernel)

    class One:
        def terms(self, _):
            return [term]
    J, r, w, group = linearise(One(), c)
    norms = np.sqrt(np.bincount(group, weights=r * r))
    w = w * kernel(norms)[group]
    np.testing.assert_allclose(H, (J * w[:, None]).T @ J, atol=1e-9)
    np.testing.assert_allclose(g, (J * w[:, None]).T @ r, atol=1e-9)
    with pytest.raises(ConfigError, match='residual kind'):
        normal_equations(c, Term('line', term.index, term.weight), kernel)


def test_beam_information_discounts_depth_along_both_beams():
    x, y, z = np.eye(3)
    same = beam_information(x[None], x[None], 5.0)[0]
    np.testing.assert_allclose(same @ x, x / 25.0)  # along the beam: 1 / k^2
    np.testing.assert_allclose(same @ y, y)  # across it: 1
    # The map point seen along y, the scan point along x: both depths discounted, z kept.
    crossed = beam_information(x[None], y[None], 5.0)[0]
    assert crossed @ x @ x < 0.1 and crossed @ y @ y < 0.1
    np.testing.assert_allclose(crossed @ z, z)
    # No map beam: the scan's stands in.
    np.testing.assert_allclose(beam_information(x[None], None, 5.0)[0], same)
