"""`gft-odom replay --through-node`: the real node in its own process, fed over DDS.

Nothing here re-implements the pipeline: the colcon-installed `lib/gft_odom/filter_odom_node`
(what `ros2 run` starts) gets the bag's scans and a `/clock` in lockstep (next scan once the
odometry of the previous one arrived), so its trajectory is comparable to the in-process replay.
"""

from __future__ import annotations

import logging
import os
import random
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2

from gft_odom.config import GftOdomConfig
from gft_odom.core.constants import NODE_NAME, SCAN_PERIOD_S
from gft_odom.core.geometry import base_to_sensor_poses
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import GftOdomError
from gft_odom.io.bags import ScanBagReader
from gft_odom.io.ground_truth import read_ground_truth
from gft_odom.io.pointcloud2 import CloudBlob, FieldSpec
from gft_odom.params_file import config_to_yaml
from gft_odom.pipeline import base_to_sensor
from gft_odom.replay import ReplayResult, is_gps_ground_truth, summarize
from gft_odom.ros.conversions import (
    blob_to_msg,
    ns_to_stamp,
    odometry_to_pose,
    pose_matrix,
    stamp_to_ns,
)

log = logging.getLogger(__name__)

RESEND_AFTER_S = 2.0
MIN_SEND_INTERVAL_S = SCAN_PERIOD_S  # a VLP-16 sweep period
# A sweep's pose holds within one period after its stamp.
SWEEP_SPAN_NS = int(SCAN_PERIOD_S * 1e9)


class NodeProcessError(GftOdomError):
    """The node process could not be started or stopped answering."""


def find_node_executable(node_exe: str | None = None) -> Path:
    """`--node-exe`, else `<prefix>/lib/gft_odom/filter_odom_node` on AMENT_PREFIX_PATH."""
    if node_exe:
        path = Path(node_exe)
        if not path.is_file():
            raise NodeProcessError(f'node executable {path} does not exist')
        return path
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
        path = Path(prefix) / 'lib' / 'gft_odom' / NODE_NAME
        if path.is_file():
            return path
    raise NodeProcessError('cannot find lib/gft_odom/filter_odom_node: colcon build the package '
                           'and source install/setup.bash, or pass --node-exe')


def stop_node_process(proc: subprocess.Popen, timeout_s: float = 15.0) -> int:
    """Ctrl-C the node (its clean shutdown logs the final counts), kill it if it hangs."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def ros_message_from_bag(raw) -> PointCloud2:
    """A bag's PointCloud2 (rosbags object, ROS 1 or 2) as an rclpy message, bytes untouched."""
    blob = CloudBlob(
        fields=tuple(FieldSpec(name=str(f.name), offset=int(f.offset), datatype=int(f.datatype),
                               count=int(f.count)) for f in raw.fields),
        point_step=int(raw.point_step), row_step=int(raw.row_step), height=int(raw.height),
        width=int(raw.width), is_bigendian=bool(raw.is_bigendian), is_dense=bool(raw.is_dense),
        data=np.asarray(raw.data, dtype=np.uint8).tobytes())
    return blob_to_msg(blob, stamp_to_ns(raw.header.stamp), str(raw.header.frame_id))


