"""numpy / core types <-> ROS 2 messages."""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, PoseStamped, Quaternion, TransformStamped, Vector3
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from gft_odom.core.constants import ns_to_sec_nanosec, sec_nanosec_to_ns
from gft_odom.core.geometry import xyz_quat_from_poses
from gft_odom.io.pointcloud2 import CloudBlob


def stamp_to_ns(stamp) -> int:
    """`builtin_interfaces/Time` -> int nanoseconds (exact, no float)."""
    return sec_nanosec_to_ns(stamp.sec, stamp.nanosec)


def ns_to_stamp(stamp_ns: int) -> Time:
    """builtin_interfaces/Time of an integer nanosecond stamp."""
    sec, nanosec = ns_to_sec_nanosec(stamp_ns)
    return Time(sec=sec, nanosec=nanosec)


def blob_to_msg(blob: CloudBlob, stamp_ns: int, frame_id: str) -> PointCloud2:
    """An rclpy PointCloud2 from the codec's output."""
    msg = PointCloud2()
    msg.header = Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)
    msg.height = blob.height
    msg.width = blob.width
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in blob.fields]
    msg.is_bigendian = blob.is_bigendian
    msg.point_step = blob.point_step
    msg.row_step = blob.row_step
    msg.is_dense = blob.is_dense
    msg.data = bytes(blob.data)
    return msg


def pose_msg(T: np.ndarray) -> Pose:
    """geometry_msgs/Pose of a 4x4 transform."""
    xyz, quat = xyz_quat_from_poses(T[None])
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in xyz[0])
    pose.orientation = Quaternion(x=float(quat[0, 0]), y=float(quat[0, 1]),
                                  z=float(quat[0, 2]), w=float(quat[0, 3]))
    return pose


def odometry_msg(T_odom_base: np.ndarray, stamp_ns: int, odom_frame: str, base_frame: str,
                 covariance: np.ndarray, twist: np.ndarray | None = None,
                 twist_covariance: np.ndarray | None = None) -> Odometry:
    """nav_msgs/Odometry of odom -> base_link with its pose covariance and, when given, the
    twist of base_link in its own axes ([v_x, v_y, v_z, w_x, w_y, w_z]) and its covariance."""
    msg = Odometry()
    msg.header = Header(stamp=ns_to_stamp(stamp_ns), frame_id=odom_frame)
    msg.child_frame_id = base_frame
    msg.pose.pose = pose_msg(T_odom_base)
    msg.pose.covariance = [float(v) for v in np.asarray(covariance, dtype=float).reshape(36)]
    if twist is not None:
        v = [float(x) for x in twist]
        msg.twist.twist.linear = Vector3(x=v[0], y=v[1], z=v[2])
        msg.twist.twist.angular = Vector3(x=v[3], y=v[4], z=v[5])
    if twist_covariance is not None:
        msg.twist.covariance = [float(x) for x in
                                np.asarray(twist_covariance, dtype=float).reshape(36)]
    return msg


def odometry_twist(msg: Odometry) -> np.ndarray:
    """[v_x, v_y, v_z, w_x, w_y, w_z] of an Odometry message."""
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    return np.array([lin.x, lin.y, lin.z, ang.x, ang.y, ang.z])


def pose_stamped_msg(T: np.ndarray, stamp_ns: int, frame_id: str) -> PoseStamped:
    """geometry_msgs/PoseStamped of a 4x4 transform."""
    msg = PoseStamped()
    msg.header = Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)
    msg.pose = pose_msg(T)
    return msg


def transform_msg(T_parent_child: np.ndarray, stamp_ns: int, parent: str,
                  child: str) -> TransformStamped:
    """geometry_msgs/TransformStamped parent -> child of a 4x4 transform."""
    msg = TransformStamped()
    msg.header = Header(stamp=ns_to_stamp(stamp_ns), frame_id=parent)
    msg.child_frame_id = child
    pose = pose_msg(T_parent_child)
    msg.transform.translation = Vector3(x=pose.position.x, y=pose.position.y, z=pose.position.z)
    msg.transform.rotation = pose.orientation
    return msg


def pose_matrix(pose: Pose) -> np.ndarray:
    """The 4x4 transform of a geometry_msgs/Pose (its quaternion normalised)."""
    from gft_odom.core.geometry import poses_from_xyz_quat
    p, q = pose.position, pose.orientation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=float)
    return poses_from_xyz_quat([p.x, p.y, p.z], quat / np.linalg.norm(quat))[0]


def odometry_to_pose(msg: Odometry) -> np.ndarray:
    """The 4x4 pose in an Odometry message."""
    return pose_matrix(msg.pose.pose)
