"""sensor_msgs/PointCloud2 <-> numpy, driven by the message's field table.

Duck-typed: it reads anything with the PointCloud2 attributes (`fields` with `.name .offset
.datatype .count`, `height width point_step row_step is_bigendian is_dense data header`), so one
codec serves rclpy messages (data is `array.array('B')`) and rosbags messages of either ROS
version (data is a numpy uint8 array). `sensor_msgs_py.point_cloud2` asserts the rclpy type and
would reject the second kind. Decoding builds one structured numpy dtype from the field table
and views the byte buffer through it (strides honour `row_step`), so each field costs exactly
one vectorised copy into a native-endian array. Every malformed message raises `CodecError`
with the reason before anything large is allocated.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from gft_odom.core.constants import NS_PER_S, sec_nanosec_to_ns
from gft_odom.core.deskew import time_offsets_from_field
from gft_odom.core.types import Scan
from gft_odom.errors import CodecError

log = logging.getLogger(__name__)

INT8 = 1
UINT8 = 2
INT16 = 3
UINT16 = 4
INT32 = 5
UINT32 = 6
FLOAT32 = 7
FLOAT64 = 8

# PointField datatype -> numpy type code (byte order added per message).
DATATYPE_CODES: dict[int, str] = {
    INT8: 'i1', UINT8: 'u1', INT16: 'i2', UINT16: 'u2',
    INT32: 'i4', UINT32: 'u4', FLOAT32: 'f4', FLOAT64: 'f8',
}
DATATYPE_SIZES: dict[int, int] = {k: int(v[1]) for k, v in DATATYPE_CODES.items()}
_DATATYPE_OF_DTYPE: dict[np.dtype, int] = {np.dtype(v): k for k, v in DATATYPE_CODES.items()}
_UINT32_MAX = 2**32 - 1


@dataclass(frozen=True)
class FieldSpec:
    """One entry of a PointCloud2 field table (sensor_msgs/PointField)."""

    name: str
    offset: int
    datatype: int
    count: int = 1

    @property
    def size_bytes(self) -> int:
        """Bytes the field takes in one point (datatype size times count)."""
        return DATATYPE_SIZES[self.datatype] * self.count


@dataclass(frozen=True)
class CloudLayout:
    """A field table plus the bytes each point occupies: what a sensor driver publishes."""

    fields: tuple[FieldSpec, ...]
    point_step: int

    def __post_init__(self) -> None:
        _check_field_table(self.fields, self.point_step)

    @property
    def names(self) -> tuple[str, ...]:
        """The field names, in table order."""
        return tuple(f.name for f in self.fields)


@dataclass
class CloudBlob:
    """Everything in a PointCloud2 except the header; the ros layer and bag writer wrap it."""

    fields: tuple[FieldSpec, ...]
    point_step: int
    row_step: int
    height: int
    width: int
    is_bigendian: bool
    is_dense: bool
    data: bytes

    def __len__(self) -> int:
        return self.width * self.height


# ---------------------------------------------------------------------------------------------
# validation helpers

def _as_dim(value: Any, what: str) -> int:
    """A non-negative integer that fits a uint32 message field, or CodecError."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise CodecError(f'PointCloud2 {what} must be an integer, got {value!r}')
    value = int(value)
    if value < 0 or value > _UINT32_MAX:
        raise CodecError(f'PointCloud2 {what} = {value} is outside [0, 2^32 - 1]')
    return value


