"""FilterOdomNode in-process: TF message, Path publishing, parameters, logging, missed counter."""

from __future__ import annotations

import copy
import logging

import numpy as np
import pytest

from gft_odom.errors import ConfigError

pytestmark = [pytest.mark.ros]


@pytest.fixture(scope='module')
def scans(orchard_messages) -> list:
    return orchard_messages[:6]


@pytest.fixture
def make_node():
    import rclpy
    from rclpy.parameter import Parameter

    from gft_odom.ros.node import FilterOdomNode
    context = rclpy.Context()
    rclpy.init(context=context)
    nodes = []

    def make(**values):
        overrides = [Parameter('use_sim_time', Parameter.Type.BOOL, True)]
        overrides += [Parameter(k, value=v) for k, v in values.items()]
        nodes.append(FilterOdomNode(context=context, parameter_overrides=overrides))
        return nodes[-1]

    try:
        yield make
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


class Recorder:
    def __init__(self):
        self.sent = []

    def send(self, msg):
        self.sent.append(msg)

    publish = send


def test_the_transform_sent_on_tf_is_the_odometry_pose(make_node, scans, monkeypatch):
    import gft_odom.ros.node as node_module
    from gft_odom.ros.conversions import stamp_to_ns
    tf = Recorder()
    monkeypatch.setattr(node_module, 'make_tf_publisher', lambda node: tf)
    node = make_node(**{'node.odom_frame': 'odom_lidar', 'node.base_frame': 'base'})
    odom = Recorder()
    node.odom_pub = odom
    for msg in scans[:4]:
        node._on_cloud(msg)
    assert len(tf.sent) == len(odom.sent) == 4
    for t, o in zip(tf.sent, odom.sent):
        assert (t.header.frame_id, t.child_frame_id) == ('odom_lidar', 'base')
        assert stamp_to_ns(t.header.stamp) == stamp_to_ns(o.header.stamp)
        p, q = o.pose.pose.position, o.pose.pose.orientation
        tr, rot = t.transform.translation, t.transform.rotation
        np.testing.assert_allclose([tr.x, tr.y, tr.z, rot.x, rot.y, rot.z, rot.w],
                                   [p.x, p.y, p.z, q.x, q.y, q.z, q.w])
    assert abs(tf.sent[-1].transform.translation.x) > 0.05  # the drive moved


def test_tf_publisher_wraps_the_transform_in_one_tfmessage():
    from geometry_msgs.msg import TransformStamped

    from gft_odom.ros.tf import TF_QOS, TfPublisher

    class FakeTFMessage:
        def __init__(self, transforms):
            self.transforms = transforms

    pub = Recorder()
    created = []

    class FakeNode:
        def create_publisher(self, msg_type, topic, qos):
            created.append((msg_type, topic, qos))
            return pub

    tf = TfPublisher(FakeNode(), FakeTFMessage)
    t = TransformStamped()
    tf.send(t)
    assert created == [(FakeTFMessage, '/tf', TF_QOS)]
    assert TF_QOS.depth == 100  # what tf2_ros.TransformBroadcaster uses
    assert pub.sent[0].transforms == [t]


def test_path_is_sent_by_the_timer_only_to_subscribers(make_node, scans):
    node = make_node()
    path = Recorder()
    path.count = 0
    path.get_subscription_count = lambda: path.count
    node.path_pub = path
    for msg in scans[:3]:
        node._on_cloud(msg)
    assert path.sent == []  # never per scan
    node._publish_path()
    assert path.sent == []  # nobody listens
    path.count = 1
    node._publish_path()
    assert len(path.sent) == 1 and len(path.sent[0].poses) == 3
    node._publish_path()
    assert len(path.sent) == 1  # unchanged: not sent again


def test_parameters_describe_themselves_and_startup_ones_are_read_only(make_node):
    from rclpy.parameter import Parameter
    node = make_node()
    tau = node.describe_parameter('spectral.tau_m')
    assert 'Unit: m.' in tau.description and len(tau.description) > 30
    assert not tau.read_only
    mode = node.describe_parameter('registration.mode')
    assert mode.read_only and 'start-up' in mode.description
    result = node.set_parameters([Parameter('registration.mode', value='paper')])[0]
    assert not result.successful
    assert node.get_parameter('registration.mode').value == 'default'


def test_a_misspelled_parameter_is_refused_with_the_closest_name(make_node):
    with pytest.raises(ConfigError, match=r"'spectral.tua_m'.*did you mean 'spectral.tau_m'"):
        make_node(**{'spectral.tua_m': 0.3})
    with pytest.raises(ConfigError, match='unknown parameter'):
        make_node(**{'nodes.odom_frame': 'odom'})


