"""A PointCloud2 built by the codec crosses DDS between two processes and decodes the same."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import load_script

pytestmark = [pytest.mark.slow, pytest.mark.ros]


def test_cloud_crosses_dds_between_processes(ros_env, ros_node):
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    from gft_odom.io.pointcloud2 import decode_scan

    publisher_path = Path(__file__).with_name('cloud_publisher.py')
    publisher_module = load_script(publisher_path)
    seed, n = 7, 30_000
    expected = publisher_module.velodyne_columns(n, seed)
    proc = subprocess.Popen([sys.executable, str(publisher_path), str(seed), str(n)],
                            env=ros_env)
    node, spin_until = ros_node
    received: list[PointCloud2] = []
    node.create_subscription(PointCloud2, 'points', received.append, qos_profile_sensor_data)
    try:
        spin_until(lambda: received or proc.poll() is not None, 30.0)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert received, 'no PointCloud2 arrived over DDS within 30 s'
    scan = decode_scan(received[0])
    assert scan.stamp_ns == 1_700_000_000_123_456_789
    assert scan.frame_id == 'velodyne'
    np.testing.assert_array_equal(scan.points_xyz[:, 0], expected['x'].astype(np.float64))
    np.testing.assert_array_equal(scan.points_xyz[:, 2], expected['z'].astype(np.float64))
    np.testing.assert_array_equal(scan.intensity, expected['intensity'])
    np.testing.assert_array_equal(scan.ring, expected['ring'])
    np.testing.assert_array_equal(scan.time_offset_s, expected['time'])