def _check_field_table(fields: tuple[FieldSpec, ...], point_step: int) -> None:
    """Datatypes known, counts >= 1, names unique, every field inside point_step."""
    seen: set[str] = set()
    for f in fields:
        if not isinstance(f.name, str) or not f.name:
            raise CodecError(f'PointField name must be a non-empty string, got {f.name!r}')
        if f.name in seen:
            raise CodecError(f'PointField {f.name!r} appears twice in the field table')
        seen.add(f.name)
        if f.datatype not in DATATYPE_CODES:
            raise CodecError(f'PointField {f.name!r} has unknown datatype {f.datatype} '
                             '(expected 1..8)')
        if f.count < 1:
            raise CodecError(f'PointField {f.name!r} has count {f.count} (must be >= 1)')
        end = f.offset + f.size_bytes
        if end > point_step:
            raise CodecError(f'PointField {f.name!r} (offset {f.offset}, {f.size_bytes} bytes) '
                             f'ends at byte {end}, beyond point_step {point_step}')


def _field_specs(msg: Any) -> tuple[FieldSpec, ...]:
    """The message's field table as FieldSpecs (rclpy or rosbags PointField alike)."""
    try:
        raw_fields = list(msg.fields)
    except (AttributeError, TypeError) as exc:
        raise CodecError(f'PointCloud2 has no readable field table: {exc}') from exc
    specs = []
    for i, f in enumerate(raw_fields):
        try:
            name, offset, datatype, count = f.name, f.offset, f.datatype, f.count
        except AttributeError as exc:
            raise CodecError(f'PointCloud2 field #{i} is not a PointField: {exc}') from exc
        if not isinstance(name, str):
            raise CodecError(f'PointCloud2 field #{i} name is not a string: {name!r}')
        specs.append(FieldSpec(name, _as_dim(offset, f'field {name!r} offset'),
                               _as_dim(datatype, f'field {name!r} datatype'),
                               _as_dim(count, f'field {name!r} count')))
    return tuple(specs)


def _byte_buffer(data: Any) -> np.ndarray:
    """A zero-copy uint8 view of the message payload, whatever container holds it."""
    if isinstance(data, np.ndarray):
        if data.dtype == np.uint8 and data.ndim == 1:
            return data
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if isinstance(data, (bytes, bytearray, memoryview)) or hasattr(data, 'buffer_info'):
        try:
            return np.frombuffer(memoryview(data).cast('B'), dtype=np.uint8)
        except (TypeError, ValueError) as exc:
            raise CodecError(f'PointCloud2 data is not a byte buffer: {exc}') from exc
    if isinstance(data, (list, tuple)):
        arr = np.asarray(data)
        if arr.ndim != 1 or (arr.size and (arr.dtype.kind not in 'iu' or arr.min() < 0
                                           or arr.max() > 255)):
            raise CodecError('PointCloud2 data list must hold byte values 0..255')
        return arr.astype(np.uint8)
    raise CodecError(f'PointCloud2 data has unsupported type {type(data).__name__}')


def _structured_dtype(fields: tuple[FieldSpec, ...], point_step: int,
                      big_endian: bool) -> np.dtype:
    order = '>' if big_endian else '<'
    formats = []
    for f in fields:
        code = order + DATATYPE_CODES[f.datatype]
        formats.append(code if f.count == 1 else (code, (f.count,)))
    return np.dtype({'names': [f.name for f in fields], 'formats': formats,
                     'offsets': [f.offset for f in fields], 'itemsize': point_step})


def _native(code: str, count: int) -> np.dtype:
    base = np.dtype(code).newbyteorder('=')
    return base if count == 1 else np.dtype((base, (count,)))


# ---------------------------------------------------------------------------------------------
# driver layouts

# ROS 2 velodyne driver (velodyne_pointcloud PointXYZIRT): `time` sits unaligned at byte 18.
VELODYNE_XYZIRT = CloudLayout(
    fields=(FieldSpec('x', 0, FLOAT32), FieldSpec('y', 4, FLOAT32), FieldSpec('z', 8, FLOAT32),
            FieldSpec('intensity', 12, FLOAT32), FieldSpec('ring', 16, UINT16),
            FieldSpec('time', 18, FLOAT32)),
    point_step=22)
