"""The colcon-installed node over DDS: input QoS that follows the publishers (rosbag2's rule),
REP-2003 QoS overrides from a params file, the twist, and ~/save_map."""

from __future__ import annotations

import subprocess
import time

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.ros]

TOPIC = '/velodyne_points'


@pytest.fixture
def start_node(installed_node, ros_env, tmp_path):
    """`start(*ros_args)`: the node in its own process and a client node here (same domain):
    (process, client node, spin_until, log path)."""
    import rclpy
    exe, env = installed_node
    env = dict(env)
    env.update({k: ros_env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    started = []

    def start(*ros_args):
        log = tmp_path / 'node.log'
        with open(log, 'w') as f:
            proc = subprocess.Popen([str(exe), '--ros-args', '-r', f'points:={TOPIC}',
                                     *ros_args], env=env, stdout=f, stderr=subprocess.STDOUT)
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']))
        node = rclpy.create_node('qos_client', context=context)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        started.append((proc, context, node, executor))

        def spin_until(done, timeout_s):
            deadline = time.monotonic() + timeout_s
            while not done() and time.monotonic() < deadline:
                assert proc.poll() is None, log.read_text()
                executor.spin_once(timeout_sec=0.02)
            return done()

        return proc, node, spin_until, log

    try:
        yield start
    finally:
        for proc, context, node, executor in started:
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=context)
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def _node_subscription(node, topic=TOPIC):
    """The filter_odom_node's endpoint on `topic`, or None."""
    found = [i for i in node.get_subscriptions_info_by_topic(topic)
             if i.node_name == 'filter_odom_node']
    return found[0] if found else None


def test_input_follows_the_publishers_and_save_map_answers(start_node, orchard_bag, tmp_path):
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from gft_odom.io.bags import ScanBagReader
    from gft_odom.io.pcd import read_pcd
    from gft_odom.io.tum import read_tum
    from gft_odom.ros.conversions import ns_to_stamp, odometry_twist, stamp_to_ns
    from gft_odom.ros.through_node import ros_message_from_bag, stop_node_process

    maps = tmp_path / 'maps'
    proc, node, spin_until, log = start_node('-p', f'node.save_map_dir:={maps}')
    with ScanBagReader([orchard_bag.bag_path]) as reader:
        scans = [ros_message_from_bag(raw) for _, raw in reader.iter_messages()][:6]
    twists = {}
    node.create_subscription(
        Odometry, '/filter_odom_node/odometry',
        lambda m: twists.__setitem__(stamp_to_ns(m.header.stamp), odometry_twist(m)),
        QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    # The stock velodyne driver: rclcpp::QoS(10), i.e. reliable.
    reliable = node.create_publisher(PointCloud2, TOPIC, QoSProfile(depth=10))
    assert spin_until(lambda: _node_subscription(node) is not None, 30.0), log.read_text()
    assert _node_subscription(node).qos_profile.reliability == ReliabilityPolicy.RELIABLE
    spin_until(lambda: False, 1.0)
    t0 = time.time_ns()
    for i, msg in enumerate(scans):
        msg.header.stamp = ns_to_stamp(t0 + i * 100_000_000)
        reliable.publish(msg)
        stamp = stamp_to_ns(msg.header.stamp)
        assert spin_until(lambda: stamp in twists, 20.0), log.read_text()
    assert 0.3 < twists[stamp][0] < 1.8  # ~1 m/s along the row, in base_link

    client = node.create_client(Trigger, '/filter_odom_node/save_map')
    assert client.wait_for_service(timeout_sec=30.0)
    for _ in range(3):  # the first answer can be lost while the reply path is matched
        future = client.call_async(Trigger.Request())
        if spin_until(future.done, 10.0):
            break
    response = future.result()
    assert response.success, response.message
    (folder,) = maps.iterdir()
    assert str(folder / 'map.pcd') in response.message
    assert read_pcd(folder / 'map.pcd').shape[0] > 1000
    assert len(read_tum(folder / 'trajectory_tum.txt')) == len(scans)

    # A best-effort publisher joins: a reliable subscription would get nothing from it.
    node.create_publisher(PointCloud2, TOPIC, qos_profile_sensor_data)
    assert spin_until(lambda: _node_subscription(node) is not None and _node_subscription(
        node).qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT, 10.0), log.read_text()
    # The graph shows the new subscription before the node has logged it: wait for the line
    # (stopping at once raced it on a loaded machine).
    assert spin_until(lambda: f'input {TOPIC}: best_effort' in log.read_text(), 10.0), (
        log.read_text())
    assert stop_node_process(proc) == 0
    text = log.read_text()
    assert f'input {TOPIC}: reliable' in text and f'input {TOPIC}: best_effort' in text


def test_qos_overrides_in_the_params_file_set_the_input_and_outputs(start_node, tmp_path):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    params = tmp_path / 'qos.yaml'
    params.write_text(
        '/**:\n  ros__parameters:\n    qos_overrides:\n'
        f'      {TOPIC}:\n        subscription:\n          reliability: best_effort\n'
        '          depth: 3\n'
        '      /filter_odom_node/odometry:\n        publisher:\n'
        '          reliability: best_effort\n          durability: volatile\n'
        '          depth: 7\n')
    proc, node, spin_until, log = start_node('--params-file', str(params))
    # A reliable publisher: auto would subscribe reliable; the override says best effort.
    node.create_publisher(PointCloud2, TOPIC, QoSProfile(depth=10))
    assert spin_until(lambda: _node_subscription(node) is not None, 30.0), log.read_text()
    spin_until(lambda: False, 1.5)  # auto would have re-checked by now
    assert _node_subscription(node).qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    assert spin_until(lambda: node.get_publishers_info_by_topic('/filter_odom_node/odometry'),
                      10.0)
    (odometry,) = node.get_publishers_info_by_topic('/filter_odom_node/odometry')
    assert odometry.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    assert odometry.qos_profile.durability == DurabilityPolicy.VOLATILE
    (path,) = node.get_publishers_info_by_topic('/filter_odom_node/path')
    assert path.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL  # not overridden
    proc.terminate()
    proc.wait(timeout=20)
    text = log.read_text()
    assert f'input {TOPIC}: best_effort, depth 3 (the qos_overrides parameter)' in text
