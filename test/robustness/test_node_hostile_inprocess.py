"""FilterOdomNode's callback fed 40+ hostile clouds in-process: one warning each, no effect.

The same callback runs in the colcon-built node (test_node_hostile_dds.py checks that over DDS);
here every message is handed to `_on_cloud` directly so each one's warning can be checked.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from gft_odom.config import GftOdomConfig
from gft_odom.io.pointcloud2 import (
    CloudLayout,
    FieldSpec,
    decode_fields,
    decode_scan,
    encode_cloud,
)
from gft_odom.pipeline import OdometryPipeline

pytestmark = [pytest.mark.ros]

SPARSE_POINTS = 60  # below registration.min_points (100): the motion prediction is used


def with_nan_inf(msg, every: int = 7):
    """A valid scan in which every `every`-th point has a NaN/Inf coordinate (no-returns)."""
    from gft_odom.ros.conversions import blob_to_msg, stamp_to_ns
    columns = decode_fields(msg)
    columns['x'][::every] = np.nan
    columns['y'][3::every] = np.inf
    columns['z'][5::every] = -np.inf
    layout = CloudLayout(tuple(FieldSpec(f.name, f.offset, f.datatype, f.count)
                               for f in msg.fields), msg.point_step)
    return blob_to_msg(encode_cloud(columns, layout), stamp_to_ns(msg.header.stamp),
                       msg.header.frame_id)


def sparse(msg, n: int = SPARSE_POINTS):
    """The same scan thinned to `n` points: too few to register."""
    from gft_odom.ros.conversions import blob_to_msg, stamp_to_ns
    columns = {k: v[::max(1, v.shape[0] // n)][:n] for k, v in decode_fields(msg).items()}
    return blob_to_msg(encode_cloud(columns), stamp_to_ns(msg.header.stamp),
                       msg.header.frame_id)


def valid_sequence(messages: list) -> list:
    """The drive with three awkward-but-valid scans: NaN/Inf holes, a new frame_id, sparse."""
    out = list(messages)
    out[3] = with_nan_inf(out[3])
    out[5] = copy.deepcopy(out[5])
    out[5].header.frame_id = 'velodyne_top'  # warned about, processed as the same sensor
    out[7] = sparse(out[7])
    return out


def interleave(valid: list, hostile_cases) -> list[tuple[str, str | None, object]]:
    """(name, expected kind or None for valid, message): hostile batches between valid scans."""
    schedule = [('valid_0', None, valid[0]), ('valid_1', None, valid[1])]
    batches = []
    for i in range(2, len(valid)):
        batches.append(hostile_cases(valid[i - 1], valid[i - 2]))
    n_batches = len(batches)
    all_names = [name for name, _, _ in batches[0]]
    for i, cases in enumerate(batches, start=2):
        # Each batch carries its share of the table, with stamps relative to its own scans.
        share = [c for j, c in enumerate(cases) if j % n_batches == i - 2]
        schedule.extend(share)
        schedule.append((f'valid_{i}', None, valid[i]))
    assert sorted(n for n, k, _ in schedule if k) == sorted(all_names)
    return schedule


@pytest.fixture
def node_in_process():
    import rclpy
    from rclpy.parameter import Parameter

    from gft_odom.ros.node import FilterOdomNode
    context = rclpy.Context()
    rclpy.init(context=context)
    # Sim time without a /clock: the clock reads 0 and the lag check is skipped (bag stamps).
    node = FilterOdomNode(context=context, parameter_overrides=[
        Parameter('use_sim_time', Parameter.Type.BOOL, True)])
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_hostile_clouds_warn_once_each_and_leave_odometry_alone(node_in_process, drive_messages,
                                                                hostile_cases, monkeypatch):
    import gft_odom.ros.node as node_module
    monkeypatch.setattr(node_module, 'WARN_PERIOD_S', 1e6)  # the run must fit in one period
    node = node_in_process
    valid = valid_sequence(drive_messages)
    schedule = interleave(valid, hostile_cases)
    n_hostile = sum(kind is not None for _, kind, _ in schedule)
    assert n_hostile >= 40

    warned: list[tuple[str, str]] = []
    published = []
    logged: list[str] = []
    real_warn, real_publish = node._warn, node._publish
    logger = node.get_logger()
    real_log_warning = logger.warning
    node._warn = lambda kind, text: (warned.append((kind, text)), real_warn(kind, text))
    node._publish = lambda result, header: (published.append(result),
                                            real_publish(result, header))[1]
    logger.warning = lambda text, **kw: (logged.append(text), real_log_warning(text, **kw))

    for name, kind, msg in schedule:
        before_w, before_p = len(warned), len(published)
        node._on_cloud(msg)  # must never raise
        new_kinds = [k for k, _ in warned[before_w:]]
        if kind is None:
            assert len(published) == before_p + 1, f'{name}: valid scan not processed'
        else:
            assert len(published) == before_p, f'{name}: hostile cloud was processed'
            assert new_kinds == [kind], f'{name}: warnings {warned[before_w:]}'
            assert warned[-1][1].strip(), name

    # Valid scans: the same odometry as a pipeline that never saw the hostile clouds.
    reference = OdometryPipeline(GftOdomConfig(), record_trajectory=False)
    expected = [reference.register_frame(decode_scan(m)) for m in valid]
    assert [r.stamp_ns for r in published] == [r.stamp_ns for r in expected]
    for got, want in zip(published, expected):
        np.testing.assert_allclose(got.T_odom_base, want.T_odom_base, atol=1e-9)
        assert got.status == want.status
    # The NaN/Inf holes were dropped, the rest of that scan used.
    n_original = len(decode_scan(drive_messages[3]))
    holes = np.isin(np.arange(n_original) % 7, (0, 3, 5)).sum()
    assert published[3].n_points_in == n_original - holes
    # The sparse scan: motion prediction, inflated covariance, counted.
    sparse_result = published[7]
    assert sparse_result.status == 'fallback_too_few_points'
    fallback_var = GftOdomConfig().registration.fallback_std_m ** 2
    assert np.all(np.diag(sparse_result.covariance)[:3] >= fallback_var - 1e-12)
    assert np.all(np.diag(published[6].covariance)[:3] < fallback_var)
    assert node.counters['fallback'] == 1
    # frame_id change: warned (to and back), processed.
    assert node.counters['frame_changed'] == 2
    # Counters add up; the log got at most one line per kind (all within WARN_PERIOD_S).
    kinds = {kind for _, kind, _ in schedule if kind}
    for kind in kinds:
        assert node.counters[kind] == sum(k == kind for _, k, _ in schedule)
    assert node.counters['processed'] == len(valid)
    assert len(logged) == len({k for k, _ in warned})
    assert len(logged) < len(warned) / 4


def test_warnings_are_rate_limited_per_kind(node_in_process, drive_messages, hostile_cases,
                                            monkeypatch):
    import gft_odom.ros.node as node_module
    node = node_in_process
    logged: list[str] = []
    logger = node.get_logger()
    logger.warning = lambda text, **kw: logged.append(text)
    cases = {name: msg for name, _, msg in hostile_cases(drive_messages[1], drive_messages[0])}
    for _ in range(30):
        node._on_cloud(cases['missing_x'])
    node._on_cloud(cases['width_0'])  # another kind is not silenced by the first
    assert len(logged) == 2
    assert 'lacks field' in logged[0] and "'x'" in logged[0]
    assert 'malformed so far: 1' in logged[0]
    assert 'empty' in logged[1]
    # After the period the next one is logged again, with the running count.
    now = node_module.time.monotonic()
    monkeypatch.setattr(node_module.time, 'monotonic', lambda: now + node_module.WARN_PERIOD_S)
    node._on_cloud(cases['missing_y'])
    assert len(logged) == 3 and 'malformed so far: 31' in logged[2]