def test_python_logging_reaches_the_node_logger_throttled(make_node, monkeypatch):
    node = make_node()
    got = []
    monkeypatch.setattr(node._log_handler, '_ros_logger',
                        type('L', (), {'warning': lambda self, t: got.append(t)})())
    for i in range(20):
        logging.getLogger('gft_odom.core.registration').warning('ICP did not converge (%d)', i)
    assert len(got) == 1 and 'gft_odom.core.registration: ICP did not converge (0)' in got[0]


def test_missed_sweeps_are_counted_at_the_sensor_rate_from_the_stamps(make_node, scans):
    from gft_odom.ros.conversions import ns_to_stamp, stamp_to_ns
    node = make_node()
    t0 = stamp_to_ns(scans[0].header.stamp)
    # A 20 Hz sensor (50 ms) with one sweep lost: scan_period_s (0.1 s) would see none missed.
    offsets_ms = [0, 50, 100, 150, 200, 300]
    for msg, dt_ms in zip(scans, offsets_ms):
        msg = copy.copy(msg)
        msg.header = copy.deepcopy(msg.header)
        msg.header.stamp = ns_to_stamp(t0 + dt_ms * 1_000_000)
        node._on_cloud(msg)
    assert node.scan_period_s() == pytest.approx(0.05)
    assert node.counters['missed'] == 1


def test_a_stamp_far_from_the_clock_points_at_the_clock():
    from gft_odom.ros.diagnostics import stale_scan_text
    text = stale_scan_text(106152016.0, use_sim_time=False, max_scan_age_s=0.5)
    assert 'use_sim_time' in text and '--clock' in text
    assert '/clock published' in stale_scan_text(106152016.0, True, 0.5)
    assert 'processing lags' in stale_scan_text(0.8, False, 0.5)


def test_check_params_files_says_what_is_wrong(tmp_path):
    from gft_odom.ros.parameters import check_params_files
    with pytest.raises(ConfigError, match='No such file'):
        check_params_files(['--ros-args', '--params-file', str(tmp_path / 'missing.yaml')])
    broken = tmp_path / 'broken.yaml'
    broken.write_text('/**:\n  ros__parameters: [\n')
    with pytest.raises(ConfigError, match='not valid YAML'):
        check_params_files(['--ros-args', '--params-file', str(broken)])


def test_default_node_publishes_every_point_with_its_frequency_and_band(make_node, scans):
    """The package defaults compute the frequencies on every scan."""
    from gft_odom.core.spectral import SpectralFilter
    from gft_odom.io.pointcloud2 import decode_fields, decode_scan
    from gft_odom.pipeline import OdometryPipeline
    node = make_node()
    clouds = Recorder()
    clouds.get_subscription_count = lambda: 1  # someone listens: the node publishes
    node.cloud_pub = clouds
    for msg in scans[:3]:
        node._on_cloud(msg)
    assert len(clouds.sent) == 3
    reference = OdometryPipeline(node.config)
    spectral = SpectralFilter(node.config.spectral)
    for msg, out in zip(scans, clouds.sent):
        fields = decode_fields(out)
        assert {'frequency', 'band'} <= set(fields)
        cropped = reference._crop(decode_scan(msg))
        assert fields['band'].shape[0] == len(cropped)  # all-pass: every point kept
        expected = spectral.scan_frequencies(cropped)
        np.testing.assert_array_equal(fields['band'], expected.band.astype(np.uint8))
        assert len(np.unique(fields['band'])) >= 4  # the bands are used, not one


def test_odometry_carries_the_body_twist_and_a_fallback_says_it_knows_none(make_node, scans):
    """The simulated drive goes ~1 m/s straight along the row (base_link x)."""
    from gft_odom.ros.conversions import odometry_twist
    node = make_node()
    odom = Recorder()
    node.odom_pub = odom
    for msg in scans[:6]:
        node._on_cloud(msg)
    first = odom.sent[0]
    np.testing.assert_array_equal(odometry_twist(first), np.zeros(6))
    reg = node.config.registration
    np.testing.assert_allclose(np.diag(np.reshape(first.twist.covariance, (6, 6))),
                               [reg.max_speed_mps ** 2] * 3 + [reg.max_yaw_rate_rps ** 2] * 3)
    moving = [odometry_twist(m) for m in odom.sent[2:]]
    # One match's noise is a few cm over 0.1 s: tenths of a m/s per scan (test/core/test_twist).
    assert 0.8 < np.mean([t[0] for t in moving]) < 1.2
    for twist, msg in zip(moving, odom.sent[2:]):
        assert 0.3 < twist[0] < 1.8 and abs(twist[1]) < 0.6 and abs(twist[5]) < 0.2
        cov = np.reshape(msg.twist.covariance, (6, 6))
        assert 0.0 < cov[0, 0] < 0.5 and 0.0 < cov[5, 5] < 0.05  # far below the unknown's
        np.testing.assert_allclose(cov, cov.T)
    assert msg.child_frame_id == node.config.node.base_frame


