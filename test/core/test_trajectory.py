"""Trajectory interpolation: linear in position, slerp in rotation, bounded extrapolation."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import GroundTruthError


def test_pose_at_interpolates_and_refuses_far_stamps():
    stamps = np.array([0, 1_000_000_000], dtype=np.int64)
    poses = np.repeat(np.eye(4)[None], 2, axis=0)
    poses[1, :3, 3] = [2.0, 0.0, 0.0]
    c, s = np.cos(0.5), np.sin(0.5)
    poses[1, :3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    traj = Trajectory(stamps, poses)
    T = traj.pose_at(500_000_000)
    np.testing.assert_allclose(T[:3, 3], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(np.arctan2(T[1, 0], T[0, 0]), 0.25)
    np.testing.assert_allclose(traj.pose_at(1_050_000_000), poses[1])  # within 0.1 s: the end
    with pytest.raises(GroundTruthError, match='outside'):
        traj.pose_at(3_000_000_000)
    with pytest.raises(GroundTruthError, match='outside'):
        traj.pose_at(1_050_000_000, max_extrapolation_s=0.01)


def test_the_recorder_keeps_every_pose_in_order_and_forgets_on_clear():
    from gft_odom.core.trajectory import TrajectoryRecorder
    recorder = TrajectoryRecorder()
    poses = np.repeat(np.eye(4)[None], 200, axis=0)
    poses[:, 0, 3] = np.arange(200) * 0.1
    for k in range(200):  # past the first two doublings
        recorder.append(k * 100_000_000, poses[k])
    traj = recorder.trajectory()
    assert len(recorder) == len(traj) == 200
    np.testing.assert_array_equal(traj.stamps_ns, np.arange(200) * 100_000_000)
    np.testing.assert_array_equal(traj.poses, poses)
    traj.poses[0, 0, 3] = 99.0  # a copy: the record is not changed through it
    assert recorder.trajectory().poses[0, 0, 3] == 0.0
    recorder.clear()
    assert len(recorder) == 0 and len(recorder.trajectory()) == 0
