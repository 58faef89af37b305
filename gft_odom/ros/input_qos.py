"""The node's input subscription: as reliable as its publishers (rosbag2's rule), or forced.

`node.input_reliability: auto` subscribes as the publishers of the input topic are and looks
again every INPUT_QOS_CHECK_S; a REP-2003 `qos_overrides` reliability in the params file, or
`reliable` / `best_effort`, fixes it.
"""

from __future__ import annotations

import collections

from rclpy.clock import Clock
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSPolicyKind,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import PointCloud2

# node.input_reliability auto: how often the publishers of the input topic are looked at.
INPUT_QOS_CHECK_S = 0.5
# The QoS policies a params file may override (REP 2003) on the input and the ~/ outputs.
OVERRIDABLE = (QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH, QoSPolicyKind.RELIABILITY,
               QoSPolicyKind.DURABILITY)
RELIABILITY_NAMES = {ReliabilityPolicy.RELIABLE: 'reliable',
                     ReliabilityPolicy.BEST_EFFORT: 'best_effort'}


def overridable(*kinds) -> QoSOverridingOptions:
    """REP-2003 overrides of `kinds` (declared read-only parameters, set from a params file)."""
    return QoSOverridingOptions(kinds or OVERRIDABLE)


def adaptive_reliability(publisher_reliabilities) -> ReliabilityPolicy | None:
    """rosbag2's rule: reliable when every publisher is reliable, best effort when any is
    best effort, None when there is no publisher (nothing to decide yet)."""
    found = list(publisher_reliabilities)
    if not found:
        return None
    if all(r == ReliabilityPolicy.RELIABLE for r in found):
        return ReliabilityPolicy.RELIABLE
    return ReliabilityPolicy.BEST_EFFORT


class AdaptiveInput:
    """Mixin of the node (an rclpy Node with `config` and `_on_cloud`): the input subscription."""

    input_sub = None
    input_reliability: ReliabilityPolicy | None = None

    @property
    def input_topic(self) -> str:
        """The input topic after remapping (`points` -> e.g. /velodyne_points)."""
        return self.resolve_topic_name('points')

    def _reliability_override(self) -> str | None:
        """The REP-2003 reliability override of the input from the params file, if any."""
        name = f'qos_overrides.{self.input_topic}.subscription.reliability'
        override = self._parameter_overrides.get(name)
        return None if override is None else str(override.value)

    def _subscribe_input(self, steady: Clock) -> None:
        """Forced reliability: subscribe now. Auto: subscribe as the publishers are, and look
        again every INPUT_QOS_CHECK_S (a publisher that comes, goes or changes)."""
        forced = self._reliability_override()
        mode = self.config.node.input_reliability
        if forced is not None or mode != 'auto':
            policy = (ReliabilityPolicy.RELIABLE if mode == 'reliable'
                      else ReliabilityPolicy.BEST_EFFORT)
            how = ('the qos_overrides parameter' if forced is not None
                   else f'node.input_reliability: {mode}')
            self._create_input(policy, how)
            return
        self._check_input_qos()
        if self.input_sub is None:
            self.get_logger().info(f'input {self.input_topic}: no publisher yet; subscribing '
                                   'as the first one is (node.input_reliability: auto)')
        self.create_timer(INPUT_QOS_CHECK_S, self._check_input_qos, clock=steady)

    def _check_input_qos(self) -> None:
        """Auto: (re)subscribe when the publishers' reliability asks for another one."""
        publishers = self.get_publishers_info_by_topic(self.input_topic)
        policy = adaptive_reliability(p.qos_profile.reliability for p in publishers)
        if policy is None or policy == self.input_reliability:
            return
        kinds = collections.Counter(RELIABILITY_NAMES.get(p.qos_profile.reliability, 'other')
                                    for p in publishers)
        self._create_input(policy, 'auto, publishers: ' + ', '.join(
            f'{n} {k}' for k, n in sorted(kinds.items())))

    def _create_input(self, policy: ReliabilityPolicy, how: str) -> None:
        """(Re)create the input subscription with `policy` (overrides still apply)."""
        if self.input_sub is not None:
            self.destroy_subscription(self.input_sub)
        qos = QoSProfile(depth=self.config.node.input_queue_depth,
                         history=HistoryPolicy.KEEP_LAST, reliability=policy,
                         durability=DurabilityPolicy.VOLATILE)
        # Reliability is overridable only when the params file sets it: a parameter declared
        # from the first choice would pin auto to it.
        kinds = OVERRIDABLE if self._reliability_override() is not None else tuple(
            k for k in OVERRIDABLE if k != QoSPolicyKind.RELIABILITY)
        self.input_sub = self.create_subscription(PointCloud2, 'points', self._on_cloud, qos,
                                                  qos_overriding_options=overridable(*kinds))
        self.input_reliability = qos.reliability
        self.get_logger().info(
            f'input {self.input_topic}: {RELIABILITY_NAMES.get(qos.reliability, "?")}, depth '
            f'{qos.depth} ({how})')
