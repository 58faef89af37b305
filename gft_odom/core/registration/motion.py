"""The motion model of scan registration: where the sensor should be, and what it could have done.

A constant velocity (rad/s, m/s) from the last trusted match, extrapolated over the real stamp
difference and capped by the robot's physical bounds, is each scan's initial guess. The same
bounds (with a margin for stamp jitter and ICP noise) refuse a match implying motion no Jackal
can make, and a match far from the prediction is a jump.

Everything is measured from the last trusted pose over the time since it, never from a
fallback's extrapolated pose: after fallbacks the previous pose is only a prediction, and its
error is not this scan's motion. A motion beyond the bounds from it may still be plausible
from the trusted pose before it: one trusted match that slid along the track must not lock
the true next pose out. After a gap or a run of fallbacks
the velocity is dropped (a stale velocity would throw every later guess off) and
re-acquisition is pending; the velocity from before the loss seeds its guesses. The twists of
the last trusted scans give deskew a velocity with the ICP noise averaged out.
"""

from __future__ import annotations

import logging
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from gft_odom.core.deskew import planar_delta, twist_from_delta
from gft_odom.core.geometry import (
    invert_transform,
    make_transform,
    rotation_matrix,
    rotation_vector,
)

if TYPE_CHECKING:
    from gft_odom.core.registration.config import RegistrationConfig

log = logging.getLogger(__name__)
# Slack on the platform's bounds for stamp jitter and ICP noise over short steps (a copy of a
# scan rotated 90 deg 30 ms later implies 52 rad/s, far beyond it).
MOTION_MARGIN = 0.5
# Largest correction to the constant-velocity prediction per scan period: a Jackal cannot
# change its velocity by more within 0.1 s. Scaled by the time the prediction covers.
MAX_TRANSLATION_JUMP_M = 0.5
MAX_ROTATION_JUMP_RAD = 0.25
# Deskew assumes the mean twist of the last this many trusted scans (ICP noise averages out;
# a mean over more lags where the yaw rate jumps at a turn's onset).
DESKEW_VELOCITY_WINDOW = 2
# Re-acquisition and the turn check also try the velocity with its yaw rate changed by
# k x TURN_GUESS_STEP_RPS, k = 1..TURN_GUESSES, either way: at a fast turn's onset in open
# ground ICP from a guess without the turn slides along the track instead of turning.
TURN_GUESSES = 2
TURN_GUESS_STEP_RPS = 1.0
# Times are counted in scan periods, at least this share of one. The jump bounds hold per
# period and scale with the time the prediction covers (a correction to the constant-velocity
# guess comes from a change of velocity, which grows with that time); ICP's own noise, mm and
# mrad, is far under a tenth of the bounds. A twist over a short span weighs its share.
MIN_PERIOD_SHARE = 0.1


def scale_delta(T: np.ndarray, factor: float) -> np.ndarray:
    """The rigid motion `T` extrapolated to `factor` times its duration (constant twist)."""
    out = np.eye(4)
    out[:3, :3] = rotation_matrix(rotation_vector(T[:3, :3]) * factor)
    out[:3, 3] = T[:3, 3] * factor
    return out


def twist_of(T_prev_curr: np.ndarray, dt_s: float) -> np.ndarray:
    """(rot_x, rot_y, rot_z, v_x, v_y, v_z) in rad/s and m/s of a motion lasting `dt_s`."""
    omega, velocity = twist_from_delta(T_prev_curr, dt_s)
    return np.r_[omega, velocity]


def delta_of_twist(twist: np.ndarray, dt_s: float) -> np.ndarray:
    """The rigid motion of a constant twist (rot rad/s, lin m/s) lasting `dt_s`."""
    return make_transform(rotation_matrix(twist[:3] * dt_s), twist[3:] * dt_s)