def test_save_map_writes_the_map_and_trajectory_and_says_where(make_node, scans, tmp_path):
    from std_srvs.srv import Trigger

    from gft_odom.io.pcd import read_pcd
    from gft_odom.io.tum import read_tum
    from gft_odom.ros.conversions import odometry_to_pose
    node = make_node(**{'node.save_map_dir': str(tmp_path / 'maps')})
    odom = Recorder()
    node.odom_pub = odom
    for msg in scans[:4]:
        node._on_cloud(msg)
    response = node._on_save_map(Trigger.Request(), Trigger.Response())
    assert response.success, response.message
    (folder,) = (tmp_path / 'maps').iterdir()
    assert str(folder / 'map.pcd') in response.message
    cloud = read_pcd(folder / 'map.pcd')
    assert cloud.shape[0] == len(node.pipeline.drive_map) > 1000  # the whole drive's map
    assert np.isfinite(cloud['frequency']).mean() > 0.5  # isolated points have none
    trajectory = read_tum(folder / 'trajectory_tum.txt')
    np.testing.assert_allclose(trajectory.poses, [odometry_to_pose(m) for m in odom.sent],
                               atol=1e-6)
    node._on_reset(Trigger.Request(), Trigger.Response())
    assert len(node.trajectory()) == 0


def test_save_map_into_a_folder_it_cannot_create_fails_with_the_reason(make_node, scans,
                                                                       tmp_path):
    from std_srvs.srv import Trigger
    blocker = tmp_path / 'file'
    blocker.write_text('not a folder')
    node = make_node(**{'node.save_map_dir': str(blocker)})
    node._on_cloud(scans[0])
    response = node._on_save_map(Trigger.Request(), Trigger.Response())
    assert not response.success and 'map not saved' in response.message


def test_diagnostics_name_the_weakest_direction_in_base_axes(make_node, scans):
    node = make_node()
    diagnostics = Recorder()
    node.diagnostics_pub = diagnostics
    for msg in scans[:4]:
        node._on_cloud(msg)
    node._publish_diagnostics()
    values = {kv.key: kv.value for kv in diagnostics.sent[-1].status[0].values}
    # Along the row: the direction of travel is the least constrained, well above the WARN.
    assert values['weakest_direction'] == 'translation along x'
    assert float(values['weakest_direction_ratio']) > node.config.node.weak_direction_warn_ratio


def test_adaptive_reliability_follows_rosbag2():
    from rclpy.qos import ReliabilityPolicy

    from gft_odom.ros.input_qos import adaptive_reliability
    reliable, best_effort = ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT
    assert adaptive_reliability([]) is None
    assert adaptive_reliability([reliable, reliable]) == reliable
    assert adaptive_reliability([reliable, best_effort]) == best_effort


def test_input_reliability_is_checked_and_read_at_start_up_only(make_node):
    from rclpy.parameter import Parameter
    with pytest.raises(ConfigError, match='input_reliability must be one of'):
        make_node(**{'node.input_reliability': 'sometimes'})
    node = make_node(**{'node.input_reliability': 'reliable'})
    from rclpy.qos import ReliabilityPolicy
    assert node.input_reliability == ReliabilityPolicy.RELIABLE
    result = node.set_parameters([Parameter('node.input_reliability', value='best_effort')])[0]
    assert not result.successful


@pytest.mark.slow
def test_a_platform_faster_than_the_bound_is_told_in_the_log_and_diagnostics(make_node,
                                                                             monkeypatch):
    """A simulated row drive at 4 m/s against the default 2 m/s bound."""
    from gft_odom.io.pointcloud2 import encode_scan
    from gft_odom.ros.conversions import blob_to_msg
    from gft_odom.ros.diagnostics import WARN
    from gft_odom.sim.simulator import ScanSimulator, SimConfig
    node = make_node()
    logged = []
    monkeypatch.setattr(node._log_handler, '_ros_logger',
                        type('L', (), {'warning': lambda self, t: logged.append(t),
                                       'info': lambda self, t: None,
                                       'debug': lambda self, t: None})())
    diagnostics = Recorder()
    node.diagnostics_pub = diagnostics
    sim = ScanSimulator.from_config(SimConfig(azimuth_step_deg=0.4, speed_mps=4.0), 'row', 16,
                                    5)
    for i in range(16):
        scan = sim.scan(i).scan
        node._on_cloud(blob_to_msg(encode_scan(scan), scan.stamp_ns, 'velodyne'))
    told = [t for t in logged if 'registration.max_speed_mps' in t]
    assert len(told) == 1 and 'm/s' in told[0]
    node._publish_diagnostics()
    status = diagnostics.sent[-1].status[0]
    # At least WARN from the bounds line; a slow, shared machine may add the latency ERROR
    # (refused matches run their retries), which says nothing about the bound.
    assert ord(status.level) >= ord(WARN) and 'registration.max_speed_mps = 2' in status.message