def start_feeder(name: str, domain_id: int):
    """(context, node, executor): an rclpy node of its own context in `domain_id`, to feed
    the node under test and read its answers."""
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node(name, context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    return context, node, executor


def stop_feeder(context, node, executor) -> None:
    """Undo `start_feeder`."""
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def _launch_node(exe: Path, config: GftOdomConfig, topic: str, env: dict[str, str],
                 log_path: str | Path | None, save_map_dir: str | Path | None = None):
    """Start filter_odom_node with the config as its params file, sim time and lockstep QoS:
    (process, temporary folder, node log, domain id)."""
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('ROS_DOMAIN_ID', str(random.randint(100, 200)))
    domain_id = int(env['ROS_DOMAIN_ID'])
    work = Path(tempfile.mkdtemp(prefix='gft_odom_node_'))
    params_path = work / 'params.yaml'
    params_path.write_text(config_to_yaml(config))
    node_log = Path(log_path) if log_path else work / 'node.log'
    # Lockstep feeding never queues scans, so a deeper input queue costs no latency; with the
    # robot's depth 1 the node was seen to miss the very first (fragmented, best-effort) cloud
    # of a run in every resend.
    cmd = [str(exe), '--ros-args', '--params-file', str(params_path),
           '-p', 'use_sim_time:=true', '-p', 'node.input_queue_depth:=10',
           '-p', 'node.input_reliability:=reliable',
           '-r', f'points:={topic}']
    if save_map_dir is not None:
        cmd[-2:-2] = ['-p', f'node.save_map_dir:={Path(save_map_dir).resolve()}']
    log.info('starting %s (ROS_DOMAIN_ID=%d)', ' '.join(cmd), domain_id)
    with open(node_log, 'w') as log_file:
        proc = subprocess.Popen(cmd, env=env, stdout=log_file, stderr=subprocess.STDOUT)
    return proc, work, node_log, domain_id


class _Feeder:
    """The feeding side: publishes /clock and the clouds, records what the node answers."""

    def __init__(self, proc, node_log: Path, domain_id: int, topic: str) -> None:
        """Subscriptions to the node's odometry, path and filtered clouds; the publishers."""
        self.proc, self.node_log = proc, node_log
        self.context, self.node, self.executor = start_feeder('gft_odom_replay_feeder',
                                                              domain_id)
        self.odometry: dict[int, np.ndarray] = {}
        self.kept_points: dict[int, int] = {}
        self.map_poses: dict[int, np.ndarray] = {}  # T_map_base, with a map to localise in
        self.last_path: list = []
        # The node's odometry is latched: poses published before our reader was matched arrive.
        latched = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(
            Odometry, f'/{NODE_NAME}/odometry',
            lambda m: self.odometry.__setitem__(stamp_to_ns(m.header.stamp),
                                                odometry_to_pose(m)), latched)
        self.node.create_subscription(
            PathMsg, f'/{NODE_NAME}/path',
            lambda m: self.last_path.__setitem__(slice(None), [m]),
            QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.node.create_subscription(
            PointCloud2, f'/{NODE_NAME}/filtered_points',
            lambda m: self.kept_points.__setitem__(stamp_to_ns(m.header.stamp),
                                                   m.width * m.height),
            qos_profile_sensor_data)
        self.node.create_subscription(
            PoseWithCovarianceStamped, f'/{NODE_NAME}/map_pose',
            lambda m: self.map_poses.__setitem__(stamp_to_ns(m.header.stamp),
                                                 pose_matrix(m.pose.pose)), latched)
        self.clock_pub = self.node.create_publisher(Clock, '/clock', QoSProfile(depth=10))
        self.cloud_pub = self.node.create_publisher(
            PointCloud2, topic, QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        self.last_sent_s = 0.0

    def spin_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Spin until `done()` (True) or the timeout (False); NodeProcessError if it exits."""
        deadline = time.monotonic() + timeout_s
        while not done():
            if self.proc.poll() is not None:
                raise NodeProcessError(
                    f'filter_odom_node exited with code {self.proc.returncode}; its log: '
                    f'{self.node_log}\n{self.node_log.read_text()[-2000:]}')
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def wait_for_node(self) -> None:
        """Until the node subscribes to the clouds and publishes odometry, plus a margin."""
        if not self.spin_until(lambda: self.cloud_pub.get_subscription_count() > 0
                               and self.node.count_publishers(f'/{NODE_NAME}/odometry') > 0,
                               60.0):
            raise NodeProcessError(f'filter_odom_node did not come up within 60 s '
                                   f'({self.node_log})')
        # Seeing each other in the graph is not yet matched endpoints both ways: give DDS a
        # moment, or the first odometry can go out before our subscription is matched.
        self.spin_until(lambda: False, 2.0)

    def answer_to(self, stamp_ns: int) -> int | None:
        """The stamp of the odometry answering the sweep stamped `stamp_ns`: the node stamps a
        pose where it holds, within the sweep (at its stamp, or mid-sweep when it was not
        deskewed); None before it came."""
        if stamp_ns in self.odometry:
            return stamp_ns
        return next((k for k in self.odometry if 0 < k - stamp_ns < SWEEP_SPAN_NS), None)

    def send(self, msg, scan_timeout_s: float) -> int | None:
        """Publish the clock and the cloud, again until its odometry comes back: the
        odometry's stamp, None when none came."""
        stamp_ns = stamp_to_ns(msg.header.stamp)
        # Never faster than the sensor: back-to-back 0.5 MB best-effort clouds were seen to
        # be lost whole on this machine (every resend of the same scan).
        self.spin_until(lambda: False,
                        self.last_sent_s + MIN_SEND_INTERVAL_S - time.monotonic())
        self.clock_pub.publish(Clock(clock=ns_to_stamp(stamp_ns)))
        got = False
        deadline = time.monotonic() + scan_timeout_s
        while not got and time.monotonic() < deadline:
            self.cloud_pub.publish(msg)
            self.last_sent_s = time.monotonic()
            got = self.spin_until(lambda: self.answer_to(stamp_ns) is not None,
                                  RESEND_AFTER_S)
        return self.answer_to(stamp_ns)

    def save_map(self, timeout_s: float = 30.0) -> str:
        """Call the node's ~/save_map; its answer (where the files went)."""
        from std_srvs.srv import Trigger
        client = self.node.create_client(Trigger, f'/{NODE_NAME}/save_map')
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise NodeProcessError(f'~/save_map did not appear ({self.node_log})')
        for _ in range(3):  # the first answer can be lost while the reply path is matched
            future = client.call_async(Trigger.Request())
            if self.spin_until(future.done, 10.0):
                response = future.result()
                if not response.success:
                    raise NodeProcessError(f'~/save_map failed: {response.message}')
                return response.message
        raise NodeProcessError(f'~/save_map did not answer ({self.node_log})')

    def close(self) -> None:
        """Stop the feeder node and the node process."""
        stop_feeder(self.context, self.node, self.executor)
        stop_node_process(self.proc)


def replay_through_node(bag_paths: Sequence[str | Path], config: GftOdomConfig,
                        gt_path: str | Path | None = None, topic: str = '/velodyne_points',
                        max_scans: int | None = None,
                        progress: Callable[[int, int], None] | None = None,
                        node_exe: str | None = None, scan_timeout_s: float = 20.0,
                        env: dict[str, str] | None = None,
                        log_path: str | Path | None = None,
                        save_map_dir: str | Path | None = None) -> ReplayResult:
    """Feed the bag to a separate `filter_odom_node` process and record what it publishes;
    `save_map_dir`: at the end, the node's ~/save_map writes its map there."""
    exe = find_node_executable(node_exe)
    ground_truth = read_ground_truth(gt_path) if gt_path is not None else None
    proc, work, node_log, domain_id = _launch_node(
        exe, config, topic, dict(os.environ if env is None else env), log_path, save_map_dir)
    saved = None
    feeder = _Feeder(proc, node_log, domain_id, topic)
    stamps, scan_stamps, latency, points_in, statuses = [], [], [], [], []
    failed = True
    try:
        feeder.wait_for_node()
        with ScanBagReader(list(bag_paths), topic=topic) as reader:
            total = len(reader) if max_scans is None else min(len(reader), max_scans)
            for i, (_, raw) in enumerate(reader.iter_messages()):
                if i >= total:
                    break
                msg = ros_message_from_bag(raw)
                t0 = time.perf_counter()
                pose_stamp_ns = feeder.send(msg, scan_timeout_s)
                latency.append(time.perf_counter() - t0)
                if pose_stamp_ns is not None:
                    points_in.append(msg.width * msg.height)
                    stamps.append(pose_stamp_ns)
                    scan_stamps.append(stamp_to_ns(msg.header.stamp))
                    statuses.append('ok')
                else:
                    log.warning('no odometry for the scan at %d ns within %.0f s (the node '
                                'skipped it; see %s)', stamp_to_ns(msg.header.stamp),
                                scan_timeout_s, node_log)
                    statuses.append('no_answer')
                if progress is not None:
                    progress(i + 1, total)
            # The last filtered cloud, and the Path (the node sends it once a second).
            feeder.spin_until(lambda: False, 0.5)
            path_length = min(len(stamps), config.node.path_max_length)
            feeder.spin_until(lambda: bool(feeder.last_path)
                              and len(feeder.last_path[0].poses) >= path_length, 3.0)
            skipped = getattr(reader, 'skipped', 0)
        if save_map_dir is not None and stamps:
            saved = feeder.save_map()
        failed = not stamps
    finally:
        feeder.close()
        # The temporary folder goes, unless it holds the log an error message points to.
        if not (failed and node_log.parent == work):
            shutil.rmtree(work, ignore_errors=True)
    if not stamps:
        raise NodeProcessError(f'filter_odom_node answered none of the {len(statuses)} scans '
                               f'sent; its log: {node_log}')
    replay = _replay_result(config, feeder, stamps, scan_stamps, latency, points_in, statuses,
                            skipped, ground_truth, gt_path, node_log if log_path else None)
    if saved is not None:
        replay.metrics['saved_map'] = saved
    return replay


def _replay_result(config, feeder: _Feeder, stamps, scan_stamps, latency, points_in, statuses,
                   skipped, ground_truth, gt_path, node_log) -> ReplayResult:
    """The ReplayResult (and its metrics) of what the node answered."""
    base_poses = np.array([feeder.odometry[s] for s in stamps]).reshape(-1, 4, 4)
    base = Trajectory(np.array(stamps, dtype=np.int64), base_poses)
    sensor = Trajectory(base.stamps_ns,
                        base_to_sensor_poses(base.poses, base_to_sensor(config)))
    replay = ReplayResult(
        sensor_trajectory=sensor, base_trajectory=base, latency_s=np.asarray(latency),
        stage_s={'round_trip': np.asarray(latency)}, points_in=np.asarray(points_in),
        # Best-effort like every sensor stream: a lost filtered cloud counts as -1.
        points_kept=np.array([feeder.kept_points.get(s, -1) for s in scan_stamps]),
        statuses=statuses, skipped_messages=skipped, ground_truth=ground_truth,
        ground_truth_is_gps=gt_path is not None and is_gps_ground_truth(gt_path))
    located = [s for s in stamps if s in feeder.map_poses]
    if located:
        replay.map_trajectory = Trajectory(np.array(located, dtype=np.int64), base_to_sensor_poses(
            np.array([feeder.map_poses[s] for s in located]), base_to_sensor(config)))
        replay.localisation_counts = {'answered': len(located)}
    replay.metrics = summarize(replay, config)
    replay.metrics['node_path_length'] = (len(feeder.last_path[0].poses) if feeder.last_path
                                          else 0)
    if node_log is not None:
        replay.metrics['node_log'] = str(node_log)
    return replay
