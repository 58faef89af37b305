"""odom -> base_link on `/tf` without tf2_ros: a tf2_msgs/TFMessage, as tf2_ros would send it.

`tf2_ros.TransformBroadcaster` is a publisher of TFMessage on `/tf` with a depth-100 reliable
QoS; doing the same here needs only the message package (no tf2_ros wheel exists for pip).
"""

from __future__ import annotations

from rclpy.qos import QoSProfile

# tf2_ros.TransformBroadcaster's default QoS (reliable, volatile, keep last 100).
TF_QOS = QoSProfile(depth=100)


class TfPublisher:
    """Sends TransformStamped messages on /tf; `sent` keeps the last one (for tests, status)."""

    def __init__(self, node, message_type) -> None:
        self._message_type = message_type
        self._pub = node.create_publisher(message_type, '/tf', TF_QOS)
        self.sent = None

    def send(self, transform) -> None:
        """Publish one TransformStamped on /tf."""
        self.sent = transform
        self._pub.publish(self._message_type(transforms=[transform]))


def make_tf_publisher(node) -> TfPublisher | None:
    """A /tf publisher, or None (with a warning) when tf2_msgs cannot be imported."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        node.get_logger().warning('tf2_msgs cannot be imported: the odom -> base_link '
                                  'transform is not published on /tf (odometry still is); '
                                  'install ros-jazzy-tf2-msgs')
        return None
    return TfPublisher(node, TFMessage)
