"""Scenes shared by the registration's tests (built once per module)."""

from __future__ import annotations

import numpy as np
import pytest
from registration_scenes import (
    SCAN_PERIOD_S,
    SENSOR_HEIGHT_M,
    headland_turn,
    make_orchard,
    scan_scene,
    static_pose,
    weaving_drive,
)
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import make_transform


@pytest.fixture(scope='module')
def orchard() -> dict:
    return make_orchard()


@pytest.fixture(scope='module')
def static_pair(orchard) -> tuple[dict, dict, np.ndarray]:
    """Two undistorted scans and the true T_a_b between them."""
    T_a = make_transform(translation=[0.0, 0.0, SENSOR_HEIGHT_M])
    T_ab = make_transform(Rotation.from_euler('z', 3.0, degrees=True).as_matrix(),
                          [0.25, -0.08, 0.02])
    a = scan_scene(orchard, static_pose(T_a), 0.0, seed=1)
    b = scan_scene(orchard, static_pose(T_a @ T_ab), 0.1, seed=2)
    return a, b, T_ab


@pytest.fixture(scope='module')
def drive(orchard) -> list[dict]:
    """2 s along the row, S-curve, with motion distortion: 21 scans."""
    pose_at = weaving_drive()
    return [scan_scene(orchard, pose_at, k * SCAN_PERIOD_S, seed=k) for k in range(21)]


@pytest.fixture(scope='module')
def open_ground_turn(orchard) -> list[dict]:
    """1.8 m/s, 14 m past the row ends, then 2 rad/s within 0.1 s: 20 scans."""
    return [scan_scene(orchard, headland_turn(34.0), k * SCAN_PERIOD_S, seed=k)
            for k in range(20)]