# CitrusFarm ROS 1 recordings (PCL PointXYZIR, 16-byte aligned, padding after z, no time).
VELODYNE_XYZIR_ROS1 = CloudLayout(
    fields=(FieldSpec('x', 0, FLOAT32), FieldSpec('y', 4, FLOAT32), FieldSpec('z', 8, FLOAT32),
            FieldSpec('intensity', 16, FLOAT32), FieldSpec('ring', 20, UINT16)),
    point_step=32)
XYZ_FLOAT32 = CloudLayout(
    fields=(FieldSpec('x', 0, FLOAT32), FieldSpec('y', 4, FLOAT32), FieldSpec('z', 8, FLOAT32)),
    point_step=12)
XYZ_FLOAT64 = CloudLayout(
    fields=(FieldSpec('x', 0, FLOAT64), FieldSpec('y', 8, FLOAT64), FieldSpec('z', 16, FLOAT64)),
    point_step=24)


# ---------------------------------------------------------------------------------------------
# decoding

def decode_fields(msg: Any) -> dict[str, np.ndarray]:
    """Every field of a PointCloud2 as a native-endian array over N = width * height points.

    Organized clouds are flattened row-major honouring `row_step`; a field with count > 1
    becomes an (N, count) array. Raises CodecError for any inconsistent message.
    """
    return _decode_fields(msg, _field_specs(msg))


def _decode_fields(msg: Any, fields: tuple[FieldSpec, ...]) -> dict[str, np.ndarray]:
    try:
        height = _as_dim(msg.height, 'height')
        width = _as_dim(msg.width, 'width')
        point_step = _as_dim(msg.point_step, 'point_step')
        row_step = _as_dim(msg.row_step, 'row_step')
        big_endian = msg.is_bigendian
        data = msg.data
    except AttributeError as exc:
        raise CodecError(f'not a PointCloud2: {exc}') from exc
    if not isinstance(big_endian, (bool, np.bool_, int, np.integer)) or int(big_endian) not in (
            0, 1):
        raise CodecError(f'PointCloud2 is_bigendian must be a bool, got {big_endian!r}')
    _check_field_table(fields, point_step)
    n_points = width * height
    if n_points == 0:
        return {f.name: np.zeros((0,) if f.count == 1 else (0, f.count),
                                 dtype=_native(DATATYPE_CODES[f.datatype], 1))
                for f in fields}
    if row_step < point_step * width:
        raise CodecError(f'PointCloud2 row_step {row_step} < point_step {point_step} * width '
                         f'{width}')
    buffer = _byte_buffer(data)
    if buffer.size < row_step * height:
        raise CodecError(f'PointCloud2 data has {buffer.size} bytes, fewer than row_step '
                         f'{row_step} * height {height} = {row_step * height} '
                         f'({width} x {height} points claimed)')
    if not fields:
        return {}
    dtype = _structured_dtype(fields, point_step, bool(big_endian))
    grid = np.ndarray(shape=(height, width), dtype=dtype, buffer=buffer,
                      strides=(row_step, point_step))
    out = {}
    for f in fields:
        column = grid[f.name].astype(_native(DATATYPE_CODES[f.datatype], 1), order='C')
        out[f.name] = column.reshape((n_points,) if f.count == 1 else (n_points, f.count))
    return out


def stamp_ns_of(header: Any) -> int:
    """header.stamp -> int nanoseconds, exact (ROS 1 and ROS 2 stamps both have sec/nanosec)."""
    try:
        sec, nanosec = header.stamp.sec, header.stamp.nanosec
    except AttributeError as exc:
        raise CodecError(f'message header has no stamp: {exc}') from exc
    if isinstance(sec, bool) or not isinstance(sec, (int, np.integer)):
        raise CodecError(f'header.stamp.sec must be an integer, got {sec!r}')
    if isinstance(nanosec, bool) or not isinstance(nanosec, (int, np.integer)) or not (
            0 <= int(nanosec) < NS_PER_S):
        raise CodecError(f'header.stamp.nanosec must be an integer in [0, 1e9), got {nanosec!r}')
    return sec_nanosec_to_ns(sec, nanosec)


