"""`filter_odom_node`: VLP-16 PointCloud2 in, graph-frequency filtered odometry out.

Subscribes `points` (remap it to `/velodyne_points`) with the publishers' reliability (like
rosbag2: reliable when every publisher is, else best effort; `node.input_reliability`);
publishes `~/filtered_points`, `~/odometry` (odom -> base_link, REP 105, pose and twist),
`~/path`, `/tf` and `/diagnostics`; serves `~/reset` and `~/save_map`. The input and the three
`~/` outputs take REP-2003 QoS overrides (`qos_overrides.<topic>.<publisher|subscription>.
<reliability|depth|history|durability>` in the params file). Parameters are declared from the
`GftOdomConfig` dataclasses, so their defaults live in one place. Bad input is logged
(rate-limited) and skipped: the node keeps running.
"""

from __future__ import annotations

import collections
import datetime
import signal
import sys
import time
from pathlib import Path as FilePath

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import SetParametersResult
from rclpy._rclpy_pybind11 import RCLError
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from gft_odom.config import GftOdomConfig, flatten, with_values
from gft_odom.core.constants import NODE_NAME, NS_PER_S
from gft_odom.core.degeneracy import weakest_translation
from gft_odom.core.trajectory import Trajectory
from gft_odom.core.twist import base_twist, base_twist_covariance, unknown_twist_covariance
from gft_odom.errors import GftOdomError
from gft_odom.io.pointcloud2 import decode_scan, encode_cloud
from gft_odom.pipeline import FrameResult, OdometryPipeline
from gft_odom.replay import write_map
from gft_odom.ros.conversions import blob_to_msg, odometry_msg, pose_stamped_msg, transform_msg
from gft_odom.ros.dds import use_large_message_profile
from gft_odom.ros.diagnostics import OdometryDiagnostics, diagnostic_array, stale_scan_text
from gft_odom.ros.input_qos import AdaptiveInput, overridable
from gft_odom.ros.localisation import MapLocalisationMixin
from gft_odom.ros.log_bridge import forward_python_logging, stop_forwarding
from gft_odom.ros.parameters import (
    check_overrides,
    check_params_files,
    descriptor,
    is_startup_only,
)
from gft_odom.ros.tf import make_tf_publisher

WARN_PERIOD_S = 5.0
SUMMARY_PERIOD_S = 10.0
DIAGNOSTICS_PERIOD_S = 1.0
# The Path holds up to node.path_max_length poses: sent at most this often, and only to
# subscribers, so its cost per scan stays bounded (it was 38 ms a scan at 5 000 poses).
PATH_PERIOD_S = 1.0
# Stamp differences kept to estimate the sensor period (5, 10 or 20 Hz VLP-16).
PERIOD_SAMPLES = 21
def _ros_value(value):
    """Dataclass value -> a value rclpy can declare (tuples become lists)."""
    return list(value) if isinstance(value, tuple) else value