def transform_magnitude(T: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation angle rad) of a rigid transform."""
    cos_angle = np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(T[:3, 3])), float(np.arccos(cos_angle))


class MotionModel:
    """The sensor's pose, last trusted pose and velocity: predicts, bounds and judges motion.

    Reads the platform's bounds, the gap and the scan period of a RegistrationConfig.
    `track_loss` False (paper mode: no map to re-acquire against) never drops the velocity.
    """

    def __init__(self, config: RegistrationConfig, track_loss: bool = True):
        self.config = config
        self.track_loss = track_loss
        self.reset()

    def reset(self) -> None:
        """No scan yet: pose identity, no velocity, nothing to re-acquire."""
        # The pose at the last scan, trusted or extrapolated, and its stamp.
        self.T_world_sensor = np.eye(4)
        self.last_stamp_ns: int | None = None
        # The last trusted pose and its stamp: fallbacks only extrapolate, so plausibility
        # and re-acquisition are measured from here, over the time since it.
        self.T_world_trusted = np.eye(4)
        self.trusted_stamp_ns: int | None = None
        # The trusted pose before it, and its stamp: a second reference of plausibility.
        self.previous_trusted: tuple[np.ndarray, int] | None = None
        # (rot_x, rot_y, rot_z, v_x, v_y, v_z) in rad/s, m/s, previous sensor axes.
        self.velocity = np.zeros(6)
        # The velocities of the last trusted scans and the time each spans: deskew assumes
        # their mean weighted by it (a scan 30 ms after the last counts a third).
        self.twists: deque[tuple[np.ndarray, float]] = deque(
            maxlen=DESKEW_VELOCITY_WINDOW)
        # Re-acquiring after a gap or a run of fallbacks; the velocity before the loss.
        self.recovering = False
        self.velocity_before_loss = np.zeros(6)
        # (m/s, rad/s) the last `is_plausible` motion implied: what a refusal reports.
        self.last_implied_rates: tuple[float | None, float | None] = (None, None)

    # ------------------------------------------------------------ prediction

    def capped(self, twist: np.ndarray) -> np.ndarray:
        """`twist` scaled down (direction kept) to the speed and rotation-rate bounds."""
        cfg = self.config
        out = np.array(twist, dtype=float)
        for part, bound in ((slice(0, 3), cfg.max_yaw_rate_rps), (slice(3, 6), cfg.max_speed_mps)):
            norm = float(np.linalg.norm(out[part]))
            if norm > bound:
                out[part] *= bound / norm
        return out

    def predicted_delta(self, dt_s: float) -> np.ndarray:
        """T_prev_curr the motion model expects `dt_s` after the last scan (none if <= 0)."""
        return delta_of_twist(self.velocity, dt_s) if dt_s > 0.0 else np.eye(4)

    def step_s(self, stamp_ns: int) -> float:
        """Seconds since the last scan (the scan period before the first)."""
        if self.last_stamp_ns is None:
            return self.config.scan_period_s
        dt_s = (int(stamp_ns) - self.last_stamp_ns) * 1e-9
        if not dt_s > 0.0:
            log.warning('scan stamp %d is not after the previous one (%d): predicting no motion',
                        stamp_ns, self.last_stamp_ns)
        return dt_s

    def predict(self, stamp_ns: int) -> tuple[float, np.ndarray]:
        """Time step since the last scan and the predicted pose. A gap drops the velocity:
        extrapolated over it, the guess would be anywhere."""
        dt_s = self.step_s(stamp_ns)
        if self.last_stamp_ns is not None and dt_s > self.config.max_gap_s:
            self.lose_track(f'gap of {dt_s:.2f} s in the scan stamps')
        return dt_s, self.T_world_sensor @ self.predicted_delta(dt_s)

    # ------------------------------------------------------------ judging a match

    def since_trusted(self, stamp_ns: int, T_world_est: np.ndarray) -> tuple[np.ndarray, float]:
        """The motion from the last trusted pose to `T_world_est` and the time it took (the
        previous scan's unless registrations fell back since). A stamp not after the trusted
        one (the API tolerates it, the pipeline refuses it) is measured from the previous pose
        over the stamp step, as before the trusted pose existed."""
        if self.trusted_stamp_ns is None or int(stamp_ns) <= self.trusted_stamp_ns:
            dt_s = (self.config.scan_period_s if self.last_stamp_ns is None
                    else (int(stamp_ns) - self.last_stamp_ns) * 1e-9)
            return invert_transform(self.T_world_sensor) @ T_world_est, dt_s
        return (invert_transform(self.T_world_trusted) @ T_world_est,
                (int(stamp_ns) - self.trusted_stamp_ns) * 1e-9)

    def is_plausible(self, T_prev_curr: np.ndarray, dt_s: float) -> bool:
        """Could the robot have made this motion in `dt_s` (bounds times 1 + margin)? The
        rates it implies are kept for a caller that reports a refusal (the bounds watch)."""
        distance_m, angle_rad = transform_magnitude(T_prev_curr)
        self.last_implied_rates = ((distance_m / dt_s, angle_rad / dt_s) if dt_s > 0.0
                                   else (float('inf'), float('inf')))
        return self._within_bounds(T_prev_curr, dt_s)

    def _within_bounds(self, T_prev_curr: np.ndarray, dt_s: float) -> bool:
        """`is_plausible` without recording the rates."""
        cfg = self.config
        distance_m, angle_rad = transform_magnitude(T_prev_curr)
        slack = (1.0 + MOTION_MARGIN) * max(dt_s, 0.0)
        return (distance_m <= cfg.max_speed_mps * slack
                and angle_rad <= cfg.max_yaw_rate_rps * slack)

    def plausible_since_trusted(self, stamp_ns: int, T_world_est: np.ndarray) -> bool:
        """Could the robot have reached `T_world_est` from the last trusted pose, or from the
        trusted pose before it? A match that slid along the track leaves a last trusted pose
        from which the true next one looks beyond the bounds; the one before it is a second
        reference. The rates reported are from the last trusted pose."""
        if self.is_plausible(*self.since_trusted(stamp_ns, T_world_est)):
            return True
        return self._from_previous_trusted(stamp_ns, T_world_est) is not None

    def _from_previous_trusted(self, stamp_ns: int, T_world_est: np.ndarray
                               ) -> tuple[np.ndarray, float] | None:
        """(motion, time it took) from the trusted pose before the last to `T_world_est`,
        when within the bounds, that pose is within a gap, and `stamp_ns` is at least half a
        scan period after the last trusted pose (sooner, a scan is more likely a copy than
        the next sweep: the fault suite's mirrored copies, 30 ms after a scan, are judged from
        that pose alone). None otherwise."""
        if (self.previous_trusted is None
                or self._elapsed_since_trusted(stamp_ns) < 0.5 * self.config.scan_period_s):
            return None
        T_world_ref, ref_stamp_ns = self.previous_trusted
        elapsed_s = (int(stamp_ns) - ref_stamp_ns) * 1e-9
        if not 0.0 < elapsed_s <= self.config.max_gap_s:
            return None
        motion = invert_transform(T_world_ref) @ T_world_est
        return (motion, elapsed_s) if self._within_bounds(motion, elapsed_s) else None

    def _periods(self, span_s):
        """`span_s` in scan periods, at least MIN_PERIOD_SHARE (scalar or array)."""
        return np.maximum(MIN_PERIOD_SHARE, np.asarray(span_s) / self.config.scan_period_s)

    def jumped(self, T_pred: np.ndarray, T_est: np.ndarray, stamp_ns: int) -> bool:
        """Farther from the prediction than the jump bounds, scaled by the time the
        prediction has been extrapolated over (since the last trusted pose) in scan periods:
        a copy of a scan 30 ms after it may stray a third as far as a scan a period later."""
        jump_m, jump_rad = transform_magnitude(invert_transform(T_pred) @ T_est)
        allowance = self._periods(self.since_trusted(stamp_ns, T_est)[1])
        if (jump_m > MAX_TRANSLATION_JUMP_M * allowance
                or jump_rad > MAX_ROTATION_JUMP_RAD * allowance):
            log.debug('ICP moved %.3f m / %.3f rad away from the prediction', jump_m, jump_rad)
            return True
        return False

    def implied_velocity(self, stamp_ns: int, T_world_est: np.ndarray) -> np.ndarray | None:
        """The capped velocity of the motion from the last trusted pose to `T_world_est`; None
        over no time or a gap (a mean over a gap is no velocity)."""
        motion, elapsed_s = self.since_trusted(stamp_ns, T_world_est)
        if not self._within_bounds(motion, elapsed_s):
            # Within them from the trusted pose before (`plausible_since_trusted`): the
            # motion since that one.
            second = self._from_previous_trusted(stamp_ns, T_world_est)
            if second is not None:
                motion, elapsed_s = second
        if 0.0 < elapsed_s <= self.config.max_gap_s:
            return self.capped(twist_of(motion, elapsed_s))
        return None

    # ------------------------------------------------------------ loss and re-acquisition

    def lose_track(self, why: str) -> None:
        """Stop extrapolating the velocity; re-acquire the next scan against the map (never
        without `track_loss`)."""
        if not self.track_loss:
            return
        if not self.recovering:
            log.info('re-acquiring against the map: %s', why)
            self.velocity_before_loss = self.velocity.copy()
        self.recovering = True
        self.velocity = np.zeros(6)
        self.twists.clear()

    def reacquisition_guesses(self, stamp_ns: int,
                              retry: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
        """(velocity, initial pose) pairs, all from the last trusted pose over the time since
        it: zero motion, the velocity before the loss (capped), and its straight-line part (a
        turn rate extrapolated over a long gap throws the guess sideways). `retry`: the
        current velocity stands for the one before the loss."""
        velocities = [np.zeros(6)]
        before = self._before_loss(retry)
        if np.any(before):
            velocities.append(before)
        if np.any(before[:3]) and np.any(before[3:]):
            velocities.append(np.r_[0.0, 0.0, 0.0, before[3:]])
        return self._from_trusted(velocities, self._elapsed_since_trusted(stamp_ns))

    def turn_guesses(self, stamp_ns: int,
                     retry: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
        """(velocity, initial pose) pairs for a turn begun or ended since the last trusted
        pose: the velocity before the loss with its yaw rate (sensor z up) changed by
        k x TURN_GUESS_STEP_RPS either way, capped. None within half a scan period
        of the trusted pose: there even 2 rad/s more turn a guess by < 0.1 rad, which the
        match covers from the prediction (and a stamp 30 ms after a scan is more likely a
        copy than a turn: the fault suite's mirrored copies)."""
        cfg = self.config
        elapsed_s = self._elapsed_since_trusted(stamp_ns)
        if elapsed_s < 0.5 * cfg.scan_period_s:
            return []
        before = self._before_loss(retry)
        velocities = []
        for k in range(1, TURN_GUESSES + 1):
            for sign in (-1.0, 1.0):
                turned = before.copy()
                turned[2] += sign * k * TURN_GUESS_STEP_RPS
                velocities.append(self.capped(turned))
        return self._from_trusted(velocities, elapsed_s)

    def _before_loss(self, retry: bool) -> np.ndarray:
        """The velocity re-acquisition starts from, capped (a retry's: the current one)."""
        return self.capped(self.velocity if retry else self.velocity_before_loss)

    def _elapsed_since_trusted(self, stamp_ns: int) -> float:
        return max(self.since_trusted(stamp_ns, self.T_world_trusted)[1], 0.0)

    def _from_trusted(self, velocities: list[np.ndarray],
                      elapsed_s: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """(velocity, initial pose) pairs: each velocity over `elapsed_s` from the last
        trusted pose."""
        return [(velocity, self.T_world_trusted @ delta_of_twist(velocity, elapsed_s))
                for velocity in velocities]

    # ------------------------------------------------------------ state updates

    def trust(self, stamp_ns: int, T_world_new: np.ndarray, status: str,
              recovered_velocity: np.ndarray | None = None) -> None:
        """A trusted pose: it becomes the reference of plausibility; a match (`ok`) sets the
        velocity to the motion since the previous trusted pose, a re-acquisition
        (`recovered`) to `recovered_velocity` (its winning guess, or a retry's motion)."""
        velocity = self.implied_velocity(stamp_ns, T_world_new) if status == 'ok' else None
        span_s = self.since_trusted(stamp_ns, T_world_new)[1]
        if self.trusted_stamp_ns is not None:
            self.previous_trusted = (self.T_world_trusted, self.trusted_stamp_ns)
        self.T_world_trusted = T_world_new.copy()
        self.trusted_stamp_ns = int(stamp_ns)
        if velocity is not None:
            self.velocity = velocity
            self.twists.append((self.velocity, span_s))
        elif status == 'recovered':
            self.velocity = recovered_velocity
        self.recovering = False

    def advance(self, stamp_ns: int, T_world_sensor: np.ndarray) -> None:
        """The pose at `stamp_ns`, trusted or not, is where the next prediction starts."""
        self.T_world_sensor = T_world_sensor
        self.last_stamp_ns = int(stamp_ns)

    # ------------------------------------------------------------ deskew

    def deskew_motion(self, dt_s: float, latest: np.ndarray | None = None) -> np.ndarray:
        """The motion over `dt_s` that deskew assumes: the twist of the recent trusted scans
        (with `latest`, this scan's own estimate, as the newest), their mean weighted by the
        share of a scan period each spans (at most 1), planar."""
        window = DESKEW_VELOCITY_WINDOW
        twists = list(self.twists)
        if latest is not None and dt_s > 0.0:
            twists = twists[len(twists) - window + 1:] + [(twist_of(latest, dt_s), dt_s)]
        if not twists or not dt_s > 0.0:
            return np.eye(4)
        velocities = np.array([twist for twist, _ in twists[-window:]])
        spans_s = np.array([span for _, span in twists[-window:]])
        # A span of a scan period or more weighs 1 (so steady scans give the plain mean); a
        # shorter one its share of a period: a velocity over 30 ms is ICP noise / 0.03 s.
        weights = np.minimum(self._periods(spans_s), 1.0)
        mean = np.sum(velocities * weights[:, None], axis=0) / np.sum(weights)
        # Planar: on rough ground a scan's roll, pitch and height rates are vibration that
        # does not persist into the next scan.
        return planar_delta(delta_of_twist(mean, dt_s))

    def scan_motion(self, stamp_ns: int, T_world_new: np.ndarray, dt_s: float) -> np.ndarray:
        """The motion over this scan's `dt_s` that deskew assumes: the mean motion since the
        last trusted pose, so a pose recovered after fallbacks is not read as one jump."""
        motion, elapsed_s = self.since_trusted(stamp_ns, T_world_new)
        if not elapsed_s > 0.0:
            return invert_transform(self.T_world_sensor) @ T_world_new
        return delta_of_twist(twist_of(motion, elapsed_s), dt_s)
