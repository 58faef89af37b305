"""What a match finds, and the second chances a poor or failed one gets: re-acquisition from
the motion model's guesses (after a loss, or at once for a failed match) and the turn check
(a poorly fitting match tried again from turned guesses).

At a turn's onset in open ground (a headland past the block's edge) ICP from a prediction
without the turn settles on a pose turned too little and slides along the track: the ground
fits any heading, and the far row ends that fix it are outside the gate. The turn check and
re-acquisition's turned guesses catch it; both compare fits by the share of the scan's points
within TURN_CHECK_GATE_M of the map, which tells the true turn where ICP's fitness (within the
1 m gate) does not. Every fit these return passes the checks of `TrustPolicy.refusal` that a
match from the prediction passes, except re-acquisition after a loss (its guesses are rough:
no jump check).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from gft_odom.core.geometry import transform_points
from gft_odom.core.registration.trust import MIN_FITNESS
from gft_odom.core.registration.uncertainty import icp_information

if TYPE_CHECKING:
    from gft_odom.core.registration.local_map import LocalMap
    from gft_odom.core.registration.matching import MapMatcher
    from gft_odom.core.registration.motion import MotionModel
    from gft_odom.core.registration.trust import TrustPolicy

# Re-acquisition's coarse ICP widens the correspondence gate by this factor.
RECOVERY_CORRESPONDENCE_FACTOR = 3.0
# A trusted match fitting below this share of the recent matches' median is checked from
# turned guesses; re-acquisition tries them when its best plain fit is below it. A missed
# turn leaves every plain fit poor (0.77-0.80 against ~0.92-0.95 before it), while a platform
# beyond the speed bound fits well and is refused on every scan.
TURN_RELATIVE_FITNESS = 0.95
# A turned fit replaces the match when it scores better by this (and re-acquisition gives up
# when a fit it refused for the bounds or the jump scores better by this than its best).
TURN_CHECK_FITNESS_MARGIN = 0.03
# The score: the share of the scan's points within this distance of the map at a pose.
TURN_CHECK_GATE_M = 0.3


class Match(NamedTuple):
    """What matching (or re-acquiring) one scan found; the pose is the prediction's unless
    trusted."""

    status: str
    T_world_sensor: np.ndarray
    fitness: float
    rmse: float
    information: np.ndarray | None  # in the target's axes; None unless trusted
    velocity: np.ndarray | None = None  # re-acquisition: the velocity it leaves behind


def fitted_match(status: str, result, T_est: np.ndarray, source_xyz: np.ndarray, target,
                 velocity: np.ndarray | None = None) -> Match:
    """A trusted Match of an ICP `result` (pose `T_est`) against `target` (the map's
    MapTarget or the previous scan's cloud): its fitness, RMSE and information."""
    rmse = float(result.inlier_rmse)
    return Match(status, T_est, float(result.fitness), rmse,
                 icp_information(source_xyz, target, result, rmse), velocity)


class Recovery:
    """Re-acquisition and the turn check of default mode, against the local map."""

    def __init__(self, matcher: MapMatcher, motion: MotionModel, trust: TrustPolicy,
                 local_map: LocalMap, max_correspondence_distance_m: float):
        self.matcher = matcher
        self.motion = motion
        self.trust = trust
        self.local_map = local_map
        self.gate_m = max_correspondence_distance_m
        self.reset()

    def reset(self) -> None:
        """The matches checked from turned guesses, and those a turn replaced."""
        self.n_turn_checks = 0
        self.n_turns_found = 0

    def _fitted(self, status: str, result, T_est: np.ndarray, source_xyz: np.ndarray,
                velocity: np.ndarray | None = None) -> Match:
        return fitted_match(status, result, T_est, source_xyz, self.local_map.target(),
                            velocity)

    def _implied_or(self, velocity: np.ndarray | None, stamp_ns: int,
                    T_est: np.ndarray) -> np.ndarray | None:
        """The velocity the motion since the last trusted pose implies (`velocity` when
        there is none to measure)."""
        implied = self.motion.implied_velocity(stamp_ns, T_est)
        return velocity if implied is None else implied

    def fit_score(self, source_xyz: np.ndarray, T_world_sensor: np.ndarray) -> float:
        """The share of the points within TURN_CHECK_GATE_M of the map at that pose."""
        if not source_xyz.shape[0]:
            return 0.0
        return self.local_map.share_near(transform_points(T_world_sensor, source_xyz),
                                         TURN_CHECK_GATE_M)

    def turn_check_due(self, match: Match) -> bool:
        """A trusted match that fits poorly for the recent matches (by ICP's fitness)."""
        return (match.status in ('ok', 'recovered')
                and self.trust.below_recent(match.fitness, TURN_RELATIVE_FITNESS))

    def turn_check(self, source_xyz: np.ndarray,
                   deskewed_as: Callable[[np.ndarray], np.ndarray], T_pred: np.ndarray,
                   stamp_ns: int, match: Match) -> Match:
        """`match` (of `source_xyz`), or the best fit from the turned guesses when it scores
        better by TURN_CHECK_FITNESS_MARGIN and passes every check a match does.
        `deskewed_as(v)`: the scan's source points as matched from a guess of velocity `v`
        (a turned pose matched with the sweep deskewed by the prediction, which has no turn,
        fits poorly)."""
        self.n_turn_checks += 1
        match_score = self.fit_score(source_xyz, match.T_world_sensor)
        best = None  # (score, result, pose, source points)
        for guess_velocity, init in self.motion.turn_guesses(stamp_ns, retry=True):
            guess_xyz = deskewed_as(guess_velocity)
            result = self.matcher.match(guess_xyz, init, self.gate_m)
            T_est = np.asarray(result.transformation)
            score = self.fit_score(guess_xyz, T_est)
            if (score < match_score + TURN_CHECK_FITNESS_MARGIN
                    or (best is not None and score <= best[0])
                    or self.trust.refusal(T_est, float(result.fitness), T_pred,
                                          stamp_ns) is not None):
                continue
            best = (score, result, T_est, guess_xyz)
        if best is None:
            return match
        self.n_turns_found += 1
        _, result, T_est, guess_xyz = best
        velocity = match.velocity
        if match.status == 'recovered':  # re-acquisition keeps the velocity it implies
            velocity = self._implied_or(velocity, stamp_ns, T_est)
        return self._fitted(match.status, result, T_est, guess_xyz, velocity)

    def reacquire(self, source_xyz: np.ndarray, T_pred: np.ndarray, stamp_ns: int,
                  retry: bool = False) -> Match:
        """Re-acquire against the map from a few initial guesses (the motion model's, from
        the last trusted pose). From each: a coarse ICP with a widened gate, then the normal
        one with more iterations. The plausible fit with the best fitness wins; no jump check
        (the guesses are rough). Only when no plain guess gives one, and their best fit is
        below TURN_RELATIVE_FITNESS x the recent ones, are turned guesses tried; a turned fit
        must fit better than every plain guess's, refused ones included. No fit is taken when
        one refused for the bounds or the jump fits clearly better: the reference it was
        measured from (the last trusted pose, perhaps one that slid) is the likelier error.

        `retry`: a second chance for a scan whose match from the prediction failed, with the
        current velocity as the one before the loss; the fit must pass every check a match
        does (relative fitness, the jump from the prediction too), and the velocity becomes
        the motion it implies."""
        wide_m = self.gate_m * RECOVERY_CORRESPONDENCE_FACTOR
        best, best_score, status = None, -1.0, 'fallback_low_fitness'
        best_plain = 0.0  # the best fitness of any plain guess's fit, refused ones included
        best_refused = -1.0  # of the fits refused for the bounds or the jump
        for turned in (False, True):
            if turned and (best is not None or not self.trust.below_recent(
                    best_plain, TURN_RELATIVE_FITNESS)):
                break
            guesses = (self.motion.turn_guesses(stamp_ns, retry) if turned
                       else self.motion.reacquisition_guesses(stamp_ns, retry))
            for velocity, init in guesses:
                coarse = self.matcher.match(source_xyz, init, wide_m)
                result = self.matcher.match(source_xyz, np.asarray(coarse.transformation),
                                            self.gate_m, recovery=True)
                T_est = np.asarray(result.transformation)
                fitness = float(result.fitness)
                if not np.all(np.isfinite(T_est)) or fitness < MIN_FITNESS:
                    continue
                if not turned:
                    best_plain = max(best_plain, fitness)
                elif fitness <= best_plain:
                    continue  # a turned guess that fits no better is a local minimum
                if retry and self.trust.relatively_unfit(fitness):
                    continue
                if retry and self.motion.jumped(T_pred, T_est, stamp_ns):
                    best_refused = max(best_refused, fitness)
                    continue
                if not self.motion.plausible_since_trusted(stamp_ns, T_est):
                    status = 'fallback_implausible'
                    best_refused = max(best_refused, fitness)
                    continue
                if best is None or fitness > best_score:
                    best, best_score = (result, T_est, velocity), fitness
        if best is not None and best_score + TURN_CHECK_FITNESS_MARGIN < best_refused:
            best, status = None, 'fallback_implausible'
        if best is None:
            return Match(status, T_pred, 0.0, 0.0, None)
        result, T_est, velocity = best
        if retry:
            velocity = self._implied_or(velocity, stamp_ns, T_est)
        return self._fitted('recovered', result, T_est, source_xyz, velocity)