class FilterOdomNode(AdaptiveInput, MapLocalisationMixin, Node):
    """Runs `OdometryPipeline` on every incoming scan and publishes its results."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        # A misspelled key in the params file would otherwise be ignored without a word.
        check_overrides(self._parameter_overrides)
        for name, value in flatten(GftOdomConfig()).items():
            self.declare_parameter(name, _ros_value(value), descriptor(name))
        # Raises ConfigError with the reason when the params file holds an invalid value.
        self.config = with_values(GftOdomConfig(), {
            name: self.get_parameter(name).value for name in flatten(GftOdomConfig())})
        # Once nothing can refuse the start any more (destroy_node undoes it).
        self._log_handler = forward_python_logging(self.get_logger(), WARN_PERIOD_S)
        self.pipeline = OdometryPipeline(self.config)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.counters = collections.Counter()
        # Rate limit per kind of problem (rclpy's throttle is per call site, so one kind would
        # silence the others): the first of each kind is always logged.
        self._last_warned_s: dict[str, float] = {}
        self.latencies_s: collections.deque[float] = collections.deque(maxlen=600)
        # Per scan: the latency and the map update after it (what the sensor period must hold).
        self.busy_s: collections.deque[float] = collections.deque(maxlen=600)
        self.path = Path()
        self.path_poses: collections.deque = collections.deque(
            maxlen=self.config.node.path_max_length)
        self.last_stamp_ns: int | None = None
        self.last_received_stamp_ns: int | None = None
        self.last_frame_id: str | None = None
        self._stamp_steps_ns: collections.deque[int] = collections.deque(maxlen=PERIOD_SAMPLES)
        self._path_dirty = False
        # For the twist and the weakest direction: the last registered frame.
        self.last_result: FrameResult | None = None
        self._weak = None

        # Reliable: matches both reliable (RViz's default) and best-effort subscribers; keep
        # last 1, so a slow subscriber costs the newest cloud only.
        self.cloud_pub = self.create_publisher(
            PointCloud2, '~/filtered_points',
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE),
            qos_overriding_options=overridable())
        # Transient local (latched): a subscriber that joins late (a recorder, RViz, a replay
        # harness whose reader is still being matched) still gets the recent poses and the
        # path. Volatile subscribers are compatible with it.
        latched = DurabilityPolicy.TRANSIENT_LOCAL
        self.odom_pub = self.create_publisher(Odometry, '~/odometry',
                                              QoSProfile(depth=50, durability=latched),
                                              qos_overriding_options=overridable())
        self.path_pub = self.create_publisher(Path, '~/path',
                                              QoSProfile(depth=1, durability=latched),
                                              qos_overriding_options=overridable())
        self.tf_pub = make_tf_publisher(self) if self.config.node.publish_tf else None
        self.diagnostics = OdometryDiagnostics()
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/save_map', self._on_save_map)
        self._start_localisation()
        # Wall-clock timers: with use_sim_time the ROS clock only moves with /clock (a lockstep
        # replay advances it 0.1 s per scan), and these are about the process, not the data.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.input_sub = None
        self.input_reliability: ReliabilityPolicy | None = None
        self._subscribe_input(steady)
        self.create_timer(SUMMARY_PERIOD_S, self._log_summary, clock=steady)
        self.create_timer(PATH_PERIOD_S, self._publish_path, clock=steady)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, clock=steady)
        self.get_logger().info(
            f'ready: filter {"on" if self.pipeline.use_filter else "off (or all-pass)"} '
            f'(n_bands={self.config.spectral.n_bands}, band_mask='
            f'{list(self.config.spectral.band_mask)}), registration mode '
            f'{self.config.registration.mode}')

    # -- parameters ------------------------------------------------------------------------

    def _on_set_parameters(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params if p.name in flatten(self.config)}
        fixed = sorted(n for n in changes if is_startup_only(n)
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
        old_config, self.config = self.config, new_config
        self.pipeline.reconfigure(new_config)
        self.path_poses = collections.deque(self.path_poses,
                                            maxlen=new_config.node.path_max_length)
        self._reconfigure_localisation(old_config)
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
        odometry_out_s = self._publish(result, msg.header)
        latency_s = odometry_out_s - t0
        self.latencies_s.append(latency_s)
        try:
            self._localise(result)
        except Exception as exc:  # the odometry is out; a failed localisation costs only it
            self._warn('failed', f'localising the scan at {scan.stamp_ns} ns failed: {exc!r}')
        # The map work a keyframe leaves, once the odometry is out (the next scan waits).
        try:
            self.pipeline.update_map()
        except Exception as exc:  # the next scan retries nothing: its map is the old one
            self._warn('failed', f'map update after the scan at {scan.stamp_ns} ns failed '
                       f'(bug?): {exc!r}')
        self.busy_s.append(time.perf_counter() - t0)
        self.counters['processed'] += 1
        if result.fell_back:
            self._warn('fallback', f'registration fell back to the motion prediction '
                       f'({result.status}, {result.n_points_kept} points kept)')
        self.get_logger().debug(
            f'scan {scan.stamp_ns}: decode {1e3 * (t_decoded - t0):.1f} ms, '
            + ', '.join(f'{k} {1e3 * v:.1f} ms' for k, v in result.timings_s.items()))

    def scan_period_s(self) -> float:
        """The sensor period: the median recent stamp step, else registration.scan_period_s."""
        if len(self._stamp_steps_ns) >= 3:
            return float(np.median(self._stamp_steps_ns)) * 1e-9
        return self.config.registration.scan_period_s

    def _count_missed(self, stamp_ns: int) -> None:
        """Sweeps that never reached this callback (queue overwritten, link loss); a step of
        the stamps beyond registration.max_gap_s is a gap or a clock jump, not lost sweeps."""
        last = self.last_received_stamp_ns
        self.last_received_stamp_ns = stamp_ns
        if last is None or not 0 < stamp_ns - last <= (
                self.config.registration.max_gap_s * NS_PER_S):
            return
        period_s = self.scan_period_s()
        self._stamp_steps_ns.append(stamp_ns - last)
        missed = int(round((stamp_ns - last) * 1e-9 / period_s)) - 1
        if missed > 0:
            self._warn('missed', f'{missed} sweep(s) never arrived before the one at '
                       f'{stamp_ns} ns (processing slower than the sensor, or lost; '
                       f'sensor period estimated from the stamps: {period_s:.3f} s)')
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
            self._warn('stale', stale_scan_text(age_s, self.get_parameter('use_sim_time').value,
                                                self.config.node.max_scan_age_s))
            return False
        if self.last_frame_id is not None and scan.frame_id != self.last_frame_id:
            self._warn('frame_changed', f'scan frame_id changed from {self.last_frame_id!r} to '
                       f'{scan.frame_id!r}; using it as the same sensor')
        self.last_frame_id = scan.frame_id
        self.last_stamp_ns = scan.stamp_ns
        return True

    def twist_of(self, result: FrameResult) -> tuple[np.ndarray, np.ndarray]:
        """base_link's twist in its own axes (linear first) and its covariance (core/twist.py):
        the motion model's velocity after a match, zero with the bounds as std otherwise."""
        reg_cfg = self.config.registration
        last = self.last_result
        step_s = ((result.stamp_ns - last.stamp_ns) * 1e-9
                  if last is not None and result.stamp_ns > last.stamp_ns
                  else self.scan_period_s())
        if result.fell_back or result.status == 'first' or not np.any(result.twist):
            return np.zeros(6), unknown_twist_covariance(reg_cfg.max_speed_mps,
                                                         reg_cfg.max_yaw_rate_rps)
        T_base_sensor = self.pipeline.T_base_sensor
        return (base_twist(result.twist, T_base_sensor, step_s),
                base_twist_covariance(result.covariance, result.T_world_sensor[:3, :3],
                                      T_base_sensor, step_s))

    def _publish(self, result: FrameResult, header) -> float:
        """Publish the scan's odometry, transform and cloud; when the odometry and the
        transform were out (`time.perf_counter`): the latency the node reports ends there."""
        node_cfg = self.config.node
        stamp_ns = result.stamp_ns
        twist, twist_cov = self.twist_of(result)
        odom = odometry_msg(result.T_odom_base, stamp_ns, node_cfg.odom_frame,
                            node_cfg.base_frame, result.covariance, twist, twist_cov)
        self.odom_pub.publish(odom)
        if result.information is not None:
            # The information is in the world (first sensor) axes: into base_link's.
            R_base_world = (self.pipeline.T_base_sensor[:3, :3]
                            @ result.T_world_sensor[:3, :3].T)
            self._weak = weakest_translation(result.information, R_base_world)
        self.last_result = result
        self.path_poses.append(pose_stamped_msg(result.T_odom_base, stamp_ns,
                                                node_cfg.odom_frame))
        self.path.header.stamp = odom.header.stamp
        self._path_dirty = True
        if self.tf_pub is not None:
            self.tf_pub.send(transform_msg(result.T_odom_base, stamp_ns, node_cfg.odom_frame,
                                           node_cfg.base_frame))
        odometry_out_s = time.perf_counter()
        if node_cfg.publish_filtered_points and self.cloud_pub.get_subscription_count() > 0:
            scan = result.filtered
            columns = {'x': scan.points_xyz[:, 0].astype(np.float32),
                       'y': scan.points_xyz[:, 1].astype(np.float32),
                       'z': scan.points_xyz[:, 2].astype(np.float32),
                       'intensity': (scan.intensity if scan.intensity is not None
                                     else np.zeros(len(scan), np.float32)).astype(np.float32)}
            nu = result.nu  # computed now when they come after the pose (the odometry is out)
            if nu is not None:
                columns['frequency'] = nu.astype(np.float32)
                columns['band'] = result.band.astype(np.uint8)
            # The cloud keeps its sweep's stamp (the driver's); the pose is stamped where it
            # holds (mid-sweep when the sweep was not deskewed).
            self.cloud_pub.publish(blob_to_msg(encode_cloud(columns), int(scan.stamp_ns),
                                               header.frame_id))
        return odometry_out_s

    def _publish_path(self) -> None:
        """The whole bounded Path, when it changed and someone listens (timer)."""
        if not self._path_dirty or self.path_pub.get_subscription_count() == 0:
            return
        self.path.header.frame_id = self.config.node.odom_frame
        self.path.poses = list(self.path_poses)
        self.path_pub.publish(self.path)
        self._path_dirty = False

    def _publish_diagnostics(self) -> None:
        assessment = self.diagnostics.assess(
            time.monotonic(), self.counters, list(self.latencies_s)[-100:],
            self.scan_period_s(), busy_s=list(self.busy_s)[-100:], weak=self._weak,
            weak_warn_ratio=self.config.node.weak_direction_warn_ratio,
            bounds_message=self.pipeline.bounds_watch.message)
        array = diagnostic_array(assessment, self.get_clock().now().to_msg(),
                                 f'{self.get_name()}: odometry', self.last_frame_id or 'lidar')
        array.status.append(self.localisation_status())
        self.diagnostics_pub.publish(array)

    def _on_reset(self, request, response):
        """`~/reset`: start the odometry again from the identity, with an empty map."""
        self.pipeline.reset()
        self.pipeline.finished_segments.clear()  # the trajectory starts again too
        self.path_poses.clear()
        self._path_dirty = True
        self.last_result = None
        self._weak = None
        self.last_stamp_ns = None
        self.last_received_stamp_ns = None
        self._stamp_steps_ns.clear()
        self.counters['reset'] += 1
        self.get_logger().info('odometry reset: the next scan starts at the identity')
        response.success = True
        response.message = 'odometry reset'
        return response

    def trajectory(self) -> Trajectory:
        """T_odom_base of every published scan since the start, the last reset or a clock
        reset (the run the map belongs to)."""
        return self.pipeline.base_trajectory()

    def _on_save_map(self, request, response):
        """`~/save_map`: the map (binary PCD with frequencies) and the trajectory (TUM), in the
        odom frame, into a new folder under node.save_map_dir; the response says where."""
        stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%d_%H%M%S_%f')
        folder = FilePath(self.config.node.save_map_dir).expanduser() / f'map_{stamp}'
        try:
            points, nu = self.pipeline.map_snapshot()
            trajectory = self.trajectory()
            pcd, tum = write_map(folder, points, nu, self.config.spectral.n_bands, trajectory,
                                 self.config.node.odom_frame)
        except (OSError, GftOdomError) as exc:
            response.success = False
            response.message = f'map not saved to {folder}: {exc}'
            self.get_logger().error(response.message)
            return response
        response.success = True
        response.message = (f'saved {points.shape[0]} map points ({int(np.isfinite(nu).sum())} '
                            f'with a frequency) to {pcd.resolve()} and {len(trajectory)} poses '
                            f'to {tum.resolve()} ({self.config.node.odom_frame} frame)')
        self.get_logger().info(response.message)
        return response

    def destroy_node(self) -> None:
        """Log the final counts, stop forwarding Python logging, then destroy."""
        stop_forwarding(self._log_handler)
        super().destroy_node()

    def _log_summary(self, final: bool = False) -> None:
        """Latency and the count of every kind of problem (all of them at shutdown)."""
        counts = ', '.join(f'{k}={v}' for k, v in sorted(self.counters.items()))
        if final:
            self.get_logger().info(f'final counts: {counts or "nothing received"}')
            return
        if not self.latencies_s:
            return
        lat_ms = 1e3 * np.asarray(self.latencies_s)
        busy_ms = 1e3 * np.asarray(self.busy_s) if self.busy_s else lat_ms
        self.get_logger().info(f'latency median {np.median(lat_ms):.1f} ms, p95 '
                               f'{np.percentile(lat_ms, 95):.1f} ms (with the map update: '
                               f'mean {np.mean(busy_ms):.1f} ms) over the last '
                               f'{lat_ms.size} scans; {counts}')


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def main(args=None) -> None:
    """Entry point of `ros2 run gft_odom filter_odom_node`."""
    node = None
    try:
        check_params_files(sys.argv if args is None else args)
        profile = use_large_message_profile()
        # Our own SIGINT/SIGTERM handling: rclpy's would shut the context down before the final
        # counts are logged ("Failed to publish log message to rosout").
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        signal.signal(signal.SIGINT, _interrupt)
        signal.signal(signal.SIGTERM, _interrupt)
        node = FilterOdomNode()
        if profile:
            node.get_logger().info(f'Fast DDS profile for large messages: {profile}')
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (GftOdomError, ParameterException, RCLError) as exc:
        # Only reachable at start-up (a missing, unreadable or invalid params file).
        text = str(exc).split(', at /')[0]  # rcl appends C source locations
        rclpy.logging.get_logger(NODE_NAME).fatal(f'cannot start: {text}')
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node._log_summary(final=True)
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
