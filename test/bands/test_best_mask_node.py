"""The best_mask.yaml a search writes starts the colcon-built filter_odom_node unchanged."""

from __future__ import annotations

import subprocess
import time

import pytest

from gft_odom.bands.run import run_band_search
from gft_odom.bands.search import BandSearchConfig, SequenceSpec
from gft_odom.config import GftOdomConfig, with_values

pytestmark = [pytest.mark.slow, pytest.mark.ros]


def test_node_starts_with_the_best_mask_params_file(installed_node, orchard_bag, ros_env,
                                                    tmp_path):
    exe, env = installed_node
    env.update({k: ros_env[k] for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID')})
    config = with_values(GftOdomConfig(), {'registration.mode': 'paper'})
    spec = SequenceSpec((str(orchard_bag.bag_path),), str(orchard_bag.gt_csv_path), 'orchard')
    run_band_search([spec], config, tmp_path / 's', BandSearchConfig(2, 2), max_scans=6,
                    figures=False)
    params = tmp_path / 's' / 'best_mask.yaml'
    proc = subprocess.Popen([str(exe), '--ros-args', '--params-file', str(params)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        # A refused parameter makes the node exit within a second or two (see
        # test_node_process); still running after 8 s means every parameter was accepted.
        time.sleep(8.0)
        assert proc.poll() is None, proc.communicate(timeout=10)[0]
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
