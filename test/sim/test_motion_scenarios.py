"""Scenario trajectories: speed, shape, terrain-following attitude, no driving through trees."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gft_odom.errors import SimulationError
from gft_odom.sim.motion import BASE_LINK_HEIGHT_M, make_motion, required_row_length_m
from gft_odom.sim.orchard import POST, TRUNK, generate_orchard


def _setup(scenario, duration_s, seed=4):
    orchard = generate_orchard(seed, n_rows=8,
                               row_length_m=required_row_length_m(scenario, duration_s),
                               margin_m=10.0)
    return orchard, make_motion(orchard, scenario, duration_s, 1.0, seed)


@pytest.fixture(scope='module', params=['row', 'uturn', 'loop'])
def run(request):
    duration = {'row': 20.0, 'uturn': 60.0, 'loop': 110.0}[request.param]
    orchard, motion = _setup(request.param, duration)
    t = np.arange(0.0, duration, 0.1)
    return request.param, orchard, motion, t, motion.poses(t)


def test_speed_is_about_one_metre_per_second(run):
    _, _, _, t, poses = run
    speed = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1) / np.diff(t)
    assert 0.85 < np.median(speed) < 1.1
    assert speed.min() > 0.5 and speed.max() < 1.3


def test_attitude_follows_the_terrain(run):
    _, orchard, _, _, poses = run
    rpy = Rotation.from_matrix(poses[:, :3, :3]).as_euler('xyz')
    assert np.abs(rpy[:, :2]).max() < np.radians(8.0)
    assert np.abs(rpy[:, :2]).max() > np.radians(0.05)  # not flat: roll/pitch do happen
    ground = orchard.ground.height(poses[:, 0, 3], poses[:, 1, 3])
    np.testing.assert_allclose(poses[:, 2, 3] - ground, BASE_LINK_HEIGHT_M, atol=0.05)


def test_path_keeps_clear_of_trunks_posts_and_boxes(run):
    _, orchard, _, _, poses = run
    cyl = orchard.cylinders
    xy = poses[:, :2, 3]
    trunks = cyl.base_m[cyl.surface == TRUNK, :2]
    assert np.linalg.norm(xy[:, None] - trunks[None], axis=2).min() > 1.5
    posts = cyl.base_m[cyl.surface == POST, :2]
    assert np.linalg.norm(xy[:, None] - posts[None], axis=2).min() > 1.0
    box = orchard.boxes
    for centre, half, yaw in zip(box.centre_m, box.half_extent_m, box.yaw_rad):
        c, s = np.cos(yaw), np.sin(yaw)
        rel = xy - centre[:2]
        local = np.abs(np.column_stack([c * rel[:, 0] + s * rel[:, 1],
                                        -s * rel[:, 0] + c * rel[:, 1]])) - half[:2]
        outside = np.linalg.norm(np.maximum(local, 0.0), axis=1)
        assert outside.min() > 1.5


def test_scenario_shape(run):
    scenario, orchard, motion, t, poses = run
    yaw = np.unwrap(Rotation.from_matrix(poses[:, :3, :3]).as_euler('xyz')[:, 2])
    turned = abs(yaw[-1] - yaw[0])
    if scenario == 'row':
        assert turned < np.radians(10.0)
        # Straight: lateral deviation from the chord within the wobble.
        p = poses[:, :2, 3]
        chord = (p[-1] - p[0]) / np.linalg.norm(p[-1] - p[0])
        lateral = chord[0] * (p[:, 1] - p[0, 1]) - chord[1] * (p[:, 0] - p[0, 0])
        assert np.abs(lateral).max() < 0.2
    elif scenario == 'uturn':
        assert abs(turned - np.pi) < np.radians(10.0)
    else:
        assert abs(turned - 2.0 * np.pi) < np.radians(25.0) or motion.duration_s > t[-1]
        end_gap = np.linalg.norm(poses[-1, :2, 3] - poses[0, :2, 3])
        start_to_far = np.linalg.norm(poses[:, :2, 3] - poses[0, :2, 3], axis=1).max()
        assert start_to_far > 20.0
        # Back near the start after one lap.
        lap = np.argmin(np.abs(t - motion.duration_s))
        if t[-1] >= motion.duration_s:
            assert np.linalg.norm(poses[lap, :2, 3] - poses[0, :2, 3]) < 1.0
        else:
            assert end_gap < start_to_far


def test_first_pose_is_not_the_identity(run):
    _, _, _, _, poses = run
    assert np.linalg.norm(poses[0, :3, 3]) > 1.0
    assert not np.allclose(poses[0, :3, :3], np.eye(3), atol=1e-3)


def test_pose_is_smooth_in_time(run):
    _, _, motion, _, _ = run
    t = np.linspace(3.0, 4.0, 1001)
    p = motion.poses(t)[:, :3, 3]
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert step.max() < 0.0025  # <= 2.5 mm per ms at ~1 m/s: no jumps


def test_unknown_scenario_is_refused():
    orchard = generate_orchard(0, n_rows=4, row_length_m=40.0, margin_m=5.0)
    with pytest.raises(SimulationError, match='zigzag'):
        make_motion(orchard, 'zigzag', 10.0)
    with pytest.raises(SimulationError, match='zigzag'):
        required_row_length_m('zigzag', 10.0)
