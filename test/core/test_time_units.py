"""Per-point time in s, ms, us, ns (relative, either sign) or absolute: the unit is found from
the values and deskew undoes a known motion distortion with each."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gft_odom.core.deskew import deskew_points, time_offsets_from_field
from gft_odom.core.geometry import make_transform
from gft_odom.io.pointcloud2 import CloudBlob, decode_scan, encode_cloud

STAMP_NS = 1_700_000_000_123_456_789
PERIOD_S = 0.1
SPEED_MPS, YAW_RATE_RPS = 2.0, 0.8  # the Jackal at full speed, turning


def as_msg(blob: CloudBlob, stamp_ns: int = STAMP_NS) -> SimpleNamespace:
    """A duck-typed PointCloud2 around `blob`."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec),
                               frame_id='velodyne'),
        height=blob.height, width=blob.width, fields=list(blob.fields),
        is_bigendian=blob.is_bigendian, point_step=blob.point_step, row_step=blob.row_step,
        data=blob.data, is_dense=blob.is_dense)


def distorted_sweep(stamp_at_end: bool, n: int = 4000, seed: int = 0):
    """Static world points seen by a sensor moving at a constant twist during one sweep.

    Returns (measured points, offsets from the stamp in s, points in the frame at the stamp,
    the motion over one period)."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform([-30.0, -30.0, -1.0], [30.0, 30.0, 4.0], (n, 3))
    offsets_s = np.linspace(0.0, PERIOD_S, n, endpoint=False)
    if stamp_at_end:
        offsets_s -= PERIOD_S
    twist = np.array([0.0, 0.0, YAW_RATE_RPS, SPEED_MPS, 0.0, 0.0])
    R = Rotation.from_rotvec(offsets_s[:, None] * twist[None, :3]).as_matrix()
    t = offsets_s[:, None] * twist[None, 3:]
    # p_stamp = R(s) p_s + t(s)  =>  p_s = R(s)^T (p_stamp - t(s))
    measured = np.einsum('nji,nj->ni', R, truth - t)
    delta = make_transform(Rotation.from_rotvec(twist[:3] * PERIOD_S).as_matrix(),
                           twist[3:] * PERIOD_S)
    return measured, offsets_s, truth, delta


# (unit name, values from offsets in s, dtype of the field)
ENCODINGS = {
    's': (lambda s: s, np.float32),
    'ms': (lambda s: s * 1e3, np.float32),
    'us': (lambda s: np.round(s * 1e6), np.float64),
    'ns': (lambda s: np.round(s * 1e9), np.float64),
    'absolute_s': (lambda s: STAMP_NS * 1e-9 + s, np.float64),
}


@pytest.mark.parametrize('stamp_at_end', [False, True], ids=['sweep_start', 'velodyne_end'])
@pytest.mark.parametrize('unit', list(ENCODINGS))
def test_time_unit_is_detected_and_deskew_is_right(unit, stamp_at_end):
    measured, offsets_s, truth, delta = distorted_sweep(stamp_at_end)
    encode, dtype = ENCODINGS[unit]
    columns = {'x': measured[:, 0].astype(np.float32), 'y': measured[:, 1].astype(np.float32),
               'z': measured[:, 2].astype(np.float32), 'time': encode(offsets_s).astype(dtype)}
    scan = decode_scan(as_msg(encode_cloud(columns), STAMP_NS))
    got, found = time_offsets_from_field(columns['time'], STAMP_NS)
    assert found == unit
    np.testing.assert_allclose(scan.time_offset_s, offsets_s, atol=2e-6)
    before = np.linalg.norm(scan.points_xyz - truth, axis=1).max()
    fixed = deskew_points(scan.points_xyz, scan.time_offset_s, delta, PERIOD_S)
    after = np.linalg.norm(fixed - truth, axis=1).max()
    assert before > 0.15
    assert after < 5e-3, (unit, after)  # float32 coordinates at 30 m: ~2 mm


def test_ouster_uint32_t_field_in_ns():
    measured, offsets_s, truth, delta = distorted_sweep(stamp_at_end=False)
    columns = {'x': measured[:, 0].astype(np.float32), 'y': measured[:, 1].astype(np.float32),
               'z': measured[:, 2].astype(np.float32),
               't': np.round(offsets_s * 1e9).astype(np.uint32)}
    scan = decode_scan(as_msg(encode_cloud(columns), STAMP_NS))
    np.testing.assert_allclose(scan.time_offset_s, offsets_s, atol=1e-6)
    fixed = deskew_points(scan.points_xyz, scan.time_offset_s, delta, PERIOD_S)
    assert np.linalg.norm(fixed - truth, axis=1).max() < 5e-3


def test_absolute_nanoseconds_are_exact_in_integers():
    offsets_s = np.linspace(-0.1, 0.0, 100)
    values = (STAMP_NS + np.round(offsets_s * 1e9).astype(np.int64)).astype(np.uint64)
    got, unit = time_offsets_from_field(values, STAMP_NS)
    assert unit == 'absolute_ns'
    np.testing.assert_allclose(got, offsets_s, atol=1e-9)


def test_time_that_fits_no_unit_is_ignored_not_misread():
    got, unit = time_offsets_from_field(np.array([5e12, 6e12]), STAMP_NS)
    assert got is None and unit == 'unknown'
