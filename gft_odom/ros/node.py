"""`filter_odom_node`: VLP-16 PointCloud2 in, graph-frequency filtered odometry out.

Subscribes `points` (remap it to `/velodyne_points`) with sensor-data QoS; publishes
`~/filtered_points`, `~/odometry` (odom -> base_link, REP 105) and `~/path`. Parameters are
declared from the `GftOdomConfig` dataclasses, so their defaults live in one place. Bad input is
logged (rate-limited) and skipped: the node keeps running.
"""

from __future__ import annotations

import collections
import time

import numpy as np
import rclpy
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2

from gft_odom.config import GftOdomConfig, flatten, with_values
from gft_odom.core.constants import NODE_NAME, NS_PER_S
from gft_odom.errors import GftOdomError
from gft_odom.io.pointcloud2 import decode_scan, encode_cloud
from gft_odom.pipeline import FrameResult, OdometryPipeline
from gft_odom.ros.conversions import blob_to_msg, odometry_msg, pose_stamped_msg, transform_msg

# Sections whose values are only read when the pipeline starts (a change needs a restart).
STARTUP_ONLY_PREFIXES = ('registration.', 'node.odom_frame', 'node.base_frame', 'evaluation.',
                         'node.base_to_sensor', 'node.publish_tf', 'ground_truth.',
                         'node.input_queue_depth', 'node.input_reliable')
WARN_PERIOD_S = 5.0
SUMMARY_PERIOD_S = 10.0


def _ros_value(value):
    """Dataclass value -> a value rclpy can declare (tuples become lists)."""
    return list(value) if isinstance(value, tuple) else value


