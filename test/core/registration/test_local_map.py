"""The local map: the keyframe window, the anchors that outlive it, the view rule."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.core.registration import local_map as local_map_module
from gft_odom.core.registration.local_map import KEYFRAME_ROTATION_RAD, LocalMap
from gft_odom.core.registration.voxels import voxel_draw

SMOOTH, ROUGH = 0.9, 0.1


def pose(x: float = 0.0, y: float = 0.0, yaw_rad: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def served(local_map: LocalMap) -> set[tuple[float, ...]]:
    return {tuple(p) for p in local_map.points_xyz.round(1)}


@pytest.fixture
def no_any_side(monkeypatch):
    """The view rule alone: no voxel drawn to be served from any side."""
    monkeypatch.setattr(local_map_module, 'ANY_SIDE_SHARE', 0.0)


def test_a_keyframe_is_due_after_the_distance_or_the_turn():
    local_map = LocalMap(0.1, 100.0, 10_000, 5, 1.0)
    assert local_map.needs_keyframe(pose())  # an empty map
    local_map.add_keyframe(np.array([[1.0, 2.0, 0.0]]), pose())
    assert not local_map.needs_keyframe(pose(0.9))
    assert local_map.needs_keyframe(pose(1.0))
    assert not local_map.needs_keyframe(pose(yaw_rad=0.9 * KEYFRAME_ROTATION_RAD))
    assert local_map.needs_keyframe(pose(yaw_rad=1.1 * KEYFRAME_ROTATION_RAD))


def test_keyframes_leaving_the_window_stay_as_anchors(no_any_side):
    """A row met again after the window moved on registers against what it showed before:
    a keyframe's points outlive it, trunk and canopy, with or without frequencies."""
    for smoothness in (np.array([SMOOTH, ROUGH]), None):
        local_map = LocalMap(0.1, 100.0, 10_000, 1, 1.0)
        local_map.add_keyframe(np.array([[0.0, 2.0, 0.0], [0.5, 2.0, 2.0]]), pose(), smoothness)
        local_map.add_keyframe(np.array([[5.0, -3.0, 0.0]]), pose(1.0),
                               None if smoothness is None else np.array([SMOOTH]))
        assert local_map.n_anchors == 2
        assert served(local_map) == {(0.0, 2.0, 0.0), (0.5, 2.0, 2.0), (5.0, -3.0, 0.0)}
    local_map.clear()
    assert local_map.n_anchors == 0 and len(local_map) == 0


def test_points_are_served_only_from_the_side_they_were_seen_from(no_any_side):
    """The row at y = 2 seen from the lane at y = 0; from the far lane (y = 4) its other face
    is another surface (porous canopy another cloud, a trunk another face): not served, in the
    window or as anchors."""
    trunk_and_canopy = np.array([[0.0, 2.0, 0.0], [0.5, 2.0, 2.0]])
    for window in (10, 1):  # both keyframes in the window, or the first an anchor
        local_map = LocalMap(0.1, 100.0, 10_000, window, 1.0)
        local_map.add_keyframe(trunk_and_canopy, pose(), np.array([SMOOTH, ROUGH]))
        local_map.add_keyframe(np.array([[5.0, 6.0, 0.0]]), pose(0.0, 4.0), np.array([SMOOTH]))
        assert served(local_map) == {(5.0, 6.0, 0.0)}, window
        # From the same lane a little further on (27 deg off its beam), both are served.
        local_map.add_keyframe(np.array([[5.0, -3.0, 0.0]]), pose(1.0, 0.0), np.array([SMOOTH]))
        assert {(0.0, 2.0, 0.0), (0.5, 2.0, 2.0)} <= served(local_map)


