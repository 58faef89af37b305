"""Shared fixtures: DDS isolation for tests that talk ROS between processes."""

from __future__ import annotations

import os
import random

import pytest


@pytest.fixture(scope='session')
def ros_domain_id() -> int:
    """A per-run DDS domain, so parallel runs on one host do not hear each other."""
    return random.Random(os.getpid()).randint(10, 200)


@pytest.fixture
def ros_env(ros_domain_id, monkeypatch) -> dict[str, str]:
    """Environment for DDS tests: traffic stays on this host, in this run's domain."""
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    monkeypatch.setenv('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    return dict(os.environ)


@pytest.fixture(scope='session')
def orchard_bag(tmp_path_factory):
    """A short simulated orchard drive (rosbag2, full VLP-16 geometry) with its ground truth."""
    from gft_odom.sim.writer import simulate_to_bag
    out = tmp_path_factory.mktemp('orchard')
    return simulate_to_bag(out, scenario='row', n_scans=15, seed=3, topdown_png=False)
