"""The package's Python logging forwarded to the node's ROS logger, and given back."""

from __future__ import annotations

import logging

import pytest

pytestmark = [pytest.mark.ros]


class _RosLogger:
    def get_effective_level(self):
        from rclpy.logging import LoggingSeverity
        return LoggingSeverity.WARN


@pytest.mark.parametrize('order', ['first in, first out', 'last in, first out'])
def test_two_nodes_in_one_process_give_the_logger_back_as_it_was(order):
    from gft_odom.ros.log_bridge import forward_python_logging, stop_forwarding
    logger = logging.getLogger('gft_odom.bridge_test')
    logger.setLevel(logging.DEBUG)
    logger.propagate = True
    first = forward_python_logging(_RosLogger(), 5.0, name='gft_odom.bridge_test')
    second = forward_python_logging(_RosLogger(), 5.0, name='gft_odom.bridge_test')
    assert logger.level == logging.WARNING and not logger.propagate
    handlers = (first, second) if order.startswith('first') else (second, first)
    stop_forwarding(handlers[0])
    assert not logger.propagate  # the other node still forwards
    stop_forwarding(handlers[1])
    assert logger.level == logging.DEBUG and logger.propagate and not logger.handlers