def decode_scan(msg: Any) -> Scan:
    """A PointCloud2 as a Scan: x, y, z required; intensity, ring, time when present.

    Points whose x, y or z is not finite (the NaN no-returns of organized clouds) are dropped.
    A `time` field (velodyne: seconds) or an integer `t` field (Ouster: nanoseconds) becomes
    `time_offset_s`, seconds from the stamp, its unit found from the values
    (`gft_odom.core.deskew.time_offsets_from_field`: s, ms, us, ns or absolute times).
    """
    # garbage bytes (signalling NaNs, huge values) must not flood the log with numpy warnings
    with np.errstate(invalid='ignore', over='ignore'):
        return _decode_scan(msg)


def _decode_scan(msg: Any) -> Scan:
    field_table = _field_specs(msg)
    specs = {f.name: f for f in field_table}
    missing = [name for name in 'xyz' if name not in specs]
    if missing:
        raise CodecError(f'PointCloud2 lacks field(s) {missing}; fields are {sorted(specs)}')
    header = getattr(msg, 'header', None)
    stamp_ns = stamp_ns_of(header)
    frame_id = getattr(header, 'frame_id', '')
    if not isinstance(frame_id, str):
        raise CodecError(f'header.frame_id must be a string, got {frame_id!r}')
    columns = _decode_fields(msg, field_table)  # validates the whole message first
    for name in 'xyz':
        f = specs[name]
        if f.datatype not in (FLOAT32, FLOAT64) or f.count != 1:
            raise CodecError(f'PointCloud2 field {name!r} must be one float32/float64 '
                             f'(datatype {f.datatype}, count {f.count})')
    x, y, z = columns['x'], columns['y'], columns['z']
    finite = np.isfinite(x)
    finite &= np.isfinite(y)
    finite &= np.isfinite(z)
    keep = None if finite.all() else finite
    if keep is not None:
        x, y, z = x[keep], y[keep], z[keep]
    points_xyz = np.empty((x.shape[0], 3), dtype=np.float64)
    points_xyz[:, 0], points_xyz[:, 1], points_xyz[:, 2] = x, y, z

    def scalar(name: str) -> np.ndarray | None:
        col = columns.get(name)
        if col is None or col.ndim != 1:
            return None
        return col if keep is None else col[keep]

    intensity = scalar('intensity')
    ring = scalar('ring')
    raw_time = scalar('time')
    if raw_time is None and (t := scalar('t')) is not None and t.dtype.kind in 'iu':
        raw_time = t
    time_s = None
    if raw_time is not None:
        time_s, unit = time_offsets_from_field(raw_time, stamp_ns)
        if time_s is None:
            log.warning('per-point time of the scan at %d ns fits no unit (|t| up to %.3g): '
                        'ignored', stamp_ns, float(np.nanmax(np.abs(raw_time.astype(float)))))
    return Scan(
        stamp_ns=stamp_ns, points_xyz=points_xyz,
        intensity=None if intensity is None else intensity.astype(np.float32, copy=False),
        ring=None if ring is None else ring.astype(np.uint16, copy=False),
        time_offset_s=None if time_s is None else time_s.astype(np.float32, copy=False),
        frame_id=frame_id)


# ---------------------------------------------------------------------------------------------
# encoding

def layout_for_columns(columns: Mapping[str, np.ndarray]) -> CloudLayout:
    """A packed layout (no padding, columns in dict order) from the columns' dtypes."""
    fields, offset = [], 0
    for name, values in columns.items():
        arr = np.asarray(values)
        datatype = _DATATYPE_OF_DTYPE.get(arr.dtype.newbyteorder('='))
        if datatype is None:
            raise CodecError(f'column {name!r} has dtype {arr.dtype}, which PointCloud2 cannot '
                             'hold (use int8/16/32, uint8/16/32, float32 or float64)')
        if arr.ndim not in (1, 2):
            raise CodecError(f'column {name!r} must be 1-D or (N, count), got shape {arr.shape}')
        count = 1 if arr.ndim == 1 else arr.shape[1]
        field = FieldSpec(name, offset, datatype, count)
        fields.append(field)
        offset += field.size_bytes
    return CloudLayout(tuple(fields), offset)


