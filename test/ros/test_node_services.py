"""The colcon-installed node over DDS: start-up errors, filtered_points QoS, reset, diagnostics,
a clean shutdown."""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest

pytestmark = [pytest.mark.slow, pytest.mark.ros]


def _env(installed_node, ros_env):
    exe, env = installed_node
    env = dict(env)
    env.update({k: ros_env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    return exe, env


@pytest.mark.parametrize('content, expected', [
    ('/**:\n  ros__parameters:\n    spectral:\n      tua_m: 0.3\n',
     "unknown parameter 'spectral.tua_m' (params file or -p); did you mean 'spectral.tau_m'?"),
    (None, 'No such file or directory'),
    ('/**:\n  ros__parameters: [\n', 'is not valid YAML'),
])
def test_a_bad_params_file_gives_one_cannot_start_line_and_exit_2(installed_node, ros_env,
                                                                  tmp_path, content, expected):
    exe, env = _env(installed_node, ros_env)
    params = tmp_path / 'params.yaml'
    if content is not None:
        params.write_text(content)
    proc = subprocess.run([str(exe), '--ros-args', '--params-file', str(params)], env=env,
                          capture_output=True, text=True, timeout=60)
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if line.strip()]
    assert proc.returncode == 2, lines
    assert len(lines) == 1 and 'cannot start:' in lines[0] and expected in lines[0], lines


@pytest.fixture
def running_node(installed_node, ros_env, tmp_path):
    """The node (package defaults) and a client node in this process, same DDS domain."""
    import rclpy
    exe, env = _env(installed_node, ros_env)
    log = tmp_path / 'node.log'
    with open(log, 'w') as f:
        proc = subprocess.Popen([str(exe), '--ros-args', '-r', 'points:=/velodyne_points'],
                                env=env, stdout=f, stderr=subprocess.STDOUT)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = rclpy.create_node('services_client', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def spin_until(done, timeout_s):
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()
            executor.spin_once(timeout_sec=0.02)
        return done()

    try:
        yield proc, node, spin_until, log
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_reset_diagnostics_filtered_points_and_a_clean_shutdown(running_node, orchard_bag):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from gft_odom.io.bags import ScanBagReader
    from gft_odom.ros.conversions import ns_to_stamp, odometry_to_pose, stamp_to_ns
    from gft_odom.ros.through_node import ros_message_from_bag, stop_node_process

    proc, node, spin_until, log = running_node
    with ScanBagReader([orchard_bag.bag_path]) as reader:
        scans = [ros_message_from_bag(raw) for _, raw in reader.iter_messages()][:5]
    odometry, clouds_reliable, clouds_best_effort, diagnostics = {}, [], [], []
    reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Odometry, '/filter_odom_node/odometry',
                             lambda m: odometry.__setitem__(stamp_to_ns(m.header.stamp),
                                                            odometry_to_pose(m)), reliable)
    # RViz's default is reliable: it must be served as well as a best-effort subscriber.
    node.create_subscription(PointCloud2, '/filter_odom_node/filtered_points',
                             clouds_reliable.append, QoSProfile(depth=5))
    node.create_subscription(PointCloud2, '/filter_odom_node/filtered_points',
                             clouds_best_effort.append, qos_profile_sensor_data)
    node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 10)
    pub = node.create_publisher(PointCloud2, '/velodyne_points', reliable)
    reset = node.create_client(Trigger, '/filter_odom_node/reset')
    assert reset.wait_for_service(timeout_sec=60.0)
    assert spin_until(lambda: pub.get_subscription_count() > 0, 30.0)
    spin_until(lambda: False, 1.0)

    # Wall-clock stamps, 0.1 s apart, like a live sensor.
    t0 = time.time_ns()
    for i, msg in enumerate(scans):
        msg.header.stamp = ns_to_stamp(t0 + i * 100_000_000)
        pub.publish(msg)
        stamp = stamp_to_ns(msg.header.stamp)
        assert spin_until(lambda: stamp in odometry, 20.0), log.read_text()
        if i == 3:
            before = odometry[stamp]
            future = reset.call_async(Trigger.Request())
            assert spin_until(future.done, 10.0)
            assert future.result().success
            t0 += 1_000_000_000  # a second later, as after a restart
    after = odometry[stamp_to_ns(scans[-1].header.stamp)]
    assert np.linalg.norm(before[:3, 3]) > 0.1  # the drive had moved
    np.testing.assert_allclose(after, np.eye(4), atol=1e-9)  # started again at the origin
    assert spin_until(lambda: clouds_reliable and clouds_best_effort, 5.0)

    def latest_values():
        return {kv.key: kv.value for kv in diagnostics[-1].status[0].values}

    # At 1 Hz: the latest one received may predate the last scans; wait for one after them.
    assert spin_until(lambda: diagnostics and latest_values().get('total_processed')
                      == str(len(scans)), 5.0)
    status = diagnostics[-1].status[0]
    assert status.name == 'filter_odom_node: odometry'
    assert status.level in (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)
    values = {kv.key: kv.value for kv in status.values}
    assert int(values['total_processed']) == len(scans) and values['total_reset'] == '1'

    assert stop_node_process(proc) == 0
    text = log.read_text()
    assert 'final counts:' in text and 'processed=5' in text
    assert 'Failed to publish log message' not in text, text[-2000:]
