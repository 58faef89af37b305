"""Publishes a codec-built velodyne cloud over DDS until killed (run as its own process)."""

import sys
import time
from pathlib import Path

import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2

from gft_odom.io.pointcloud2 import VELODYNE_XYZIRT, encode_cloud
from gft_odom.ros.conversions import blob_to_msg

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script
from helpers import velodyne_columns  # noqa: E402


def main() -> None:
    seed, n = int(sys.argv[1]), int(sys.argv[2])
    msg = blob_to_msg(encode_cloud(velodyne_columns(n, seed), VELODYNE_XYZIRT),
                      1_700_000_000_123_456_789, 'velodyne')
    rclpy.init()
    node = rclpy.create_node('cloud_publisher')
    pub = node.create_publisher(PointCloud2, 'points', qos_profile_sensor_data)
    try:
        while rclpy.ok():
            pub.publish(msg)
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
