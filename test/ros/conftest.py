"""DDS tests here publish full VLP-16 clouds best effort, as a driver does: like the README asks
of a driver, this process uses the packaged Fast DDS profile for large messages (with the 512 KB
default shared-memory segment about a quarter of such clouds is lost). Set before any
participant of the test session exists: Fast DDS reads it once per process."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(
    Path(__file__).resolve().parents[2] / 'config' / 'fastdds_large_messages.xml'))


@pytest.fixture(scope='session')
def orchard_messages(orchard_bag) -> list:
    """The first PointCloud2 messages of the orchard bag, as a driver publishes them."""
    from gft_odom.io.bags import ScanBagReader
    from gft_odom.ros.through_node import ros_message_from_bag
    with ScanBagReader([orchard_bag.bag_path]) as reader:
        return [ros_message_from_bag(raw) for _, raw in reader.iter_messages()][:8]
