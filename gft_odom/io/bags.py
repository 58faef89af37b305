"""Reading scans and odometry from bags, writing small bags, all through `rosbags`.

One reader for everything a user may hold: a ROS 1 `.bag`, the parts of a split ROS 1
recording (CitrusFarm's `base_*.bag`, merged in time order), or a rosbag2 folder (sqlite3 or
mcap; a path to its `.db3`/`.mcap` file means its folder). No ROS install is needed. Failures
become `BagError` naming the file and topic; a single scan that does not decode is logged,
counted in `skipped` and passed over, so one bad message does not end a long replay.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from gft_odom.core.constants import NS_PER_S, ns_to_sec_nanosec
from gft_odom.core.geometry import xyz_quat_from_poses
from gft_odom.core.trajectory import Trajectory
from gft_odom.core.types import Scan
from gft_odom.errors import BagError, GftOdomError
from gft_odom.io._poses import trajectory_from_columns
from gft_odom.io.pointcloud2 import CloudBlob, decode_scan, stamp_ns_of

log = logging.getLogger(__name__)

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
ODOMETRY = 'nav_msgs/msg/Odometry'
ROS2_SUFFIXES = ('.db3', '.mcap')
ROS1_MAGIC = b'#ROSBAG V2.0\n'
# Beyond CodecError, what decoding a hostile message can raise: numpy's size and shape
# errors on a field table that lies about the data.
DECODE_ERRORS = (ValueError, TypeError, IndexError, OverflowError, MemoryError)

PathLike = str | Path


def rosbags_errors() -> tuple[type[Exception], ...]:
    """What reading, decoding or writing a bag through rosbags can raise on bad data or I/O.

    rosbags' own errors, and what its parsers let through on a damaged file: struct, sqlite3
    and apsw (its sqlite3 storage), bz2 (OSError/ValueError) and lz4 (RuntimeError) errors, bad
    offsets and missing keys.
    """
    import sqlite3
    import struct

    import apsw
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Ros1ReaderError
    from rosbags.rosbag1 import WriterError as Ros1WriterError
    from rosbags.rosbag2 import ReaderError as Ros2ReaderError
    from rosbags.rosbag2 import WriterError as Ros2WriterError
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    return (AnyReaderError, Ros1ReaderError, Ros1WriterError, Ros2ReaderError, Ros2WriterError,
            SerdeError, TypesysError, sqlite3.Error, apsw.Error, struct.error, OSError, EOFError,
            ValueError, KeyError, IndexError, TypeError, AttributeError, RuntimeError)


def _as_path_list(paths: PathLike | Sequence[PathLike]) -> list[Path]:
    if isinstance(paths, (str, Path)):
        return [Path(paths)]
    return [Path(p) for p in paths]


def _natural_key(path: Path) -> list:
    """`base_10.bag` after `base_9.bag`."""
    import re
    return [int(t) if t.isdigit() else t for t in re.split(r'(\d+)', path.name)]


def _check_ros1_magic(path: Path) -> None:
    try:
        with path.open('rb') as f:
            magic = f.read(len(ROS1_MAGIC))
    except OSError as exc:
        raise BagError(f'cannot read bag {path}: {exc}') from exc
    if magic != ROS1_MAGIC:
        raise BagError(f'{path} is not a ROS 1 bag (it does not start with {ROS1_MAGIC!r})')


def resolve_bag_paths(paths: PathLike | Sequence[PathLike]) -> tuple[list[Path], bool]:
    """The files/folders `AnyReader` should open, and whether they are ROS 1 bags.

    Accepts `.bag` files (one or several parts), a rosbag2 folder, the `.db3`/`.mcap` file
    inside one (its folder is meant), or a folder of ROS 1 parts (all `*.bag` inside).
    """
    given = _as_path_list(paths)
    if not given:
        raise BagError('no bag path given')
    resolved: list[Path] = []
    for path in given:
        if not path.exists():
            raise BagError(f'bag path {path} does not exist')
        if path.is_file() and path.suffix.lower() in ROS2_SUFFIXES:
            path = path.parent
        if path.is_dir():
            if (path / 'metadata.yaml').is_file():
                resolved.append(path)
                continue
            parts = sorted(path.glob('*.bag'), key=_natural_key)
            if not parts:
                raise BagError(f'{path} is neither a rosbag2 folder (no metadata.yaml) nor a '
                               'folder of ROS 1 .bag files')
            for part in parts:
                _check_ros1_magic(part)
            resolved.extend(parts)
        elif path.suffix.lower() == '.bag':
            _check_ros1_magic(path)
            resolved.append(path)
        else:
            raise BagError(f'{path} is not a bag: expected a ROS 1 .bag file, a rosbag2 folder '
                           'or its .db3/.mcap file')
    unique = list(dict.fromkeys(p.resolve() for p in resolved))
    is_ros1 = [p.suffix.lower() == '.bag' for p in unique]
    if any(is_ros1) and not all(is_ros1):
        raise BagError(f'cannot mix ROS 1 bags and rosbag2 folders in one read: {unique}')
    if not is_ros1[0] and len(unique) > 1:
        raise BagError(f'read one rosbag2 folder at a time, got {len(unique)}: {unique}')
    return unique, is_ros1[0]


class _BagSource:
    """An open AnyReader over resolved paths, with errors turned into BagError."""

    def __init__(self, paths: PathLike | Sequence[PathLike]) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.paths, self.is_ros1 = resolve_bag_paths(paths)
        self.where = ', '.join(str(p) for p in self.paths)
        store = Stores.ROS1_NOETIC if self.is_ros1 else Stores.ROS2_JAZZY
        try:
            self.reader = AnyReader(self.paths, default_typestore=get_typestore(store))
            self.reader.open()
        except rosbags_errors() as exc:  # many types for a damaged file
            raise BagError(f'cannot open bag {self.where}: not a readable bag ({exc})') from exc

    def close(self) -> None:
        if self.reader is not None and self.reader.stack is not None:
            self.reader.close()
        self.reader = None

    def topics(self) -> dict[str, str]:
        return {c.topic: c.msgtype for c in self.reader.connections}

    def connections(self, topic: str, msgtype: str) -> list:
        """The connections of `topic`, checked to carry `msgtype`."""
        found = [c for c in self.reader.connections if c.topic == topic]
        if not found:
            available = ', '.join(f'{t} ({m})' for t, m in sorted(self.topics().items()))
            raise BagError(f'topic {topic} not in bag {self.where}; available topics: '
                           f'{available or "none"}')
        wrong = sorted({c.msgtype for c in found if c.msgtype != msgtype})
        if wrong:
            raise BagError(f'topic {topic} in bag {self.where} carries {", ".join(wrong)}, '
                           f'expected {msgtype}')
        return found

    def raw(self, connections: list) -> Iterator[tuple[Any, int, bytes]]:
        """(connection, log time ns, raw bytes); a damaged file mid-way raises BagError."""
        topic = connections[0].topic
        messages = self.reader.messages(connections=connections)
        while True:
            try:
                item = next(messages)
            except StopIteration:
                return
            except rosbags_errors() as exc:
                raise BagError(f'bag {self.where} is damaged, reading {topic} stopped: '
                               f'{exc!r}') from exc
            yield item


class ScanBagReader:
    """The PointCloud2 scans of one topic, as `Scan`s in time order.

    `len(reader)` is the number of messages on the topic (for progress bars); `skipped`
    counts messages that could not be decoded and were passed over with a warning.
    """

    def __init__(self, paths: PathLike | Sequence[PathLike],
                 topic: str = '/velodyne_points') -> None:
        self.topic = topic
        self.skipped = 0
        self._source = _BagSource(paths)
        try:
            self._connections = self._source.connections(topic, POINTCLOUD2)
        except BagError:
            self._source.close()
            raise

    @property
    def paths(self) -> list[Path]:
        """The bag files or folders, in the order they are read."""
        return list(self._source.paths)

    def __enter__(self) -> 'ScanBagReader':
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Close the bag files."""
        self._source.close()

    def __len__(self) -> int:
        return int(sum(c.msgcount for c in self._connections))

    def topics(self) -> dict[str, str]:
        """Every topic in the bag and its message type."""
        return self._source.topics()

    def iter_messages(self) -> Iterator[tuple[int, Any]]:
        """(bag log time ns, deserialized message) for the topic; scans use header.stamp."""
        if self._source.reader is None:
            raise BagError(f'bag {self._source.where} is closed')
        for connection, log_time_ns, raw in self._source.raw(self._connections):
            try:
                msg = self._source.reader.deserialize(raw, connection.msgtype)
            except rosbags_errors() as exc:
                self._skip(log_time_ns, f'cannot deserialize: {exc}')
                continue
            yield log_time_ns, msg

    def __iter__(self) -> Iterator[Scan]:
        for log_time_ns, msg in self.iter_messages():
            try:
                scan = decode_scan(msg)
            except GftOdomError as exc:
                self._skip(log_time_ns, str(exc))
                continue
            except DECODE_ERRORS as exc:  # a hostile message must not end a replay
                self._skip(log_time_ns, repr(exc))
                continue
            yield scan

    def _skip(self, log_time_ns: int, reason: str) -> None:
        self.skipped += 1
        log.warning('skipping message on %s at bag time %d.%09d s in %s: %s', self.topic,
                    log_time_ns // NS_PER_S, log_time_ns % NS_PER_S, self._source.where, reason)


def read_odometry(paths: PathLike | Sequence[PathLike],
                  topic: str = '/gps/fix/odometry') -> Trajectory:
    """nav_msgs/Odometry poses (header.stamp, pose.pose) of one topic, sorted by time.

    Messages with a non-finite position are dropped with a warning; a zero or non-finite
    quaternion (GPS fixes carry no orientation) becomes the identity.
    """
    source = _BagSource(paths)
    try:
        connections = source.connections(topic, ODOMETRY)
        stamps, values = [], []
        for connection, _, raw in source.raw(connections):
            try:
                msg = source.reader.deserialize(raw, connection.msgtype)
                stamp_ns = stamp_ns_of(msg.header)
            except rosbags_errors() as exc:
                raise BagError(f'bad Odometry message on {topic} in {source.where}: '
                               f'{exc}') from exc
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            stamps.append(stamp_ns)
            values.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
    finally:
        source.close()
    stamps_ns = np.asarray(stamps, dtype=np.int64)
    values_arr = np.asarray(values, dtype=np.float64).reshape(-1, 7)
    return trajectory_from_columns(stamps_ns, values_arr[:, :3], values_arr[:, 3:],
                                   f'{topic} in {source.where}', drop_nonfinite=True)


class BagWriter:
    """Writes PointCloud2 and Odometry messages into a new bag (tests, simulator, tools).

    `fmt='ros1'` writes one `.bag` file at `path` (ROS1_NOETIC types); `fmt='ros2'` a rosbag2
    folder at `path` (ROS2_JAZZY types, version 9, `storage` sqlite3 or mcap). The bag's log
    time of each message is its header stamp. One connection per topic, made on first use.
    """

    def __init__(self, path: PathLike, fmt: str = 'ros2', storage: str = 'sqlite3') -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        if fmt not in ('ros1', 'ros2'):
            raise BagError(f'bag format must be ros1 or ros2, got {fmt!r} (writing {path})')
        if fmt == 'ros2' and storage not in ('sqlite3', 'mcap'):
            raise BagError(f'rosbag2 storage must be sqlite3 or mcap, got {storage!r} '
                           f'(writing {path})')
        if self.path.exists():
            raise BagError(f'{self.path} exists already; not overwriting it')
        self.fmt, self.storage = fmt, storage
        self.typestore = get_typestore(Stores.ROS1_NOETIC if fmt == 'ros1'
                                       else Stores.ROS2_JAZZY)
        self._writer = None
        self._connections: dict[str, tuple[Any, str]] = {}
        self._seq: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def open(self) -> 'BagWriter':
        """Create the bag (BagError when it cannot be created)."""
        try:
            if self.fmt == 'ros1':
                from rosbags.rosbag1 import Writer as Writer1
                self._writer = Writer1(self.path)
            else:
                from rosbags.rosbag2 import StoragePlugin
                from rosbags.rosbag2 import Writer as Writer2
                plugin = (StoragePlugin.MCAP if self.storage == 'mcap'
                          else StoragePlugin.SQLITE3)
                self._writer = Writer2(self.path, version=9, storage_plugin=plugin)
            self._writer.open()
        except rosbags_errors() as exc:
            self._writer = None
            raise BagError(f'cannot create bag {self.path}: {exc}') from exc
        return self

    def close(self) -> None:
        """Finish the bag (index, metadata); safe to call twice."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except rosbags_errors() as exc:
                raise BagError(f'cannot finish bag {self.path}: {exc}') from exc

    def __enter__(self) -> 'BagWriter':
        return self.open() if self._writer is None else self

    def __exit__(self, *exc_info) -> None:
        # Close even after an error: what was written stays readable.
        self.close()

    # -- messages ---------------------------------------------------------------------------

    def _header(self, topic: str, stamp_ns: int, frame_id: str):
        types = self.typestore.types
        stamp_ns = int(stamp_ns)
        if stamp_ns < 0:
            raise BagError(f'negative stamp {stamp_ns} ns on {topic} (writing {self.path})')
        sec, nanosec = ns_to_sec_nanosec(stamp_ns)
        stamp = types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec)
        if self.fmt == 'ros1':
            seq = self._seq.get(topic, 0)
            self._seq[topic] = seq + 1
            return types['std_msgs/msg/Header'](seq=seq, stamp=stamp, frame_id=frame_id)
        return types['std_msgs/msg/Header'](stamp=stamp, frame_id=frame_id)

    def write_message(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        """Serialize and write any message of this bag's typestore at log time `stamp_ns`."""
        if self._writer is None:
            raise BagError(f'bag {self.path} is not open (use it as a context manager)')
        known = self._connections.get(topic)
        if known is None:
            try:
                connection = self._writer.add_connection(topic, msgtype,
                                                         typestore=self.typestore)
            except rosbags_errors() as exc:
                raise BagError(f'cannot add topic {topic} ({msgtype}) to {self.path}: '
                               f'{exc}') from exc
            known = self._connections[topic] = (connection, msgtype)
        connection, topic_type = known
        if topic_type != msgtype:
            raise BagError(f'topic {topic} in {self.path} already carries {topic_type}, '
                           f'not {msgtype}')
        try:
            if self.fmt == 'ros1':
                raw = self.typestore.serialize_ros1(msg, msgtype)
            else:
                raw = self.typestore.serialize_cdr(msg, msgtype)
            self._writer.write(connection, int(stamp_ns), raw)
        except rosbags_errors() as exc:
            raise BagError(f'cannot write {msgtype} on {topic} to {self.path}: {exc}') from exc
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def write_metadata(self, topic: str, stamp_ns: int, key: str, text: str) -> None:
        """Record `text` in the bag: rosbag2 custom_data[`key`]; a ROS 1 bag has no such
        field, so there it is one std_msgs/String on `topic`."""
        if self._writer is None:
            raise BagError(f'bag {self.path} is not open')
        if self.fmt == 'ros2':
            self._writer.set_custom_data(key, text)
            return
        self.write_message(topic, 'std_msgs/msg/String', stamp_ns,
                           self.typestore.types['std_msgs/msg/String'](data=text))

    def write_cloud(self, topic: str, stamp_ns: int, blob: CloudBlob, frame_id: str,
                    log_time_ns: int | None = None) -> None:
        """One sensor_msgs/PointCloud2 made from the codec's output; logged at `log_time_ns`
        (default: its stamp), so a bag can hold a mis-stamped scan where it arrived."""
        types = self.typestore.types
        field_type = types['sensor_msgs/msg/PointField']
        msg = types[POINTCLOUD2](
            header=self._header(topic, stamp_ns, frame_id),
            height=int(blob.height), width=int(blob.width),
            fields=[field_type(name=f.name, offset=int(f.offset), datatype=int(f.datatype),
                               count=int(f.count)) for f in blob.fields],
            is_bigendian=bool(blob.is_bigendian), point_step=int(blob.point_step),
            row_step=int(blob.row_step), data=np.frombuffer(bytes(blob.data), dtype=np.uint8),
            is_dense=bool(blob.is_dense))
        self.write_message(topic, POINTCLOUD2, stamp_ns if log_time_ns is None else log_time_ns,
                           msg)

    def write_odometry(self, topic: str, stamp_ns: int, T_world_body: np.ndarray,
                       frame_id: str = 'map', child_frame_id: str = 'gps',
                       covariance_diag: Sequence[float] | None = None) -> None:
        """One nav_msgs/Odometry with pose T_world_body (twist zero); 6 diagonal covariances."""
        types = self.typestore.types
        xyz, quat = xyz_quat_from_poses(np.asarray(T_world_body, dtype=float).reshape(1, 4, 4))
        covariance = np.zeros(36)
        if covariance_diag is not None:
            diag = np.asarray(covariance_diag, dtype=float).reshape(-1)
            if diag.shape != (6,):
                raise BagError(f'covariance_diag needs 6 values, got {diag.shape[0]} '
                               f'(topic {topic}, {self.path})')
            covariance[::7] = diag
        vector3 = types['geometry_msgs/msg/Vector3']
        pose = types['geometry_msgs/msg/Pose'](
            position=types['geometry_msgs/msg/Point'](*(float(v) for v in xyz[0])),
            orientation=types['geometry_msgs/msg/Quaternion'](*(float(v) for v in quat[0])))
        twist = types['geometry_msgs/msg/Twist'](linear=vector3(0.0, 0.0, 0.0),
                                                 angular=vector3(0.0, 0.0, 0.0))
        msg = types[ODOMETRY](
            header=self._header(topic, stamp_ns, frame_id), child_frame_id=child_frame_id,
            pose=types['geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=covariance),
            twist=types['geometry_msgs/msg/TwistWithCovariance'](twist=twist,
                                                                 covariance=np.zeros(36)))
        self.write_message(topic, ODOMETRY, stamp_ns, msg)