def encode_cloud(columns: Mapping[str, np.ndarray], layout: CloudLayout | None = None, *,
                 height: int = 1, is_bigendian: bool = False,
                 row_padding_bytes: int = 0) -> CloudBlob:
    """Pack named columns into PointCloud2 bytes.

    With `layout`, its fields are filled from the columns of the same name (missing ones are
    zero, columns not in the layout are ignored); without, a packed layout is built from the
    columns' dtypes. `height` > 1 makes an organized cloud of width N / height, and
    `row_padding_bytes` pads each row (row_step > point_step * width), as some drivers do.
    """
    if layout is None:
        layout = layout_for_columns(columns)
    arrays = {name: np.asarray(values) for name, values in columns.items()}
    lengths = {name: arr.shape[0] if arr.ndim else -1 for name, arr in arrays.items()}
    if len(set(lengths.values())) > 1 or -1 in lengths.values():
        raise CodecError(f'columns must have the same length, got {lengths}')
    n_points = next(iter(lengths.values()), 0)
    height = _as_dim(height, 'height')
    row_padding_bytes = _as_dim(row_padding_bytes, 'row padding')
    if height == 0 and n_points:
        raise CodecError('height 0 with a non-empty cloud')
    if height and n_points % height:
        raise CodecError(f'{n_points} points do not fill {height} rows evenly')
    width = n_points // height if height else 0
    packed = np.zeros(n_points, dtype=_structured_dtype(layout.fields, layout.point_step,
                                                        is_bigendian))
    for f in layout.fields:
        values = arrays.get(f.name)
        if values is None:
            continue
        shape = (n_points,) if f.count == 1 else (n_points, f.count)
        if values.shape != shape:
            raise CodecError(f'column {f.name!r} has shape {values.shape}, layout wants {shape}')
        packed[f.name] = values
    row_step = layout.point_step * width + row_padding_bytes
    if row_padding_bytes and height:
        rows = np.zeros((height, row_step), dtype=np.uint8)
        rows[:, :layout.point_step * width] = packed.view(np.uint8).reshape(height, -1)
        data = rows.tobytes()
    else:
        data = packed.tobytes()
    is_dense = True
    if all(name in arrays for name in 'xyz') and n_points:
        is_dense = bool(all(np.isfinite(arrays[name]).all() for name in 'xyz'))
    return CloudBlob(fields=layout.fields, point_step=layout.point_step, row_step=row_step,
                     height=height, width=width, is_bigendian=bool(is_bigendian),
                     is_dense=is_dense, data=data)


def scan_columns(scan: Scan) -> dict[str, np.ndarray]:
    """A Scan's per-point arrays under their velodyne field names."""
    xyz = np.asarray(scan.points_xyz)
    columns: dict[str, np.ndarray] = {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2]}
    if scan.intensity is not None:
        columns['intensity'] = scan.intensity
    if scan.ring is not None:
        columns['ring'] = scan.ring
    if scan.time_offset_s is not None:
        columns['time'] = scan.time_offset_s
    return columns


def encode_scan(scan: Scan, layout: CloudLayout | None = VELODYNE_XYZIRT) -> CloudBlob:
    """A Scan as PointCloud2 bytes in a driver layout (None: packed, x/y/z float32)."""
    columns = scan_columns(scan)
    if layout is None:
        columns = {k: (v.astype(np.float32) if k in ('x', 'y', 'z') else v)
                   for k, v in columns.items()}
    return encode_cloud(columns, layout)