def test_a_share_of_the_voxels_drawn_by_voxel_is_served_from_any_side():
    rng = np.random.default_rng(3)
    canopy = np.column_stack([rng.uniform(-1.0, 1.0, 4000), rng.uniform(1.5, 2.5, 4000),
                              rng.uniform(0.0, 1.0, 4000)])
    draw = voxel_draw(canopy, 0.1)
    # Fixed by the voxel, spread evenly over [0, 1).
    np.testing.assert_array_equal(draw, voxel_draw(canopy + 1e-4 * (canopy % 0.1 < 0.05), 0.1))
    assert np.all((draw >= 0.0) & (draw < 1.0))
    local_map = LocalMap(0.1, 100.0, 100_000, 1, 1.0)
    local_map.add_keyframe(canopy, pose(), np.full(len(canopy), ROUGH))
    local_map.add_keyframe(np.array([[0.0, 6.0, 0.0]]), pose(0.0, 4.0), np.array([SMOOTH]))
    share = (len(local_map) - 1) / local_map.n_anchors  # seen from the far lane
    assert abs(share - local_map_module.ANY_SIDE_SHARE) < 0.05


def test_a_smooth_point_takes_over_a_rough_anchors_voxel():
    """First seen far off, as rough; then near, as smooth: the voxel's anchor becomes the
    smooth point (a filled voxel otherwise keeps its older anchor)."""
    local_map = LocalMap(1.0, 100.0, 10_000, 1, 1.0)
    T = pose()
    for x, s in ((0.2, ROUGH), (0.6, SMOOTH), (0.4, 0.2)):
        local_map.add_keyframe(np.array([[x, 0.5, 0.5]]), T, np.array([s]))
        T = pose(T[0, 3] + 20.0)
    local_map.add_keyframe(np.array([[99.0, 0.5, 0.5]]), T, np.array([SMOOTH]))
    assert local_map.n_anchors == 1
    assert local_map._anchors.find(np.array([local_map_module.voxel_keys(
        np.array([[0.6, 0.5, 0.5]]), 1.0)[0]]))[1][0] == SMOOTH


def test_an_older_anchor_keeps_its_voxel_and_far_anchors_are_not_served(no_any_side):
    local_map = LocalMap(1.0, 15.0, 10_000, 1, 1.0)
    local_map.add_keyframe(np.array([[0.2, 0.5, 0.5]]), pose(), np.array([SMOOTH]))
    local_map.add_keyframe(np.array([[0.7, 0.5, 0.5]]), pose(0.5), np.array([SMOOTH]))
    # The anchor (0.2) is older than the window's point in the same voxel: it stays.
    assert local_map.points_xyz[:, 0].tolist() == [0.2]
    local_map.add_keyframe(np.array([[30.2, 0.5, 0.5]]), pose(30.0), np.array([SMOOTH]))
    assert local_map.points_xyz[:, 0].tolist() == [30.2]  # anchors beyond 15 m not served
    assert local_map.n_anchors == 1  # the 0.7 point's voxel was already anchored


def test_anchors_are_bounded_by_dropping_the_farthest(monkeypatch):
    monkeypatch.setattr(local_map_module, 'ANCHOR_MAX_POINTS', 2)
    local_map = LocalMap(0.1, 100.0, 10_000, 1, 1.0)
    for x in (0.0, 10.0, 20.0, 30.0):
        local_map.add_keyframe(np.array([[x, -2.0, 0.0]]), pose(x))
    # Keyframes 0, 10 and 20 left the window; the newest is at 30: 0 is the farthest.
    assert local_map.n_anchors == 2


def test_the_map_keeps_the_nearest_points_within_its_cap_and_has_normals():
    rng = np.random.default_rng(4)
    ground = np.column_stack([rng.uniform(-20.0, 20.0, (5000, 2)), np.zeros(5000)])
    local_map = LocalMap(0.3, 100.0, 1000, 5, 1.0)
    local_map.add_keyframe(ground, pose())
    assert len(local_map) == 1000
    radius = np.linalg.norm(local_map.points_xyz[:, :2], axis=1)  # ~10 m holds 1000 voxels
    assert radius.max() < 11.5 and np.median(radius) < 8.0
    target = local_map.target()
    np.testing.assert_allclose(np.abs(target.normals[:, 2]), 1.0, atol=1e-6)  # the ground
    assert local_map.target() is target  # built once per rebuild
    assert local_map.share_near(np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 5.0]]), 0.3) == 0.5