class FilterOdomNode(Node):
    """Runs `OdometryPipeline` on every incoming scan and publishes its results."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        for name, value in flatten(GftOdomConfig()).items():
            self.declare_parameter(name, _ros_value(value),
                                   ParameterDescriptor(description=f'gft_odom.config: {name}'))
        # Raises ConfigError with the reason when the params file holds an invalid value.
        self.config = with_values(GftOdomConfig(), {
            name: self.get_parameter(name).value for name in flatten(GftOdomConfig())})
        self.pipeline = OdometryPipeline(self.config, record_trajectory=False)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.counters = collections.Counter()
        # Rate limit per kind of problem (rclpy's throttle is per call site, so one kind would
        # silence the others): the first of each kind is always logged.
        self._last_warned_s: dict[str, float] = {}
        self.latencies_s: collections.deque[float] = collections.deque(maxlen=600)
        self.path = Path()
        self.path_poses: collections.deque = collections.deque(
            maxlen=self.config.node.path_max_length)
        self.last_stamp_ns: int | None = None
        self.last_received_stamp_ns: int | None = None
        self.last_frame_id: str | None = None

        self.cloud_pub = self.create_publisher(PointCloud2, '~/filtered_points',
                                               qos_profile_sensor_data)
        # Transient local (latched): a subscriber that joins late (a recorder, RViz, a replay
        # harness whose reader is still being matched) still gets the recent poses and the
        # path. Volatile subscribers are compatible with it.
        latched = DurabilityPolicy.TRANSIENT_LOCAL
        self.odom_pub = self.create_publisher(Odometry, '~/odometry',
                                              QoSProfile(depth=50, durability=latched))
        self.path_pub = self.create_publisher(Path, '~/path',
                                              QoSProfile(depth=1, durability=latched))
        self.tf_broadcaster = self._make_tf_broadcaster()
        input_qos = QoSProfile(depth=self.config.node.input_queue_depth,
                               reliability=(ReliabilityPolicy.RELIABLE
                                            if self.config.node.input_reliable
                                            else qos_profile_sensor_data.reliability),
                               durability=qos_profile_sensor_data.durability,
                               history=qos_profile_sensor_data.history)
        self.create_subscription(PointCloud2, 'points', self._on_cloud, input_qos)
        self.create_timer(SUMMARY_PERIOD_S, self._log_summary)
        self.get_logger().info(
            f'ready: filter {"on" if self.pipeline.use_filter else "off (or all-pass)"} '
            f'(n_bands={self.config.spectral.n_bands}, band_mask='
            f'{list(self.config.spectral.band_mask)}), registration mode '
            f'{self.config.registration.mode}')

    def _make_tf_broadcaster(self):
        if not self.config.node.publish_tf:
            return None
        try:
            from tf2_ros import TransformBroadcaster
        except ImportError:
            self.get_logger().warning('tf2_ros cannot be imported: the odom -> base_link '
                                      'transform is not published on /tf (odometry still is)')
            return None
        return TransformBroadcaster(self)

    # -- parameters ------------------------------------------------------------------------

    def _on_set_parameters(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params if p.name in flatten(self.config)}
        fixed = sorted(n for n in changes if n.startswith(STARTUP_ONLY_PREFIXES)
                       and changes[n] != _ros_value(flatten(self.config)[n]))
        if fixed:
            return SetParametersResult(
                successful=False,
                reason=f'{", ".join(fixed)} can only be set at start-up; restart the node')
        try:
            new_config = with_values(self.config, changes)
        except GftOdomError as exc:
            self.get_logger().warning(f'parameter change refused: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        self.config = new_config
        self.pipeline.reconfigure(new_config)
        self.path_poses = collections.deque(self.path_poses,
                                            maxlen=new_config.node.path_max_length)
        return SetParametersResult(successful=True)

    # -- per scan --------------------------------------------------------------------------

    def _warn(self, kind: str, text: str) -> None:
        """Count the problem; log it unless the same kind was logged < WARN_PERIOD_S ago."""
        self.counters[kind] += 1
        now_s = time.monotonic()
        last_s = self._last_warned_s.get(kind)
        if last_s is not None and now_s - last_s < WARN_PERIOD_S:
            return
        self._last_warned_s[kind] = now_s
        self.get_logger().warning(f'{text} ({kind} so far: {self.counters[kind]})')

    def _on_cloud(self, msg: PointCloud2) -> None:
        t0 = time.perf_counter()
        try:
            scan = decode_scan(msg)
        except GftOdomError as exc:
            self._warn('malformed', f'skipping malformed PointCloud2: {exc}')
            return
        except Exception as exc:  # a hostile message must never take the node down
            self._warn('malformed', f'skipping PointCloud2 that failed to decode: {exc!r}')
            return
        if not self._accept(scan):
            return
        t_decoded = time.perf_counter()
        try:
            result = self.pipeline.register_frame(scan)
        except GftOdomError as exc:
            self._warn('failed', f'scan at {scan.stamp_ns} ns not processed: {exc}')
            return
        except Exception as exc:  # an exception in a callback would end rclpy.spin
            self._warn('failed', f'scan at {scan.stamp_ns} ns not processed (bug?): {exc!r}')
            return
        self._publish(result, msg.header)
        latency_s = time.perf_counter() - t0
        self.latencies_s.append(latency_s)
        self.counters['processed'] += 1
        if result.fell_back:
            self._warn('fallback', f'registration fell back to the motion prediction '
                       f'({result.status}, {result.n_points_kept} points kept)')
        self.get_logger().debug(
            f'scan {scan.stamp_ns}: decode {1e3 * (t_decoded - t0):.1f} ms, '
            + ', '.join(f'{k} {1e3 * v:.1f} ms' for k, v in result.timings_s.items()))

    def _count_missed(self, stamp_ns: int) -> None:
        """Sweeps that never reached this callback (queue overwritten, link loss); a step of
        the stamps beyond registration.max_gap_s is a gap or a clock jump, not lost sweeps."""
        last = self.last_received_stamp_ns
        self.last_received_stamp_ns = stamp_ns
        if last is None or not 0 < stamp_ns - last <= (
                self.config.registration.max_gap_s * NS_PER_S):
            return
        period_ns = self.config.registration.scan_period_s * NS_PER_S
        missed = int(round((stamp_ns - last) / period_ns)) - 1
        if missed > 0:
            self._warn('missed', f'{missed} sweep(s) never arrived before the one at '
                       f'{stamp_ns} ns (processing slower than the sensor, or lost)')
            self.counters['missed'] += missed - 1

    def _accept(self, scan) -> bool:
        """The pipeline's acceptance (the replay and the offline tools apply the same), then
        the node's own checks: a scan that arrives too late to matter, a changed frame."""
        rejection = self.pipeline.screen(scan)
        if rejection is not None:
            self.pipeline.register_frame(scan)  # counts it, remembers a stamp jump
            self._warn(rejection.reason, rejection.text)
            return False
        self._count_missed(scan.stamp_ns)
        now_ns = self.get_clock().now().nanoseconds
        age_s = (now_ns - scan.stamp_ns) * 1e-9
        if now_ns > 0 and age_s > self.config.node.max_scan_age_s:
            self._warn('stale', f'dropping scan {age_s:.2f} s old (processing lags; '
                       f'max_scan_age_s={self.config.node.max_scan_age_s})')
            return False
        if self.last_frame_id is not None and scan.frame_id != self.last_frame_id:
            self._warn('frame_changed', f'scan frame_id changed from {self.last_frame_id!r} to '
                       f'{scan.frame_id!r}; using it as the same sensor')
        self.last_frame_id = scan.frame_id
        self.last_stamp_ns = scan.stamp_ns
        return True

    def _publish(self, result: FrameResult, header) -> None:
        node_cfg = self.config.node
        stamp_ns = result.stamp_ns
        odom = odometry_msg(result.T_odom_base, stamp_ns, node_cfg.odom_frame,
                            node_cfg.base_frame, result.covariance)
        self.odom_pub.publish(odom)
        self.path_poses.append(pose_stamped_msg(result.T_odom_base, stamp_ns,
                                                node_cfg.odom_frame))
        self.path.header.stamp = odom.header.stamp
        self.path.header.frame_id = node_cfg.odom_frame
        self.path.poses = list(self.path_poses)
        self.path_pub.publish(self.path)
        if self.tf_broadcaster is not None:
            self.tf_broadcaster.sendTransform(transform_msg(
                result.T_odom_base, stamp_ns, node_cfg.odom_frame, node_cfg.base_frame))
        if node_cfg.publish_filtered_points and self.cloud_pub.get_subscription_count() > 0:
            scan = result.filtered
            columns = {'x': scan.points_xyz[:, 0].astype(np.float32),
                       'y': scan.points_xyz[:, 1].astype(np.float32),
                       'z': scan.points_xyz[:, 2].astype(np.float32),
                       'intensity': (scan.intensity if scan.intensity is not None
                                     else np.zeros(len(scan), np.float32)).astype(np.float32)}
            if result.nu is not None:
                columns['frequency'] = result.nu.astype(np.float32)
                columns['band'] = result.band.astype(np.uint8)
            self.cloud_pub.publish(blob_to_msg(encode_cloud(columns), stamp_ns, header.frame_id))

    def _log_summary(self, final: bool = False) -> None:
        """Latency and the count of every kind of problem (all of them at shutdown)."""
        counts = ', '.join(f'{k}={v}' for k, v in sorted(self.counters.items()))
        if final:
            self.get_logger().info(f'final counts: {counts or "nothing received"}')
            return
        if not self.latencies_s:
            return
        lat_ms = 1e3 * np.asarray(self.latencies_s)
        self.get_logger().info(f'latency median {np.median(lat_ms):.1f} ms, p95 '
                               f'{np.percentile(lat_ms, 95):.1f} ms over the last '
                               f'{lat_ms.size} scans; {counts}')


def main(args=None) -> None:
    rclpy.init(args=args)
    node = None
    try:
        node = FilterOdomNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (GftOdomError, ParameterException) as exc:
        # Only reachable at start-up (invalid params file): nothing to keep running.
        rclpy.logging.get_logger(NODE_NAME).fatal(f'cannot start: {exc}')
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node._log_summary(final=True)
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
