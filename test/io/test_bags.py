"""Bags written with BagWriter (ROS 1, rosbag2 sqlite3 and mcap) read back by ScanBagReader."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import velodyne_columns

from gft_odom.core.geometry import rpy_transform
from gft_odom.errors import BagError, GroundTruthError
from gft_odom.io.bags import BagWriter, ScanBagReader, read_odometry, resolve_bag_paths
from gft_odom.io.pointcloud2 import (
    VELODYNE_XYZIR_ROS1,
    VELODYNE_XYZIRT,
    CloudBlob,
    CloudLayout,
    decode_fields,
    encode_cloud,
)

T0_NS = 1_680_000_000_000_000_000
PERIOD_NS = 100_000_000
SCAN_TOPIC = '/velodyne_points'
GPS_TOPIC = '/gps/fix/odometry'

# (fmt, storage, file name, layout): both velodyne layouts, all three containers
BAG_KINDS = {
    'ros1-xyzir': ('ros1', 'sqlite3', 'base.bag', VELODYNE_XYZIR_ROS1),
    'ros2-sqlite3-xyzirt': ('ros2', 'sqlite3', 'scans', VELODYNE_XYZIRT),
    'ros2-mcap-xyzirt': ('ros2', 'mcap', 'scans', VELODYNE_XYZIRT),
    'ros1-xyzirt': ('ros1', 'sqlite3', 'scans.bag', VELODYNE_XYZIRT),
}


def scan_columns(i: int) -> dict[str, np.ndarray]:
    return velodyne_columns(300, seed=i)


def gps_pose(i: int) -> np.ndarray:
    return rpy_transform((0.5 * i, 0.1 * i, 0.01 * i), (0.0, 0.0, 0.05 * i))


def write_bag(path: Path, fmt: str, storage: str, layout: CloudLayout, indices=range(5),
              with_gps: bool = True) -> Path:
    with BagWriter(path, fmt=fmt, storage=storage) as writer:
        for i in indices:
            stamp_ns = T0_NS + i * PERIOD_NS
            writer.write_cloud(SCAN_TOPIC, stamp_ns, encode_cloud(scan_columns(i), layout),
                               'velodyne')
            if with_gps:
                writer.write_odometry(GPS_TOPIC, stamp_ns + 1, gps_pose(i),
                                      covariance_diag=[0.01] * 3 + [1e3] * 3)
    return path


@pytest.fixture(params=sorted(BAG_KINDS))
def bag(request, tmp_path):
    fmt, storage, name, layout = BAG_KINDS[request.param]
    return write_bag(tmp_path / name, fmt, storage, layout), fmt, storage, layout


def test_scans_read_back_exactly(bag):
    path, fmt, storage, layout = bag
    with ScanBagReader([path]) as reader:
        assert len(reader) == 5
        assert reader.topics() == {SCAN_TOPIC: 'sensor_msgs/msg/PointCloud2',
                                   GPS_TOPIC: 'nav_msgs/msg/Odometry'}
        scans = list(reader)
        assert reader.skipped == 0
    assert [s.stamp_ns for s in scans] == [T0_NS + i * PERIOD_NS for i in range(5)]
    for i, scan in enumerate(scans):
        cols = scan_columns(i)
        np.testing.assert_array_equal(scan.points_xyz,
                                      np.column_stack([cols['x'], cols['y'], cols['z']]))
        np.testing.assert_array_equal(scan.ring, cols['ring'])
        assert scan.frame_id == 'velodyne'
        if 'time' in layout.names:
            np.testing.assert_array_equal(scan.time_offset_s, cols['time'])
        else:
            assert scan.time_offset_s is None


def test_raw_messages_keep_the_layout(bag):
    path, fmt, storage, layout = bag
    with ScanBagReader(path) as reader:  # a single path, not a list, is fine too
        stamps, msgs = zip(*reader.iter_messages())
    assert list(stamps) == [T0_NS + i * PERIOD_NS for i in range(5)]
    assert msgs[0].point_step == layout.point_step
    assert [f.name for f in msgs[0].fields] == list(layout.names)
    np.testing.assert_array_equal(decode_fields(msgs[2])['intensity'],
                                  scan_columns(2)['intensity'])


def test_odometry_reads_back(bag):
    path = bag[0]
    traj = read_odometry([path])
    assert traj.stamps_ns.tolist() == [T0_NS + i * PERIOD_NS + 1 for i in range(5)]
    np.testing.assert_allclose(traj.poses, np.stack([gps_pose(i) for i in range(5)]),
                               atol=1e-12)


def test_rosbag2_storage_file_means_its_folder(tmp_path):
    for storage, suffix in (('sqlite3', '.db3'), ('mcap', '.mcap')):
        folder = write_bag(tmp_path / storage, 'ros2', storage, VELODYNE_XYZIRT)
        (storage_file,) = folder.glob(f'*{suffix}')
        with ScanBagReader([str(storage_file)]) as reader:
            assert len(reader) == 5 and len(list(reader)) == 5


def test_split_ros1_bag_parts_read_in_time_order(tmp_path):
    """CitrusFarm-style base_1..3.bag, given out of order, some parts interleaved in time."""
    parts = {
        'base_3.bag': [6, 7, 8],
        'base_1.bag': [0, 2, 1],  # written out of order within the part
        'base_2.bag': [3, 5, 4],
    }
    for name, indices in parts.items():
        write_bag(tmp_path / name, 'ros1', 'sqlite3', VELODYNE_XYZIR_ROS1, indices)
    paths = [tmp_path / name for name in parts]
    with ScanBagReader(paths) as reader:
        assert len(reader) == 9
        stamps = [s.stamp_ns for s in reader]
        first = next(iter(reader))
    assert stamps == [T0_NS + i * PERIOD_NS for i in range(9)]
    np.testing.assert_array_equal(first.points_xyz[:, 0], scan_columns(0)['x'])
    # the folder holding the parts reads the same, and so does the GPS track across parts
    with ScanBagReader(tmp_path) as reader:
        assert [s.stamp_ns for s in reader] == stamps
    assert read_odometry(paths).stamps_ns.tolist() == [s + 1 for s in stamps]


def test_split_parts_interleaved_in_time_are_merged(tmp_path):
    write_bag(tmp_path / 'a.bag', 'ros1', 'sqlite3', VELODYNE_XYZIR_ROS1, [0, 2, 4])
    write_bag(tmp_path / 'b.bag', 'ros1', 'sqlite3', VELODYNE_XYZIR_ROS1, [1, 3, 5])
    with ScanBagReader([tmp_path / 'b.bag', tmp_path / 'a.bag']) as reader:
        assert [(s.stamp_ns - T0_NS) // PERIOD_NS for s in reader] == list(range(6))


# --- errors ---------------------------------------------------------------------------------

def test_missing_path(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        ScanBagReader([tmp_path / 'nope.bag'])
    with pytest.raises(BagError, match='no bag path'):
        ScanBagReader([])


def test_not_a_bag(tmp_path):
    text = tmp_path / 'notes.bag'
    text.write_text('hello, I am not a bag\n' * 50)
    with pytest.raises(BagError, match='not a ROS 1 bag'):
        ScanBagReader([text])
    other = tmp_path / 'scan.pcd'
    other.write_text('x')
    with pytest.raises(BagError, match='is not a bag'):
        ScanBagReader([other])
    empty_dir = tmp_path / 'empty'
    empty_dir.mkdir()
    with pytest.raises(BagError, match='neither a rosbag2 folder'):
        ScanBagReader([empty_dir])
    fake2 = tmp_path / 'fake2'
    fake2.mkdir()
    (fake2 / 'metadata.yaml').write_text('rosbag2_bagfile_information: {version: 9}\n')
    with pytest.raises(BagError, match='fake2'):
        ScanBagReader([fake2])


def _storage_file(path: Path, fmt: str) -> Path:
    if fmt == 'ros1':
        return path
    (found,) = [p for p in path.iterdir() if p.suffix in ('.db3', '.mcap')]
    return found


@pytest.mark.parametrize('keep_fraction', [0.0, 0.3, 0.7, 0.97])
def test_truncated_bag_raises_bag_error_naming_the_file(bag, keep_fraction):
    path, fmt = bag[0], bag[1]
    target = _storage_file(path, fmt)
    data = target.read_bytes()
    target.write_bytes(data[:int(keep_fraction * len(data))])
    with pytest.raises(BagError, match=path.name):
        with ScanBagReader([path]) as reader:
            list(reader)


def test_overwritten_bytes_in_one_message_skip_that_scan(bag, caplog):
    """A scan whose header was overwritten is logged, counted and passed over."""
    path, fmt = bag[0], bag[1]
    target = _storage_file(path, fmt)
    data = bytearray(target.read_bytes())
    stamp_of_third = T0_NS + 2 * PERIOD_NS
    # every scan has frame_id 'velodyne' (length-prefixed in both wire formats; the topic
    # name is not): damage the bytes right after the third one's
    marker = b'\x08\x00\x00\x00velodyne' if fmt == 'ros1' else b'\x09\x00\x00\x00velodyne\x00'
    at = -1
    for _ in range(3):
        at = data.index(marker, at + 1)
    data[at + len(marker):at + len(marker) + 12] = b'\xff' * 12
    target.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger='gft_odom.io.bags'):
        with ScanBagReader([path]) as reader:
            stamps = [s.stamp_ns for s in reader]
            assert reader.skipped == 1
    assert stamp_of_third not in stamps and len(stamps) == 4
    assert any('skipping message' in r.getMessage() and '1680000000.200000000' in r.getMessage()
               for r in caplog.records)


def test_overwritten_file_header_is_not_a_readable_bag(bag):
    path, fmt = bag[0], bag[1]
    target = _storage_file(path, fmt)
    data = bytearray(target.read_bytes())
    data[:16] = b'\x00' * 16
    target.write_bytes(bytes(data))
    with pytest.raises(BagError, match=path.name):
        ScanBagReader([path])


def test_missing_topic_lists_the_available_ones(bag):
    with pytest.raises(BagError, match=r'/ouster/points not in bag .*available topics: '
                                       r'/gps/fix/odometry \(nav_msgs/msg/Odometry\), '
                                       r'/velodyne_points'):
        ScanBagReader([bag[0]], topic='/ouster/points')


def test_wrong_message_type_on_topic(bag):
    with pytest.raises(BagError, match='carries nav_msgs/msg/Odometry, expected '
                                       'sensor_msgs/msg/PointCloud2'):
        ScanBagReader([bag[0]], topic=GPS_TOPIC)
    with pytest.raises(BagError, match='expected nav_msgs/msg/Odometry'):
        read_odometry([bag[0]], topic=SCAN_TOPIC)


def test_malformed_scan_mid_bag_is_skipped_with_a_warning(tmp_path, caplog):
    path = tmp_path / 'bad.bag'
    good = encode_cloud(scan_columns(0), VELODYNE_XYZIRT)
    bad = CloudBlob(good.fields, good.point_step, good.row_step, good.height,
                    good.width + 1000, False, True, good.data)  # claims more than it holds
    no_xyz = encode_cloud({'intensity': np.ones(4, np.float32)})
    with BagWriter(path, fmt='ros1') as writer:
        for i, blob in enumerate([good, bad, good, no_xyz, good]):
            writer.write_cloud(SCAN_TOPIC, T0_NS + i * PERIOD_NS, blob, 'velodyne')
    with caplog.at_level(logging.WARNING):
        with ScanBagReader(path) as reader:
            scans = list(reader)
            assert len(reader) == 5 and reader.skipped == 2
    assert [(s.stamp_ns - T0_NS) // PERIOD_NS for s in scans] == [0, 2, 4]
    messages = [r.getMessage() for r in caplog.records]
    assert any('1680000000.100000000' in m and 'row_step 6600 <' in m for m in messages)
    assert any('1680000000.300000000' in m and 'lacks field' in m for m in messages)


def test_mixing_ros1_and_rosbag2_is_refused(tmp_path):
    a = write_bag(tmp_path / 'a.bag', 'ros1', 'sqlite3', VELODYNE_XYZIRT, [0])
    b = write_bag(tmp_path / 'b', 'ros2', 'sqlite3', VELODYNE_XYZIRT, [1])
    with pytest.raises(BagError, match='cannot mix'):
        resolve_bag_paths([a, b])


def _odometry(store, sec: int, xyz, quat_xyzw):
    """A ROS 1 nav_msgs/Odometry built field by field (bypassing BagWriter.write_odometry)."""
    header = store['std_msgs/msg/Header'](
        seq=0, stamp=store['builtin_interfaces/msg/Time'](sec=sec, nanosec=5), frame_id='map')
    pose = store['geometry_msgs/msg/Pose'](
        position=store['geometry_msgs/msg/Point'](*xyz),
        orientation=store['geometry_msgs/msg/Quaternion'](*quat_xyzw))
    vec = store['geometry_msgs/msg/Vector3'](0.0, 0.0, 0.0)
    return store['nav_msgs/msg/Odometry'](
        header=header, child_frame_id='gps',
        pose=store['geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=np.zeros(36)),
        twist=store['geometry_msgs/msg/TwistWithCovariance'](
            twist=store['geometry_msgs/msg/Twist'](linear=vec, angular=vec),
            covariance=np.zeros(36)))


def test_odometry_without_orientation_or_position(tmp_path):
    """GPS fixes: a zero quaternion means no orientation (identity); NaN positions drop."""
    path = tmp_path / 'gt.bag'
    with BagWriter(path, fmt='ros1') as writer:
        for i, xyz in enumerate([(1.0, 2.0, 3.0), (np.nan, 0.0, 0.0), (4.0, 5.0, 6.0)]):
            msg = _odometry(writer.typestore.types, 100 + i, xyz, (0.0, 0.0, 0.0, 0.0))
            writer.write_message(GPS_TOPIC, 'nav_msgs/msg/Odometry', 10**9 * (100 + i), msg)
    traj = read_odometry(path)
    assert traj.stamps_ns.tolist() == [100_000_000_005, 102_000_000_005]
    np.testing.assert_array_equal(traj.poses[:, :3, :3], np.stack([np.eye(3)] * 2))
    np.testing.assert_array_equal(traj.positions_xyz, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize('n_swapped, ok', [(1, True), (8, False)])
def test_odometry_header_stamps_out_of_order(tmp_path, n_swapped, ok):
    """Header stamps that step back a few times are sorted; a shuffled stream is an error."""
    path = tmp_path / 'gt.bag'
    secs = np.arange(20)
    for k in range(n_swapped):
        secs[[2 * k, 2 * k + 1]] = secs[[2 * k + 1, 2 * k]]
    with BagWriter(path, fmt='ros1') as writer:
        for k, sec in enumerate(secs.tolist()):  # the bag's own time increases
            msg = _odometry(writer.typestore.types, 100 + sec, (float(sec), 0.0, 0.0),
                            (0.0, 0.0, 0.0, 1.0))
            writer.write_message(GPS_TOPIC, 'nav_msgs/msg/Odometry', T0_NS + k, msg)
    if ok:
        traj = read_odometry(path)
        assert np.all(np.diff(traj.stamps_ns) > 0)
        np.testing.assert_array_equal(traj.positions_xyz[:, 0], np.arange(20))
    else:
        with pytest.raises(GroundTruthError, match='time goes backwards 8 times'):
            read_odometry(path)


# --- the writer -----------------------------------------------------------------------------

def test_writer_refuses_bad_requests(tmp_path):
    existing = write_bag(tmp_path / 'x.bag', 'ros1', 'sqlite3', VELODYNE_XYZIRT, [0])
    with pytest.raises(BagError, match='exists already'):
        BagWriter(existing, fmt='ros1')
    with pytest.raises(BagError, match='ros1 or ros2'):
        BagWriter(tmp_path / 'y', fmt='ros3')
    with pytest.raises(BagError, match='sqlite3 or mcap'):
        BagWriter(tmp_path / 'y', storage='leveldb')
    blob = encode_cloud(scan_columns(0), VELODYNE_XYZIRT)
    with pytest.raises(BagError, match='not open'):
        BagWriter(tmp_path / 'z').write_cloud(SCAN_TOPIC, T0_NS, blob, 'velodyne')
    with BagWriter(tmp_path / 'w', fmt='ros2') as writer:
        writer.write_cloud(SCAN_TOPIC, T0_NS, blob, 'velodyne')
        with pytest.raises(BagError, match='already carries'):
            writer.write_odometry(SCAN_TOPIC, T0_NS, np.eye(4))
        with pytest.raises(BagError, match='6 values'):
            writer.write_odometry(GPS_TOPIC, T0_NS, np.eye(4), covariance_diag=[1.0, 2.0])
        with pytest.raises(BagError, match='negative stamp'):
            writer.write_cloud(SCAN_TOPIC, -5, blob, 'velodyne')
    # what was written before the refusals is intact
    with ScanBagReader(tmp_path / 'w') as reader:
        assert len(reader) == 1


def test_writer_keeps_what_was_written_when_the_caller_fails(tmp_path):
    path = tmp_path / 'partial'
    blob = encode_cloud(scan_columns(0), VELODYNE_XYZIRT)
    with pytest.raises(RuntimeError):
        with BagWriter(path, fmt='ros2', storage='mcap') as writer:
            writer.write_cloud(SCAN_TOPIC, T0_NS, blob, 'velodyne')
            writer.write_cloud(SCAN_TOPIC, T0_NS + PERIOD_NS, blob, 'velodyne')
            raise RuntimeError('simulator crashed')
    with ScanBagReader(path) as reader:
        assert len(list(reader)) == 2


def test_covariance_diag_lands_on_the_diagonal(tmp_path):
    path = tmp_path / 'cov'
    with BagWriter(path) as writer:
        writer.write_odometry(GPS_TOPIC, T0_NS, np.eye(4), frame_id='utm', child_frame_id='ant',
                              covariance_diag=[1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    with _odometry_messages(path) as msgs:
        (msg,) = msgs
    cov = np.asarray(msg.pose.covariance).reshape(6, 6)
    np.testing.assert_array_equal(cov, np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]))
    assert msg.header.frame_id == 'utm' and msg.child_frame_id == 'ant'


class _odometry_messages:
    """Raw Odometry messages of a bag, read with rosbags directly (an independent reader)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self):
        from rosbags.highlevel import AnyReader
        self.reader = AnyReader([self.path])
        self.reader.open()
        return [self.reader.deserialize(raw, c.msgtype)
                for c, _, raw in self.reader.messages()]

    def __exit__(self, *exc) -> None:
        self.reader.close()


def test_bag_copy_survives_a_rename(tmp_path):
    """A rosbag2 folder moved elsewhere still reads (paths inside are relative)."""
    src = write_bag(tmp_path / 'orig', 'ros2', 'mcap', VELODYNE_XYZIRT, [0, 1])
    moved = tmp_path / 'moved'
    shutil.move(src, moved)
    with ScanBagReader(moved) as reader:
        assert len(list(reader)) == 2
