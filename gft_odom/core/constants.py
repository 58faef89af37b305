"""Constants every layer shares: time units, the VLP-16 sweep period, the node's name."""

from __future__ import annotations

NS_PER_S = 1_000_000_000
# A VLP-16 spins at 10 Hz: one sweep, one scan, every 0.1 s.
SCAN_PERIOD_S = 0.1
# The ROS node's name: params files address it (`filter_odom_node: ros__parameters: ...`).
NODE_NAME = 'filter_odom_node'


def sec_nanosec_to_ns(sec: int, nanosec: int) -> int:
    """A ROS stamp's (sec, nanosec) -> int nanoseconds, exact (no float on the way)."""
    return int(sec) * NS_PER_S + int(nanosec)


def ns_to_sec_nanosec(stamp_ns: int) -> tuple[int, int]:
    """Int nanoseconds -> a ROS stamp's (sec, nanosec), nanosec in [0, 1e9)."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return sec, nanosec
