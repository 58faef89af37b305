"""The node's localisation in a saved map: `map -> odom` and the pose in the map frame.

`localisation.map_file` (or `~/load_map` after setting it) loads a map `~/save_map` wrote; the
start pose comes from `localisation.initial_pose_xy_yaw` or `/initialpose`
(`geometry_msgs/PoseWithCovarianceStamped` in the map frame, as RViz's "2D Pose Estimate"
sends it). After each scan's odometry is out, the scan is matched to the map from the
odometry's prediction (core/localisation.py); the node publishes `map -> odom` on /tf (REP
105: localisation owns it, the odometry `odom -> base_link`) and `~/map_pose`. A map that is
missing, unreadable or in another frame is one error in the log and in `/diagnostics`; the
odometry goes on.
"""

from __future__ import annotations

import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_srvs.srv import Trigger

from gft_odom.core.localisation import MapLocalisation
from gft_odom.errors import GftOdomError
from gft_odom.replay import map_localisation
from gft_odom.ros.conversions import ns_to_stamp, pose_matrix, pose_msg, transform_msg

# /diagnostics WARNs when the map has not fitted a scan for this long.
NOT_FITTED_WARN_S = 2.0


class MapLocalisationMixin:
    """Mixin of the node (an rclpy Node with `config`, `pipeline`, `tf_pub`, `_warn`)."""

    localisation: MapLocalisation | None = None
    map_error: str | None = None
    last_fit = None
    _last_fitted_s: float | None = None

    def _start_localisation(self) -> None:
        self.map_pose_pub = self.create_publisher(
            PoseWithCovarianceStamped, '~/map_pose',
            QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.create_subscription(PoseWithCovarianceStamped, '/initialpose',
                                 self._on_initial_pose, 10)
        self.create_service(Trigger, '~/load_map', self._on_load_map)
        if self.config.localisation.map_file:
            self._load_map()

    def _load_map(self) -> bool:
        """Load `localisation.map_file`; on failure say why once and go on with odometry."""
        cfg = self.config.localisation
        self.localisation, self.last_fit, self._last_fitted_s = None, None, None
        try:
            self.localisation = map_localisation(self.config, self.pipeline.T_base_sensor)
        except GftOdomError as exc:
            self.map_error = str(exc)
            self.get_logger().error(f'localisation off, odometry goes on: {exc}')
            return False
        self.map_error = None
        n_points = self.localisation.prior.points_xyz.shape[0]
        self.get_logger().info(f'map {cfg.map_file}: {n_points} points; '
                               f'starting at {list(cfg.initial_pose_xy_yaw)} '
                               f'({cfg.map_frame} frame) at the next scan')
        return True

    def _reconfigure_localisation(self, old_config) -> None:
        """A new `localisation.map_file` at run time: load it (empty: localisation off)."""
        if self.config.localisation.map_file == old_config.localisation.map_file:
            return
        if self.config.localisation.map_file:
            self._load_map()
        else:
            self.localisation, self.map_error, self.last_fit = None, None, None

    def _on_load_map(self, request, response):
        """`~/load_map`: (re)load `localisation.map_file`."""
        response.success = bool(self.config.localisation.map_file) and self._load_map()
        response.message = ('map loaded' if response.success else
                            self.map_error or 'localisation.map_file is empty')
        return response

    def _on_initial_pose(self, msg: PoseWithCovarianceStamped) -> None:
        """RViz's "2D Pose Estimate": where base_link is in the map now."""
        frame = self.config.localisation.map_frame
        if msg.header.frame_id.lstrip('/') != frame:
            self._warn('initial_pose', f'/initialpose in frame {msg.header.frame_id!r} '
                       f'ignored: it must be in {frame!r}')
            return
        if self.localisation is None:
            self._warn('initial_pose', '/initialpose ignored: no map is loaded '
                       '(set localisation.map_file)')
            return
        q = msg.pose.pose.orientation
        with np.errstate(invalid='ignore', divide='ignore'):
            T = pose_matrix(msg.pose.pose)
        if not (np.all(np.isfinite(T)) and np.linalg.norm([q.x, q.y, q.z, q.w]) > 0.5):
            self._warn('initial_pose', '/initialpose ignored: it is not finite')
            return
        self.localisation.start_at(T)
        self.get_logger().info(f'initial pose set in {frame}: x {T[0, 3]:.2f} y {T[1, 3]:.2f}')

    def _localise(self, result) -> None:
        """The scan whose odometry is out, in the map: map -> odom and ~/map_pose."""
        if self.localisation is None or not result.accepted:
            return
        points = self.pipeline.registration.deskewed_like_last(result.filtered.points_xyz)
        fit = self.localisation.localise(points, result.T_world_sensor, result.nu)
        if fit is None:
            return
        self.last_fit = fit
        self.counters[f'map_{fit.status}'] += 1
        if fit.status == 'localised':
            self._last_fitted_s = time.monotonic()
        cfg, node_cfg = self.config.localisation, self.config.node
        if self.tf_pub is not None:
            self.tf_pub.send(transform_msg(fit.T_map_odom, result.stamp_ns, cfg.map_frame,
                                           node_cfg.odom_frame))
        msg = PoseWithCovarianceStamped()
        msg.header.stamp = ns_to_stamp(result.stamp_ns)
        msg.header.frame_id = cfg.map_frame
        msg.pose.pose = pose_msg(self.localisation.base_pose(fit))
        msg.pose.covariance = [float(v) for v in fit.covariance.reshape(36)]
        self.map_pose_pub.publish(msg)

    def localisation_status(self) -> DiagnosticStatus:
        """`<node>: localisation`: OK while the map fits, WARN when it has not for a while or
        no start pose is set, ERROR when the map could not be loaded."""
        status = DiagnosticStatus(name=f'{self.get_name()}: localisation',
                                  hardware_id=self.config.localisation.map_frame)
        if self.map_error is not None:
            status.level, status.message = DiagnosticStatus.ERROR, self.map_error
        elif self.localisation is None:
            status.level, status.message = DiagnosticStatus.OK, 'no map (odometry only)'
        elif self.last_fit is None:
            status.level, status.message = DiagnosticStatus.WARN, 'map loaded, waiting for a scan'
        else:
            since = (None if self._last_fitted_s is None
                     else time.monotonic() - self._last_fitted_s)
            fits = since is not None and since < NOT_FITTED_WARN_S
            status.level = DiagnosticStatus.OK if fits else DiagnosticStatus.WARN
            status.message = ('the scans fit the map' if fits else
                              'the scans do not fit the map: the odometry carries the pose')
            status.values = [KeyValue(key='fitness', value=f'{self.last_fit.fitness:.3f}'),
                             KeyValue(key='inlier_rmse_m',
                                      value=f'{self.last_fit.inlier_rmse_m:.3f}'),
                             KeyValue(key='last_status', value=self.last_fit.status)]
        return status
