"""FilterOdomNode localising in a saved map: map -> odom, ~/map_pose, /initialpose, the map's
errors, /diagnostics (in-process)."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = [pytest.mark.ros]


@pytest.fixture(scope='module')
def scans(orchard_messages) -> list:
    return orchard_messages[:8]


@pytest.fixture
def make_node(monkeypatch):
    import rclpy
    from rclpy.parameter import Parameter

    import gft_odom.ros.node as node_module
    from gft_odom.ros.node import FilterOdomNode
    context = rclpy.Context()
    rclpy.init(context=context)
    nodes, sent = [], []
    monkeypatch.setattr(node_module, 'make_tf_publisher', lambda node: Recorder(sent))

    def make(**values):
        overrides = [Parameter('use_sim_time', Parameter.Type.BOOL, True)]
        overrides += [Parameter(k, value=v) for k, v in values.items()]
        node = FilterOdomNode(context=context, parameter_overrides=overrides)
        node.tf_sent = sent
        node.odom_pub, node.map_pose_pub = Recorder([]), Recorder([])
        nodes.append(node)
        return node

    try:
        yield make
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


class Recorder:
    def __init__(self, sent):
        self.sent = sent

    def send(self, msg):
        self.sent.append(msg)

    publish = send


@pytest.fixture
def saved_map(make_node, scans, tmp_path) -> str:
    """The map of the first scans, as ~/save_map writes it."""
    from std_srvs.srv import Trigger
    node = make_node(**{'node.save_map_dir': str(tmp_path / 'maps')})
    for msg in scans:
        node._on_cloud(msg)
    assert node._on_save_map(Trigger.Request(), Trigger.Response()).success
    (folder,) = (tmp_path / 'maps').iterdir()
    return str(folder / 'map.pcd')


def _pose(msg) -> np.ndarray:
    p = msg.pose.pose.position
    return np.array([p.x, p.y, p.z])


def test_the_same_drive_localises_where_its_odometry_put_it(make_node, scans, saved_map):
    from gft_odom.ros.conversions import stamp_to_ns
    node = make_node(**{'localisation.map_file': saved_map})
    for msg in scans:
        node._on_cloud(msg)
    assert node.counters['map_localised'] == len(scans)
    map_to_odom = [t for t in node.tf_sent if t.header.frame_id == 'map']
    assert len(map_to_odom) == len(scans) and map_to_odom[0].child_frame_id == 'odom'
    poses = node.map_pose_pub.sent
    assert len(poses) == len(scans) and poses[0].header.frame_id == 'map'
    errors = []
    for pose, odom in zip(poses, node.odom_pub.sent):
        assert stamp_to_ns(pose.header.stamp) == stamp_to_ns(odom.header.stamp)
        # The map is this drive's, in its odom frame: the map pose is the odometry's (the map
        # holds the second scan; the others are matched to it from up to a metre away).
        errors.append(np.linalg.norm(_pose(pose) - _pose(odom)))
    assert max(errors) < 0.1  # a frame mixed up would be 0.38 m off (the mount)
    covariance = np.array(poses[-1].pose.covariance).reshape(6, 6)
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    status = node.localisation_status()
    assert status.level == status.OK and 'fit' in status.message


def test_initialpose_in_the_map_frame_moves_the_start_and_others_are_refused(
        make_node, scans, saved_map):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    node = make_node(**{'localisation.map_file': saved_map})
    wrong = PoseWithCovarianceStamped()
    wrong.header.frame_id = 'odom'
    node._on_initial_pose(wrong)
    assert node.counters['initial_pose'] == 1
    shifted = PoseWithCovarianceStamped()
    shifted.header.frame_id = 'map'
    shifted.pose.pose.position.x = 0.2  # 20 cm off: the map pulls it back
    shifted.pose.pose.orientation.w = 1.0
    node._on_initial_pose(shifted)
    assert node.counters['initial_pose'] == 1
    for msg in scans:
        node._on_cloud(msg)
    errors = [np.linalg.norm(_pose(p) - _pose(o))
              for p, o in zip(node.map_pose_pub.sent, node.odom_pub.sent)]
    assert max(errors) < 0.1  # from 0.2 m off at the start


@pytest.mark.parametrize('case', ['missing', 'sensor frame'])
def test_a_map_that_cannot_serve_is_one_error_and_the_odometry_goes_on(
        make_node, scans, tmp_path, case):
    from gft_odom.io.pcd import frequency_cloud, write_pcd
    path = tmp_path / 'map.pcd'
    if case == 'sensor frame':
        points = np.random.default_rng(0).uniform(-5, 5, (500, 3))
        write_pcd(path, frequency_cloud(points, None, np.zeros(500, np.float32),
                                        np.zeros(500, np.uint8)), frame_id='velodyne')
    node = make_node(**{'localisation.map_file': str(path)})
    assert node.localisation is None and str(path) in node.map_error
    for msg in scans[:3]:
        node._on_cloud(msg)
    assert len(node.odom_pub.sent) == 3 and not node.map_pose_pub.sent
    status = node.localisation_status()
    assert status.level == status.ERROR and str(path) in status.message


def test_a_map_file_set_at_run_time_is_loaded(make_node, scans, saved_map):
    from rclpy.parameter import Parameter
    node = make_node()
    assert node.localisation is None and node.localisation_status().message.startswith('no map')
    result = node.set_parameters([Parameter('localisation.map_file', value=saved_map)])
    assert result[0].successful and node.localisation is not None
    node._on_cloud(scans[0])
    assert node.counters['map_localised'] == 1
