"""filter_odom_node as users run it: colcon-built, its own process, DDS in and out."""

from __future__ import annotations

import json
import subprocess
import tempfile
import time

import numpy as np
import pytest

from gft_odom.config import GftOdomConfig, with_values
from gft_odom.io.pcd import read_pcd
from gft_odom.io.tum import read_tum
from gft_odom.params_file import load_config, packaged_params_file, write_params_file
from gft_odom.replay import run_replay
from gft_odom.ros.through_node import replay_through_node

pytestmark = [pytest.mark.slow, pytest.mark.ros]

N_SCANS = 12


def test_node_trajectory_equals_in_process_replay(installed_node, orchard_bag, ros_env,
                                                   tmp_path):
    exe, env = installed_node
    env.update({k: ros_env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    # The paper-mode mask: the node really filters (frequency fields, points dropped).
    config = load_config(packaged_params_file('paper_mode_gft.yaml'))
    in_process = run_replay([orchard_bag.bag_path], config, max_scans=N_SCANS)
    through_node = replay_through_node([orchard_bag.bag_path], config, max_scans=N_SCANS,
                                       node_exe=str(exe), env=env,
                                       log_path=tmp_path / 'node.log')
    assert len(through_node.sensor_trajectory) == N_SCANS
    np.testing.assert_array_equal(through_node.sensor_trajectory.stamps_ns,
                                  in_process.sensor_trajectory.stamps_ns)
    # Same code, same scans: equal up to float round-off of the Odometry message (float64).
    np.testing.assert_allclose(through_node.base_trajectory.poses,
                               in_process.base_trajectory.poses, atol=1e-6)
    assert through_node.metrics['node_path_length'] == N_SCANS
    # Filtered clouds (best-effort QoS) came back with as many points as in-process kept.
    received = through_node.points_kept >= 0
    assert received.sum() >= N_SCANS // 2
    np.testing.assert_array_equal(through_node.points_kept[received],
                                  in_process.points_kept[received])


def test_node_refuses_an_invalid_params_file(installed_node, ros_env, tmp_path):
    exe, env = installed_node
    env.update({k: ros_env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    params = tmp_path / 'bad.yaml'
    params.write_text('/**:\n  ros__parameters:\n    spectral:\n      tau_m: -0.3\n')
    proc = subprocess.run([str(exe), '--ros-args', '--params-file', str(params)], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0
    assert 'tau_m' in proc.stdout + proc.stderr


def test_node_refuses_an_invalid_parameter_at_run_time(installed_node, ros_env, tmp_path):
    import rclpy
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import GetParameters, SetParameters

    exe, env = installed_node
    env.update({k: ros_env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    good = with_values(GftOdomConfig(), {'spectral.tau_m': 0.35})
    params = write_params_file(tmp_path / 'good.yaml', good)
    proc = subprocess.Popen([str(exe), '--ros-args', '--params-file', str(params)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = rclpy.create_node('param_client', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def call(client, request):
        assert client.wait_for_service(timeout_sec=30.0), 'node services did not appear'
        # The first response can be lost while the reply path is still being matched:
        # these requests are idempotent, so an unanswered one is sent again.
        for _ in range(3):
            future = client.call_async(request)
            deadline = time.monotonic() + 10.0
            while not future.done() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            if future.done():
                return future.result()
        raise AssertionError('the node answered none of 3 requests')

    def double(name, value):
        return Parameter(name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE,
                                                         double_value=value))

    try:
        setter = node.create_client(SetParameters, '/filter_odom_node/set_parameters')
        getter = node.create_client(GetParameters, '/filter_odom_node/get_parameters')
        bad = call(setter, SetParameters.Request(parameters=[double('spectral.tau_m', -1.0)]))
        assert not bad.results[0].successful
        assert 'tau_m' in bad.results[0].reason
        band = Parameter(name='spectral.band_mask', value=ParameterValue(
            type=ParameterType.PARAMETER_INTEGER_ARRAY, integer_array_value=[0, 11]))
        bad_band = call(setter, SetParameters.Request(parameters=[band]))
        assert not bad_band.results[0].successful
        value = call(getter, GetParameters.Request(names=['spectral.tau_m'])).values[0]
        assert value.double_value == pytest.approx(0.35)  # the old value stays
        ok = call(setter, SetParameters.Request(parameters=[double('spectral.tau_m', 0.4)]))
        assert ok.results[0].successful, ok.results[0].reason
        assert proc.poll() is None, 'the node must keep running'
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        proc.terminate()
        proc.wait(timeout=15)


def test_replay_cli_through_the_node_writes_the_results_folder(installed_node, orchard_bag,
                                                               ros_env, tmp_path, monkeypatch):
    from gft_odom.tools.cli import main

    exe, env = installed_node
    for key in ('PYTHONPATH', 'AMENT_PREFIX_PATH'):
        monkeypatch.setenv(key, env[key])  # as after `source install/setup.bash`
    out = tmp_path / 'through_node'
    temp = tmp_path / 'tmp'  # a private temp dir: other runs on this host use /tmp too
    temp.mkdir()
    monkeypatch.setattr(tempfile, 'tempdir', str(temp))
    assert main(['replay', str(orchard_bag.bag_path), '--gt', str(orchard_bag.gt_csv_path),
                 '--out', str(out), '--through-node', '--max-scans', '5', '--quiet',
                 '--config', str(packaged_params_file('paper_mode_gft.yaml')),
                 '--save-map']) == 0
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['n_scans'] == 5 and metrics['ate_rmse_m'] is not None
    # The node's ~/save_map wrote its map (paper mode: the last trusted scan) under <out>/map.
    (saved,) = (out / 'map').iterdir()
    assert str(saved / 'map.pcd') in metrics['saved_map']
    assert read_pcd(saved / 'map.pcd').shape[0] > 300
    assert len(read_tum(saved / 'trajectory_tum.txt')) == 5
    poses = [line for line in (out / 'trajectory_tum.txt').read_text().splitlines()
             if not line.startswith('#')]
    assert len(poses) == 5
    assert (out / 'trajectory.png').is_file()
    # The node's log goes with the results; no temporary folder is left behind.
    assert 'final counts:' in (out / 'node.log').read_text()
    assert not list(temp.glob('gft_odom_node_*'))


def test_node_localises_in_a_saved_map_over_dds(installed_node, orchard_bag, ros_env,
                                                 tmp_path):
    """The node in its own process loads a map (localisation.map_file), publishes
    ~/map_pose for every scan, near where its odometry puts the same drive."""
    exe, env = installed_node
    env.update({k: ros_env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    config = GftOdomConfig()
    run_replay([orchard_bag.bag_path], config, max_scans=N_SCANS, save_map_dir=tmp_path / 'm')
    with_map = with_values(config, {'localisation.map_file': str(tmp_path / 'm' / 'map.pcd')})
    through_node = replay_through_node([orchard_bag.bag_path], with_map, max_scans=N_SCANS,
                                       node_exe=str(exe), env=env,
                                       log_path=tmp_path / 'node.log')
    located = through_node.map_trajectory
    assert located is not None and len(located) >= N_SCANS - 1
    odometry = through_node.sensor_trajectory
    at = np.searchsorted(odometry.stamps_ns, located.stamps_ns)
    gap_m = np.linalg.norm(located.positions_xyz - odometry.positions_xyz[at], axis=1)
    assert gap_m.max() < 0.1
    assert 'map' in (tmp_path / 'node.log').read_text()
