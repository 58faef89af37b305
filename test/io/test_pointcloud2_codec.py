"""The PointCloud2 codec: exact round trips, independent byte-level oracles, hostile input."""

from __future__ import annotations

import array
import struct
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import velodyne_columns
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gft_odom.core.types import Scan
from gft_odom.errors import CodecError
from gft_odom.io.pointcloud2 import (
    DATATYPE_CODES,
    FLOAT32,
    FLOAT64,
    INT32,
    UINT8,
    UINT16,
    VELODYNE_XYZIR_ROS1,
    VELODYNE_XYZIRT,
    XYZ_FLOAT32,
    XYZ_FLOAT64,
    CloudBlob,
    CloudLayout,
    FieldSpec,
    decode_fields,
    decode_scan,
    encode_cloud,
    encode_scan,
    layout_for_columns,
)

STAMP_NS = 1_700_000_000_123_456_789


def as_msg(blob: CloudBlob, stamp_ns: int = STAMP_NS, frame_id: str = 'velodyne', **override):
    """A duck-typed PointCloud2 (the codec must not care about the concrete class)."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    attrs = dict(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec),
                               frame_id=frame_id),
        height=blob.height, width=blob.width,
        fields=[SimpleNamespace(name=f.name, offset=f.offset, datatype=f.datatype,
                                count=f.count) for f in blob.fields],
        is_bigendian=blob.is_bigendian, point_step=blob.point_step, row_step=blob.row_step,
        data=blob.data, is_dense=blob.is_dense)
    attrs.update(override)
    return SimpleNamespace(**attrs)


# --- independent oracle: bytes packed with `struct`, not with the codec -----------------------

def test_decodes_velodyne_xyzirt_bytes_packed_by_struct():
    cols = velodyne_columns(50)
    record = struct.Struct('<ffffHf')
    assert record.size == VELODYNE_XYZIRT.point_step == 22
    data = b''.join(record.pack(*(cols[k][i].item() for k in
                                  ('x', 'y', 'z', 'intensity', 'ring', 'time')))
                    for i in range(50))
    blob = CloudBlob(VELODYNE_XYZIRT.fields, 22, 22 * 50, 1, 50, False, True, data)
    scan = decode_scan(as_msg(blob))
    np.testing.assert_array_equal(scan.points_xyz,
                                  np.column_stack([cols['x'], cols['y'], cols['z']]))
    np.testing.assert_array_equal(scan.intensity, cols['intensity'])
    np.testing.assert_array_equal(scan.ring, cols['ring'])
    np.testing.assert_array_equal(scan.time_offset_s, cols['time'])
    assert scan.stamp_ns == STAMP_NS and scan.frame_id == 'velodyne'
    assert scan.points_xyz.dtype == np.float64 and scan.ring.dtype == np.uint16
    # and the encoder writes exactly those bytes
    assert encode_cloud(cols, VELODYNE_XYZIRT).data == data


def test_decodes_citrusfarm_xyzir_big_endian_organized_with_row_padding():
    """PointXYZIR (32-byte points, padding after z), big-endian, 2 rows of 3, 7 pad bytes."""
    cols = velodyne_columns(6, seed=1)
    cols['x'][4] = np.nan  # a no-return in an organized cloud
    record = struct.Struct('>fff4xfH10x')
    assert record.size == VELODYNE_XYZIR_ROS1.point_step == 32
    rows = []
    for r in range(2):
        pts = [record.pack(*(cols[k][3 * r + c].item() for k in
                             ('x', 'y', 'z', 'intensity', 'ring'))) for c in range(3)]
        rows.append(b''.join(pts) + b'\xab' * 7)
    blob = CloudBlob(VELODYNE_XYZIR_ROS1.fields, 32, 3 * 32 + 7, 2, 3, True, False,
                     b''.join(rows))
    fields = decode_fields(as_msg(blob))
    np.testing.assert_array_equal(fields['x'], cols['x'])  # NaN compares equal here
    np.testing.assert_array_equal(fields['ring'], cols['ring'])
    scan = decode_scan(as_msg(blob))
    keep = np.arange(6) != 4
    assert len(scan) == 5
    np.testing.assert_array_equal(scan.points_xyz[:, 1], cols['y'][keep])
    np.testing.assert_array_equal(scan.intensity, cols['intensity'][keep])
    assert scan.time_offset_s is None  # CitrusFarm has no per-point time
    # the encoder writes the same bytes (its padding is zeros)
    zero_padded = b''.join(row[:-7] + b'\0' * 7 for row in rows)
    assert encode_cloud(cols, VELODYNE_XYZIR_ROS1, height=2, is_bigendian=True,
                        row_padding_bytes=7).data == zero_padded


# --- property: anything encoded decodes to the same values -------------------------------------

DTYPES = [np.int8, np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.float32, np.float64]


@st.composite
def clouds(draw):
    """Random columns (x, y, z float + extras of any type/count), random layout and shape."""
    height = draw(st.integers(1, 4))
    width = draw(st.integers(0, 12))
    n = height * width
    xyz_dtype = draw(st.sampled_from([np.float32, np.float64]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    columns = {k: rng.normal(0, 50, n).astype(xyz_dtype) for k in 'xyz'}
    if n:
        bad = rng.random(n) < draw(st.sampled_from([0.0, 0.3]))
        columns[draw(st.sampled_from('xyz'))][bad] = draw(st.sampled_from([np.nan, np.inf]))
    for i in range(draw(st.integers(0, 3))):
        dtype = np.dtype(draw(st.sampled_from(DTYPES)))
        count = draw(st.integers(1, 3))
        shape = (n,) if count == 1 else (n, count)
        if dtype.kind == 'f':
            values = rng.normal(0, 1e3, shape).astype(dtype)
        else:
            info = np.iinfo(dtype)
            values = rng.integers(info.min, info.max, shape, dtype=dtype, endpoint=True)
        columns[f'extra{i}'] = values
    names = draw(st.permutations(list(columns)))
    columns = {k: columns[k] for k in names}
    layout = None
    if draw(st.booleans()):  # a layout with gaps between fields and a longer point_step
        fields, offset = [], 0
        for name, values in columns.items():
            offset += draw(st.integers(0, 5))
            datatype = layout_for_columns({name: values}).fields[0].datatype
            spec = FieldSpec(name, offset, datatype, 1 if values.ndim == 1 else values.shape[1])
            fields.append(spec)
            offset += spec.size_bytes
        layout = CloudLayout(tuple(fields), offset + draw(st.integers(0, 9)))
    options = dict(height=height, is_bigendian=draw(st.booleans()),
                   row_padding_bytes=draw(st.integers(0, 11)))
    return columns, layout, options


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(clouds())
def test_round_trip_any_layout_shape_and_byte_order(cloud):
    columns, layout, options = cloud
    blob = encode_cloud(columns, layout, **options)
    assert blob.height * blob.width == columns['x'].shape[0]
    assert len(blob.data) == blob.row_step * blob.height
    decoded = decode_fields(as_msg(blob))
    assert list(decoded) == list(columns)
    for name, values in columns.items():
        assert decoded[name].dtype == values.dtype.newbyteorder('=')
        np.testing.assert_array_equal(decoded[name], values)
    scan = decode_scan(as_msg(blob))
    xyz = np.column_stack([columns[k].astype(np.float64) for k in 'xyz'])
    finite = np.isfinite(xyz).all(axis=1)
    np.testing.assert_array_equal(scan.points_xyz, xyz[finite])
    assert blob.is_dense == bool(finite.all())


def test_encode_scan_round_trip_in_both_velodyne_layouts():
    cols = velodyne_columns(100, seed=3)
    scan = Scan(42, np.column_stack([cols['x'], cols['y'], cols['z']]).astype(np.float64),
                cols['intensity'], cols['ring'], cols['time'], 'lidar')
    back = decode_scan(as_msg(encode_scan(scan), stamp_ns=42, frame_id='lidar'))
    np.testing.assert_array_equal(back.points_xyz, scan.points_xyz)
    np.testing.assert_array_equal(back.time_offset_s, scan.time_offset_s)
    ros1 = decode_scan(as_msg(encode_scan(scan, VELODYNE_XYZIR_ROS1)))
    np.testing.assert_array_equal(ros1.ring, scan.ring)
    assert ros1.time_offset_s is None
    packed = encode_scan(scan, layout=None)
    assert packed.point_step == 3 * 4 + 4 + 2 + 4
    np.testing.assert_array_equal(decode_scan(as_msg(packed)).intensity, scan.intensity)


def test_layout_missing_columns_are_zero_and_xyz64_layout_keeps_precision():
    xyz = {'x': np.array([1e6 + 0.001]), 'y': np.array([2.0]), 'z': np.array([3.0])}
    fields = decode_fields(as_msg(encode_cloud(xyz, VELODYNE_XYZIRT)))
    assert fields['ring'].tolist() == [0] and fields['time'].tolist() == [0.0]
    exact = decode_scan(as_msg(encode_cloud(xyz, XYZ_FLOAT64)))
    assert exact.points_xyz[0, 0] == 1e6 + 0.001
    assert decode_scan(as_msg(encode_cloud(xyz, XYZ_FLOAT32))).points_xyz[0, 0] != 1e6 + 0.001


def test_packed_layout_for_filtered_output_columns():
    n = 5
    columns = {**{k: np.zeros(n, np.float32) for k in ('x', 'y', 'z', 'intensity')},
               'frequency': np.linspace(0, 1, n, dtype=np.float32),
               'band': np.arange(n, dtype=np.uint8)}
    blob = encode_cloud(columns)
    assert [(f.name, f.offset, f.datatype) for f in blob.fields] == [
        ('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), ('intensity', 12, FLOAT32),
        ('frequency', 16, FLOAT32), ('band', 20, UINT8)]
    assert blob.point_step == 21 and blob.row_step == 21 * n
    np.testing.assert_array_equal(decode_fields(as_msg(blob))['band'], columns['band'])


@pytest.mark.parametrize('container', [bytes, bytearray, memoryview,
                                       lambda b: array.array('B', b),
                                       lambda b: np.frombuffer(b, np.uint8),
                                       lambda b: list(b)])
def test_data_containers_decode_alike(container):
    cols = velodyne_columns(20)
    blob = encode_cloud(cols, VELODYNE_XYZIRT)
    scan = decode_scan(as_msg(blob, data=container(blob.data)))
    np.testing.assert_array_equal(scan.time_offset_s, cols['time'])


def test_empty_cloud_decodes_to_empty_arrays():
    blob = encode_cloud({k: np.zeros(0, np.float32) for k in 'xyz'}, VELODYNE_XYZIRT)
    assert blob.width == 0 and blob.data == b''
    fields = decode_fields(as_msg(blob))
    assert set(fields) == set(VELODYNE_XYZIRT.names)
    assert all(v.shape == (0,) for v in fields.values())
    scan = decode_scan(as_msg(blob))
    assert len(scan) == 0 and scan.points_xyz.shape == (0, 3)
    # width 0 with a stale height, and height 0 with a width: still empty, not an error
    assert len(decode_scan(as_msg(blob, height=5, width=0, row_step=0))) == 0
    assert len(decode_scan(as_msg(blob, height=0, width=7))) == 0


def test_ouster_style_integer_t_field_becomes_seconds():
    cols = {'x': np.ones(3, np.float32), 'y': np.ones(3, np.float32),
            'z': np.ones(3, np.float32), 't': np.array([0, 50_000_000, 99_000_000], np.uint32)}
    scan = decode_scan(as_msg(encode_cloud(cols)))
    np.testing.assert_allclose(scan.time_offset_s, [0.0, 0.05, 0.099], rtol=1e-6)


# --- the same bytes as rosbags messages (ROS 1 and ROS 2) and as an rclpy message --------------

def _rosbags_msg(store_name: str, blob: CloudBlob):
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(getattr(Stores, store_name))
    t = store.types
    sec, nanosec = divmod(STAMP_NS, 1_000_000_000)
    header_kwargs = dict(stamp=t['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
                         frame_id='velodyne')
    if store_name == 'ROS1_NOETIC':
        header_kwargs['seq'] = 7
    msg = t['sensor_msgs/msg/PointCloud2'](
        header=t['std_msgs/msg/Header'](**header_kwargs), height=blob.height, width=blob.width,
        fields=[t['sensor_msgs/msg/PointField'](name=f.name, offset=f.offset,
                                                datatype=f.datatype, count=f.count)
                for f in blob.fields],
        is_bigendian=blob.is_bigendian, point_step=blob.point_step, row_step=blob.row_step,
        data=np.frombuffer(blob.data, np.uint8), is_dense=blob.is_dense)
    # through the wire format and back, as a bag reader would see it
    if store_name == 'ROS1_NOETIC':
        raw = store.serialize_ros1(msg, 'sensor_msgs/msg/PointCloud2')
        return store.deserialize_ros1(raw, 'sensor_msgs/msg/PointCloud2')
    raw = store.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2')
    return store.deserialize_cdr(raw, 'sensor_msgs/msg/PointCloud2')


def _assert_same_scan(a: Scan, b: Scan) -> None:
    assert a.stamp_ns == b.stamp_ns and a.frame_id == b.frame_id
    np.testing.assert_array_equal(a.points_xyz, b.points_xyz)
    for name in ('intensity', 'ring', 'time_offset_s'):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@pytest.mark.parametrize('layout', [VELODYNE_XYZIRT, VELODYNE_XYZIR_ROS1])
def test_rosbags_ros1_and_ros2_messages_decode_the_same(layout):
    cols = velodyne_columns(64, seed=5)
    cols['z'][3] = np.nan
    blob = encode_cloud(cols, layout, height=4)
    reference = decode_scan(as_msg(blob))
    assert len(reference) == 63
    for store_name in ('ROS1_NOETIC', 'ROS2_JAZZY'):
        _assert_same_scan(decode_scan(_rosbags_msg(store_name, blob)), reference)


def test_rclpy_message_decodes_the_same_as_rosbags():
    try:
        import sensor_msgs.msg  # noqa: F401

        from gft_odom.ros.conversions import blob_to_msg
    except ImportError as exc:  # pragma: no cover - only without the ROS wheels
        pytest.skip(f'rclpy message packages not importable: {exc}')
    cols = velodyne_columns(64, seed=6)
    blob = encode_cloud(cols, VELODYNE_XYZIRT, height=2, row_padding_bytes=3)
    msg = blob_to_msg(blob, STAMP_NS, 'velodyne')
    assert isinstance(msg.data, array.array)
    _assert_same_scan(decode_scan(msg), decode_scan(_rosbags_msg('ROS2_JAZZY', blob)))


# --- every malformed message is a CodecError with its reason -----------------------------------

def _good_blob() -> CloudBlob:
    return encode_cloud(velodyne_columns(10), VELODYNE_XYZIRT)


def _fields(*specs):
    return [SimpleNamespace(name=n, offset=o, datatype=d, count=c) for n, o, d, c in specs]


XYZ = [('x', 0, FLOAT32, 1), ('y', 4, FLOAT32, 1), ('z', 8, FLOAT32, 1)]

INVALID = {
    'missing z': (dict(fields=_fields(*XYZ[:2])), 'lacks field'),
    'data shorter than row_step*height': (dict(data=b'\0' * 219), 'fewer than row_step'),
    'row_step < point_step*width': (dict(row_step=21 * 10), 'row_step'),
    'field beyond point_step': (dict(fields=_fields(*XYZ, ('time', 20, FLOAT32, 1))),
                                'beyond point_step'),
    'unknown datatype 9': (dict(fields=_fields(*XYZ, ('i', 12, 9, 1))), 'unknown datatype'),
    'unknown datatype 0': (dict(fields=_fields(('x', 0, 0, 1), *XYZ[1:])), 'unknown datatype'),
    'count 0': (dict(fields=_fields(*XYZ, ('i', 12, FLOAT32, 0))), 'count'),
    'absurd width*height': (dict(width=2**24, height=2**24, row_step=22 * 2**24),
                            'fewer than row_step'),
    'width overflowing row_step': (dict(width=2**32 - 1, height=2**32 - 1), 'row_step 220 <'),
    'absurd row_step': (dict(row_step=2**32 - 1), 'fewer than row_step'),
    'negative width': (dict(width=-1), 'width'),
    'float height': (dict(height=1.0), 'height'),
    'string point_step': (dict(point_step='22'), 'point_step'),
    'negative field offset': (dict(fields=_fields(('x', -4, FLOAT32, 1), *XYZ[1:])), 'offset'),
    'integer x': (dict(fields=_fields(('x', 0, INT32, 1), *XYZ[1:])), 'float32/float64'),
    'x with count 3': (dict(fields=_fields(('x', 0, FLOAT32, 3), *XYZ[1:])), 'count 3'),
    'duplicate field': (dict(fields=_fields(*XYZ, ('x', 12, FLOAT32, 1))), 'twice'),
    'data is text': (dict(data='not bytes' * 100), 'unsupported type'),
    'data list out of byte range': (dict(data=[300] * 220), 'byte values'),
    'field table not a list': (dict(fields=5), 'field table'),
    'field without datatype': (dict(fields=[SimpleNamespace(name='x', offset=0, count=1)]),
                               'not a PointField'),
    'is_bigendian not bool': (dict(is_bigendian='yes'), 'is_bigendian'),
    'nanosec out of range': (dict(header=SimpleNamespace(
        stamp=SimpleNamespace(sec=1, nanosec=1_000_000_000), frame_id='v')), 'nanosec'),
    'no header': (dict(header=None), 'header'),
}


@pytest.mark.parametrize('case', sorted(INVALID))
def test_invalid_message_raises_codec_error_with_reason(case):
    override, reason = INVALID[case]
    msg = as_msg(_good_blob(), **override)
    with pytest.raises(CodecError, match=reason):
        decode_scan(msg)


def test_not_a_message_at_all():
    with pytest.raises(CodecError):
        decode_scan(object())
    with pytest.raises(CodecError):
        decode_fields(SimpleNamespace(fields=[]))


@pytest.mark.parametrize('bad', [
    dict(columns={'x': np.zeros(3, np.int64)}, layout=None),
    dict(columns={'x': np.zeros(3, bool)}, layout=None),
    dict(columns={'x': np.zeros(3, np.float32), 'y': np.zeros(4, np.float32)}, layout=None),
    dict(columns={'x': np.zeros((3, 2, 2), np.float32)}, layout=None),
    dict(columns={'x': np.zeros(5, np.float32)}, layout=XYZ_FLOAT32, height=2),
    dict(columns={'x': np.zeros((5, 2), np.float32)}, layout=XYZ_FLOAT32),
])
def test_encode_rejects_what_pointcloud2_cannot_hold(bad):
    with pytest.raises(CodecError):
        encode_cloud(bad.pop('columns'), bad.pop('layout'), **bad)


def test_layout_is_checked_when_made():
    with pytest.raises(CodecError, match='beyond point_step'):
        CloudLayout((FieldSpec('x', 0, FLOAT64),), 4)
    with pytest.raises(CodecError, match='unknown datatype'):
        CloudLayout((FieldSpec('x', 0, 11),), 8)


# --- fuzz: hostile field tables and bytes never crash, hang or allocate wildly ------------------

@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(['x', 'y', 'z', 'ring', 'time', 'i']),
                          st.integers(-2, 40), st.integers(-1, 10), st.integers(-1, 4)),
                max_size=6),
       st.integers(-1, 2**32 + 1), st.integers(-1, 2**32 + 1), st.integers(-1, 64),
       st.integers(-1, 2**32 + 1), st.booleans(), st.binary(max_size=512))
def test_fuzzed_messages_decode_or_raise_codec_error(fields, height, width, point_step,
                                                     row_step, big_endian, data):
    msg = SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=2), frame_id='f'),
        fields=_fields(*fields), height=height, width=width, point_step=point_step,
        row_step=row_step, is_bigendian=big_endian, data=data, is_dense=False)
    try:
        scan = decode_scan(msg)
    except CodecError:
        return
    assert scan.points_xyz.shape[0] <= max(width * height, 0)
    assert np.isfinite(scan.points_xyz).all()
    assert scan.points_xyz.shape[0] * point_step <= len(data)


def test_datatype_table_matches_the_message_definition():
    """Our constants against sensor_msgs/PointField's own, sizes against numpy's."""
    from rosbags.typesys import Stores, get_typestore
    point_field = get_typestore(Stores.ROS2_JAZZY).types['sensor_msgs/msg/PointField']
    for name, value in (('INT8', 1), ('UINT8', UINT8), ('UINT16', UINT16), ('INT32', INT32),
                        ('FLOAT32', FLOAT32), ('FLOAT64', FLOAT64)):
        assert getattr(point_field, name) == value
    for datatype, code in DATATYPE_CODES.items():
        name = {'i': 'INT', 'u': 'UINT', 'f': 'FLOAT'}[code[0]] + str(8 * np.dtype(code).itemsize)
        assert getattr(point_field, name) == datatype
