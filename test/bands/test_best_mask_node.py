"""The best_mask.yaml a search writes starts the colcon-built filter_odom_node unchanged."""

from __future__ import annotations

import subprocess

import pytest

from gft_odom.bands.run import run_band_search
from gft_odom.bands.search import BandSearchConfig, SequenceSpec
from gft_odom.config import GftOdomConfig, with_values
from gft_odom.params_file import read_params_file

pytestmark = [pytest.mark.slow, pytest.mark.ros]


def test_node_starts_with_the_best_mask_params_file(installed_node, orchard_bag, ros_env,
                                                    ros_service_caller, tmp_path):
    from rcl_interfaces.srv import GetParameters
    from rclpy.parameter import parameter_value_to_python

    exe, env = installed_node
    env.update({k: ros_env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    config = with_values(GftOdomConfig(), {'registration.mode': 'paper'})
    spec = SequenceSpec((str(orchard_bag.bag_path),), str(orchard_bag.gt_csv_path), 'orchard')
    run_band_search([spec], config, tmp_path / 's', BandSearchConfig(2, 2), max_scans=6,
                    figures=False)
    params = tmp_path / 's' / 'best_mask.yaml'
    expected = read_params_file(params)
    assert 'spectral.band_mask' in expected and expected['registration.mode'] == 'paper'
    proc = subprocess.Popen([str(exe), '--ros-args', '--params-file', str(params)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        # The node itself says which values it runs with: every one from the file.
        try:
            answer = ros_service_caller(GetParameters, '/filter_odom_node/get_parameters',
                                        GetParameters.Request(names=list(expected)))
        except AssertionError:
            proc.terminate()
            raise AssertionError(proc.communicate(timeout=30)[0]) from None
        got = {}
        for name, value in zip(expected, answer.values):
            value = parameter_value_to_python(value)
            got[name] = value if isinstance(value, (bool, int, float, str)) else list(value)
        assert got == expected
        assert proc.poll() is None, 'the node must keep running'
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
