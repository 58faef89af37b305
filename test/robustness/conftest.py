"""Hostile PointCloud2 messages for the node tests, and a small simulated drive to feed it.

`hostile_cases(previous, before_previous)` returns a table of (name, expected kind, message):
the kind is the counter the node must bump (`malformed`, `empty`, `degenerate`,
`out_of_order`, `clock_jump`). None of them may change the odometry. `previous` /
`before_previous` are the last two valid scans the node processed (for the repeated and
out-of-order stamps).
"""

from __future__ import annotations

import copy
from typing import Callable

import numpy as np
import pytest

HUGE_POINTS = 2_000_000


def _cloud(columns: dict, stamp_ns: int, frame_id: str = 'velodyne'):
    from gft_odom.io.pointcloud2 import encode_cloud
    from gft_odom.ros.conversions import blob_to_msg
    return blob_to_msg(encode_cloud(columns), stamp_ns, frame_id)


def _xyz(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {k: rng.uniform(-20.0, 20.0, n).astype(np.float32) for k in 'xyz'}


def _edit(msg, **changes):
    out = copy.deepcopy(msg)
    for name, value in changes.items():
        setattr(out, name, value)
    return out


def _with_field(msg, field_name: str, **changes):
    from sensor_msgs.msg import PointField
    out = copy.deepcopy(msg)
    fields = []
    for f in out.fields:
        g = PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
        if f.name == field_name:
            for key, value in changes.items():
                setattr(g, key, value)
        fields.append(g)
    out.fields = fields
    return out


def _without_field(msg, name: str):
    out = copy.deepcopy(msg)
    out.fields = [f for f in out.fields if f.name != name]
    return out


def make_hostile_cases(previous, before_previous) -> list[tuple[str, str, object]]:
    """40+ malformed, empty, degenerate and mis-stamped clouds (see the module docstring)."""
    from sensor_msgs.msg import PointField

    from gft_odom.ros.conversions import stamp_to_ns
    t_prev = stamp_to_ns(previous.header.stamp)
    t_new = t_prev + 50_000_000  # between the previous scan and the next valid one
    n = 1000
    base = _cloud(_xyz(n), t_new)  # a well-formed small cloud to break in many ways
    data = bytes(base.data)
    cases: list[tuple[str, str, object]] = []

    def add(name: str, kind: str, msg) -> None:
        cases.append((name, kind, msg))

    # -- missing / wrong fields --------------------------------------------------------------
    for axis in 'xyz':
        add(f'missing_{axis}', 'malformed', _without_field(base, axis))
    add('no_fields_at_all', 'malformed', _edit(base, fields=[]))
    for datatype in (PointField.UINT8, PointField.INT16, PointField.INT32, PointField.UINT32):
        add(f'x_datatype_{datatype}', 'malformed', _with_field(base, 'x', datatype=datatype))
    for datatype in (0, 9, 255):
        add(f'unknown_datatype_{datatype}', 'malformed',
            _with_field(base, 'y', datatype=datatype))
    add('x_count_0', 'malformed', _with_field(base, 'x', count=0))
    add('x_count_3', 'malformed', _with_field(base, 'z', count=3))
    add('duplicate_field', 'malformed', _edit(base, fields=list(base.fields) + [
        PointField(name='x', offset=0, datatype=PointField.FLOAT32, count=1)]))
    add('empty_field_name', 'malformed', _with_field(base, 'z', name=''))
    add('field_offset_beyond_point', 'malformed', _with_field(base, 'z', offset=1000))
    add('field_offset_uint32_max', 'malformed', _with_field(base, 'x', offset=2**32 - 1))
    # -- sizes that do not add up ------------------------------------------------------------
    add('truncated_half', 'malformed', _edit(base, data=data[:len(data) // 2]))
    add('truncated_one_byte', 'malformed', _edit(base, data=data[:-1]))
    add('no_data_but_1000_points', 'malformed', _edit(base, data=b''))
    add('width_2e9', 'malformed', _edit(base, width=2_000_000_000, row_step=12 * 2_000_000_000
                                        % 2**32))
    add('width_height_1e10', 'malformed', _edit(base, width=100_000, height=100_000,
                                                row_step=1_200_000))
    add('height_16_data_for_1', 'malformed', _edit(base, height=16))
    add('point_step_8_fields_12', 'malformed', _edit(base, point_step=8, row_step=8 * n))
    add('point_step_0', 'malformed', _edit(base, point_step=0, row_step=0))
    add('row_step_too_small', 'malformed', _edit(base, row_step=12 * n - 1))
    add('row_step_uint32_max', 'malformed', _edit(base, row_step=2**32 - 1))
    bad_stamp = copy.deepcopy(base)
    bad_stamp.header.stamp.nanosec = 2_000_000_000
    add('nanosec_2e9', 'malformed', bad_stamp)
    # -- no usable point -----------------------------------------------------------------------
    add('width_0', 'empty', _edit(base, width=0, row_step=0, data=b''))
    add('height_0_width_1000', 'empty', _edit(base, height=0, row_step=12 * n, data=b''))
    nan_cols = _xyz(n)
    nan_cols['x'][:] = np.nan
    add('all_x_nan', 'empty', _cloud(nan_cols, t_new))
    inf_cols = _xyz(n)
    inf_cols['z'][:] = np.inf
    add('all_z_inf', 'empty', _cloud(inf_cols, t_new))
    mixed = _xyz(n)
    mixed['x'][::3], mixed['y'][1::3], mixed['z'][2::3] = np.nan, np.inf, -np.inf
    add('nan_inf_mixture', 'empty', _cloud(mixed, t_new))
    nan64 = {k: np.full(n, np.nan) for k in 'xyz'}  # float64 fields, all NaN
    add('all_nan_float64', 'empty', _cloud(nan64, t_new))
    # -- degenerate content --------------------------------------------------------------------
    add('all_points_identical', 'degenerate',
        _cloud({k: np.full(n, 5.0, np.float32) for k in 'xyz'}, t_new))
    add('all_points_at_origin', 'degenerate',
        _cloud({k: np.zeros(n, np.float32) for k in 'xyz'}, t_new))
    add('single_point', 'degenerate', _cloud({k: np.ones(1, np.float32) for k in 'xyz'}, t_new))
    one_and_nans = {k: np.full(n, np.nan, np.float32) for k in 'xyz'}
    for k in 'xyz':
        one_and_nans[k][7] = 3.0
    add('one_finite_point_among_nans', 'degenerate', _cloud(one_and_nans, t_new))
    # -- stamps ----------------------------------------------------------------------------------
    add('repeated_stamp_copy', 'out_of_order', copy.deepcopy(previous))
    add('older_stamp_copy', 'out_of_order', copy.deepcopy(before_previous))
    add('stamp_zero', 'out_of_order', _cloud(_xyz(n, 1), 0))
    add('stamp_one_ns_before', 'out_of_order', _cloud(_xyz(n, 2), t_prev - 1))
    add('repeated_stamp_other_frame', 'out_of_order', _cloud(_xyz(n, 3), t_prev, 'ouster'))
    # A lone stamp an hour ahead: held back, then dropped when the next scan continues the clock.
    add('stamp_one_hour_ahead', 'clock_jump', _cloud(_xyz(n, 6), t_prev + 3600 * 10**9))
    # Big clouds with the previous stamp: decoded, then refused. Over best-effort DDS the
    # 2-million-point one (~24 MB) is usually lost in transport; 300 k points (3.6 MB) arrive.
    add('300k_points_repeated_stamp', 'out_of_order', _cloud(_xyz(300_000, 5), t_prev))
    add('two_million_points_repeated_stamp', 'out_of_order',
        _cloud(_xyz(HUGE_POINTS, 4), t_prev))
    return cases


@pytest.fixture(scope='session')
def hostile_cases() -> Callable:
    return make_hostile_cases


@pytest.fixture(scope='session')
def small_drive(tmp_path_factory):
    """A short simulated drive at half the VLP-16 azimuth resolution (cheap, still a scene)."""
    from gft_odom.sim.simulator import SimConfig
    from gft_odom.sim.writer import simulate_to_bag
    out = tmp_path_factory.mktemp('robust_drive')
    return simulate_to_bag(out, scenario='row', n_scans=10, seed=21,
                           config=SimConfig(azimuth_step_deg=0.4), topdown_png=False)


@pytest.fixture(scope='session')
def drive_messages(small_drive) -> list:
    """The drive's scans as rclpy PointCloud2 messages, bytes as recorded."""
    from gft_odom.io.bags import ScanBagReader
    from gft_odom.ros.through_node import ros_message_from_bag
    with ScanBagReader([small_drive.bag_path]) as reader:
        return [ros_message_from_bag(raw)
                for _, raw in reader.iter_messages()]
