"""Gauss-Newton ICP: known transforms, agreement with open3d, weak directions, kernels."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from helpers import box_scene, target_of
from scipy.spatial.transform import Rotation

from gft_odom.core.gauss_newton import (
    GaussNewtonICP,
    MapTarget,
    _CandidateSearch,
    apply_update,
    kernel_weights,
)
from gft_odom.core.geometry import invert_transform, make_transform
from gft_odom.core.residuals import PlaneResidual, SmoothnessResidual


@pytest.fixture(scope='module')
def scene():
    return box_scene()


T_TRUE = make_transform(Rotation.from_euler('z', 4.0, degrees=True).as_matrix(),
                        [0.3, -0.15, 0.02])


def test_update_moves_about_the_sensor_origin():
    T = make_transform(np.eye(3), [5.0, 0.0, 0.0])
    moved = apply_update(T, np.r_[0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(moved[:3, 3], [5.0, 0.0, 0.0])  # rotation about itself
    np.testing.assert_allclose(moved[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize('model', [PlaneResidual(),
                                   SmoothnessResidual('frequency', 'beam_perpendicular'),
                                   SmoothnessResidual('frequency', 'beam_covariance', 1.0, 5.0)])
def test_recovers_a_known_transform(scene, model):
    source = (invert_transform(T_TRUE)[:3, :3] @ scene.T).T + invert_transform(T_TRUE)[:3, 3]
    source += np.random.default_rng(1).normal(0.0, 0.01, source.shape)
    smooth = np.random.default_rng(2).uniform(0.0, 1.0, source.shape[0])
    solver = GaussNewtonICP(model, 'tukey', 0.3, max_iterations=50)
    result = solver.register(source, target_of(scene), np.eye(4), 1.0, smooth)
    error = invert_transform(T_TRUE) @ result.transformation
    assert np.linalg.norm(error[:3, 3]) < 0.01
    assert Rotation.from_matrix(error[:3, :3]).magnitude() < np.deg2rad(0.05)
    assert result.fitness > 0.95 and result.inlier_rmse < 0.1
    assert result.n_iterations < 50
    assert np.all(np.linalg.eigvalsh(result.information) > 0.0)


def test_agrees_with_open3d_point_to_plane(scene):
    source = (invert_transform(T_TRUE)[:3, :3] @ scene.T).T + invert_transform(T_TRUE)[:3, 3]
    source = source[::3] + np.random.default_rng(3).normal(0.0, 0.02, source[::3].shape)
    target = target_of(scene)
    ours = GaussNewtonICP(PlaneResidual(), 'tukey', 0.3, 50, 1e-6).register(
        source, target, np.eye(4), 1.0)
    reg = o3d.pipelines.registration
    cloud_t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target.points))
    cloud_t.normals = o3d.utility.Vector3dVector(target.normals)
    theirs = reg.registration_icp(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)), cloud_t, 1.0, np.eye(4),
        reg.TransformationEstimationPointToPlane(reg.TukeyLoss(0.3)),
        reg.ICPConvergenceCriteria(1e-9, 1e-9, 50))
    diff = invert_transform(np.asarray(theirs.transformation)) @ ours.transformation
    assert np.linalg.norm(diff[:3, 3]) < 0.005
    assert abs(ours.fitness - theirs.fitness) < 0.01


def test_a_corridor_leaves_the_along_axis_weak():
    corridor = box_scene(corridor=True)
    solver = GaussNewtonICP(PlaneResidual(), 'tukey', 0.3)
    result = solver.register(corridor[::2], target_of(corridor), np.eye(4), 1.0)
    translation = result.information[:3, :3]
    values, vectors = np.linalg.eigh(translation)
    weakest = vectors[:, 0]
    assert abs(weakest[0]) > 0.99  # along the walls (x)
    assert values[0] < 0.02 * values[1]


def test_kernels_down_weight_large_residuals():
    e = np.array([0.0, 0.1, 0.3, 1.0])
    tukey = kernel_weights('tukey', e, 0.3)
    assert tukey[0] == 1.0 and tukey[2] == 0.0 and tukey[3] == 0.0 and 0 < tukey[1] < 1
    for kind in ('huber', 'cauchy'):
        w = kernel_weights(kind, e, 0.3)
        assert np.all(np.diff(w) <= 0.0) and w[0] == 1.0
    np.testing.assert_array_equal(kernel_weights('none', e, 0.3), 1.0)


def test_too_few_pairs_returns_no_information(scene):
    far = scene[:50] + 100.0
    result = GaussNewtonICP(PlaneResidual()).register(far, target_of(scene), np.eye(4), 1.0)
    assert result.fitness == 0.0 and result.information is None


def test_affinity_pairs_like_with_like():
    # A rough map point 0.10 m away and a smooth one 0.08 m away: by distance the smooth one
    # wins; with the affinity a rough scan point picks the rough one, a smooth one its own.
    points = np.array([[0.10, 0.0, 0.0], [-0.08, 0.0, 0.0]])
    target = MapTarget(points, np.tile([0.0, 0.0, 1.0], (2, 1)),
                       point_smoothness=np.array([0.0, 1.0]))
    scan = np.zeros((2, 3))
    plain = _CandidateSearch(target, 1.0)
    assert list(plain.nearest(scan)[1]) == [1, 1]
    alike = _CandidateSearch(target, 1.0, np.array([0.0, 1.0]), affinity_m=0.5)
    assert list(alike.nearest(scan)[1]) == [0, 1]
    # An unknown smoothness (NaN, either side) falls back to the distance.
    unknown = _CandidateSearch(target, 1.0, np.array([np.nan, 0.0]), affinity_m=0.5)
    assert list(unknown.nearest(scan)[1]) == [1, 0]


def test_affinity_never_pairs_beyond_the_distance():
    points = np.array([[0.5, 0.0, 0.0], [1.5, 0.0, 0.0]])
    target = MapTarget(points, np.tile([0.0, 0.0, 1.0], (2, 1)),
                       point_smoothness=np.array([1.0, 0.0]))
    valid, index = _CandidateSearch(target, 1.0, np.array([0.0]), affinity_m=5.0).nearest(
        np.zeros((1, 3)))
    assert list(valid) == [0] and list(index) == [0]  # the rough one is 1.5 m away: not it


def test_affinity_prefers_a_pair_within_the_distance():
    # The alike map point is 1.02 m away (a candidate, beyond the distance); the unlike one at
    # 0.6 m is the pair.
    points = np.array([[1.02, 0.0, 0.0], [0.6, 0.0, 0.0]])
    target = MapTarget(points, np.tile([0.0, 0.0, 1.0], (2, 1)),
                       point_smoothness=np.array([0.0, 1.0]))
    valid, index = _CandidateSearch(target, 1.0, np.array([0.0]), affinity_m=5.0).nearest(
        np.zeros((1, 3)))
    assert list(valid) == [0] and list(index) == [1]


def test_a_motion_prior_holds_the_prediction_where_few_pairs_constrain():
    # A corridor along x: only a small wall at its end (100 points) says where along x the
    # scan is, and it says +0.15 m. Without a prior the estimate follows it; with a prior worth
    # 300 pairs at the prediction (identity) it moves ~100 / 400 of that. Across the
    # corridor (~3000 wall pairs) the data still mostly rules.
    rng = np.random.default_rng(4)
    corridor = box_scene(corridor=True)
    end_wall = np.c_[np.full(100, 10.0), rng.uniform(-3.5, 3.5, 100), rng.uniform(0.2, 2.5, 100)]
    scene = np.concatenate([corridor, end_wall])
    source = scene.copy()
    source[-100:, 0] -= 0.15
    source[:, 1] -= 0.05  # and 5 cm across the corridor
    solver = GaussNewtonICP(PlaneResidual(), 'tukey', 0.5, max_iterations=50)
    free = solver.register(source, target_of(scene), np.eye(4), 1.0)
    held = solver.register(source, target_of(scene), np.eye(4), 1.0, prior=(np.eye(4), 300.0))
    assert free.transformation[0, 3] > 0.12
    assert 0.02 < held.transformation[0, 3] < 0.06
    np.testing.assert_allclose([free.transformation[1, 3], held.transformation[1, 3]],
                               0.05, atol=0.01)
