"""What a match finds, and the second chances a poor or failed one gets: re-acquisition from
the motion model's guesses (after a loss, or at once for a failed match) and the turn check
(a poorly fitting match tried again from turned guesses).

Every fit these return passes the checks of `TrustPolicy.refusal` that a match from the
prediction passes, except re-acquisition after a loss (its guesses are rough: no jump check).
docs/registration.md has the drives behind each rule.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from gft_odom.core.geometry import transform_points
from gft_odom.core.local_map import LocalMap, to_cloud
from gft_odom.core.trust import RECENT_FITNESS_WINDOW, below_recent_median
from gft_odom.core.uncertainty import icp_information

if TYPE_CHECKING:
    from gft_odom.core.icp_backend import IcpBackend
    from gft_odom.core.motion_model import MotionModel
    from gft_odom.core.registration_config import RegistrationConfig
    from gft_odom.core.trust import TrustPolicy


class Match(NamedTuple):
    """What matching (or re-acquiring) one scan found; the pose is the prediction's unless
    trusted."""

    status: str
    T_world_sensor: np.ndarray
    fitness: float
    rmse: float
    information: np.ndarray | None  # in the target's axes; None unless trusted
    velocity: np.ndarray | None = None  # re-acquisition: the velocity it leaves behind


class TurnedFit(NamedTuple):
    """One turned guess of the turn check, as far as it has been matched."""

    score: float  # Recovery._fit_score
    result: object  # the ICP result
    T_world_sensor: np.ndarray
    source_xyz: np.ndarray  # the scan deskewed as the guess
    source: object  # the same as an open3d cloud (what ICP is given)


def fitted_match(status: str, result, T_est: np.ndarray, source_xyz: np.ndarray,
                 icp: IcpBackend, target, velocity: np.ndarray | None = None,
                 wide=None) -> Match:
    """A trusted Match of an ICP `result` (pose `T_est`, by `icp` against `target`): its
    fitness, RMSE (`IcpBackend.match_rmse_m`) and information. `wide`: the match that
    `result` refined within a narrower gate (or `result` itself); its fitness and RMSE are
    the match's (the trust policy's and the covariance's gate), the information is of
    `result`'s pairs."""
    judged = result if wide is None else wide
    rmse = icp.match_rmse_m(judged, source_xyz, target)
    return Match(status, T_est, float(judged.fitness), rmse,
                 icp_information(source_xyz, icp.matched(target), result, rmse), velocity)


class Recovery:
    """Re-acquisition and the turn check of default mode, against the local map."""

    def __init__(self, config: RegistrationConfig, icp: IcpBackend, motion: MotionModel,
                 trust: TrustPolicy, local_map: LocalMap):
        self.config = config
        self.icp = icp
        self.motion = motion
        self.trust = trust
        self.local_map = local_map
        self.reset()

    def reset(self) -> None:
        """turn_check: the matches checked from turned guesses, and those a turn replaced;
        the shares near the map of the recent trusted matches (`turn_check_share_ratio`)."""
        self.n_turn_checks = 0
        self.n_turns_found = 0
        self.recent_share: deque[float] = deque(maxlen=RECENT_FITNESS_WINDOW)

    def _fitted(self, status: str, result, T_est: np.ndarray, source_xyz: np.ndarray,
                target, velocity: np.ndarray | None = None) -> Match:
        return fitted_match(status, result, T_est, source_xyz, self.icp, target,
                            velocity)

    def _implied_or(self, velocity: np.ndarray | None, stamp_ns: int,
                    T_est: np.ndarray) -> np.ndarray | None:
        """The velocity the motion since the last trusted pose implies (`velocity` when
        there is none to measure)."""
        implied = self.motion.implied_velocity(stamp_ns, T_est)
        return velocity if implied is None else implied

    def _fit_score(self, source_xyz: np.ndarray, T_world_sensor: np.ndarray,
                   fitness: float) -> float:
        """What the turn check compares fits by: ICP's `fitness`, or (`turn_check_gate_m`
        > 0) the share of the points within that distance of the map at that pose."""
        gate_m = self.config.turn_check_gate_m
        if gate_m <= 0.0 or not source_xyz.shape[0]:
            return fitness
        return self.local_map.share_near(transform_points(T_world_sensor, source_xyz), gate_m)

    def _reacquisition_score(self, source_xyz: np.ndarray, T_world_sensor: np.ndarray,
                             fitness: float) -> float:
        """What re-acquisition compares its fits by: ICP's `fitness`, or
        (`reacquisition_by_share`) the turn check's score."""
        if not self.config.reacquisition_by_share:
            return fitness
        return self._fit_score(source_xyz, T_world_sensor, fitness)

    def turn_check_due(self, match: Match, source_xyz: np.ndarray) -> bool:
        """A trusted match (of `source_xyz`) that fits poorly for the recent matches
        (`turn_check`): by ICP's fitness, or (`turn_check_share_ratio`) by its share of points
        near the map."""
        cfg = self.config
        if not (cfg.turn_check and cfg.mode == 'default'
                and match.status in ('ok', 'recovered')):
            return False
        due = self.trust.below_recent(match.fitness, cfg.recovery_turn_relative_fitness)
        if cfg.turn_check_share_ratio > 0.0:
            share = self._fit_score(source_xyz, match.T_world_sensor, match.fitness)
            due = due or below_recent_median(share, self.recent_share,
                                             cfg.turn_check_share_ratio)
            self.recent_share.append(share)
        return due

    def turn_check(self, source_xyz: np.ndarray,
                   deskewed_as: Callable[[np.ndarray], np.ndarray], T_pred: np.ndarray,
                   stamp_ns: int, match: Match) -> Match:
        """`match` (of `source_xyz`), or the best fit from the turned guesses when it fits
        better by `turn_check_fitness_margin` (by `_fit_score`) and passes every check a match
        does. `deskewed_as(v)`: the scan's source points as matched from a guess of velocity
        `v`. With `turn_check_screen_iterations`, only the guesses `_carried_on` are matched
        to the full budget."""
        cfg = self.config
        target = self.local_map.cloud
        self.n_turn_checks += 1
        match_score = self._fit_score(source_xyz, match.T_world_sensor, match.fitness)
        screen = cfg.turn_check_screen_iterations
        screening = 0 < screen < cfg.max_iterations
        fits = []
        for guess_velocity, init in self.motion.turn_guesses(stamp_ns, retry=True):
            guess_xyz = deskewed_as(guess_velocity)
            fits.append(self._turned_fit(guess_xyz, to_cloud(guess_xyz), init,
                                         screen if screening else None))
        if screening and fits:
            fits = self._carried_on(fits, match_score, screen)
        best = None
        for fit in fits:
            if (fit.score < match_score + cfg.turn_check_fitness_margin
                    or (best is not None and fit.score <= best.score)
                    or self.trust.refusal(fit.T_world_sensor, float(fit.result.fitness),
                                          T_pred, stamp_ns) is not None):
                continue
            best = fit
        if best is None:
            return match
        self.n_turns_found += 1
        velocity = match.velocity
        if match.status == 'recovered':  # re-acquisition keeps the velocity it implies
            velocity = self._implied_or(velocity, stamp_ns, best.T_world_sensor)
        return self._fitted(match.status, best.result, best.T_world_sensor, best.source_xyz,
                            target, velocity)

    def _turned_fit(self, source_xyz: np.ndarray, source, init: np.ndarray,
                    max_iterations: int | None) -> TurnedFit:
        """ICP of a turned guess's scan from `init` (None: the usual budget), scored."""
        result = self.icp.register(source, self.local_map.cloud, init,
                                   self.config.max_correspondence_distance_m,
                                   max_iterations=max_iterations)
        T_est = np.asarray(result.transformation)
        return TurnedFit(self._fit_score(source_xyz, T_est, float(result.fitness)), result,
                         T_est, source_xyz, source)

    def _carried_on(self, fits: list[TurnedFit], match_score: float,
                    screen: int) -> list[TurnedFit]:
        """The screened turned fits that go on to the full budget (from where they stopped):
        the better half, and any that already fit as well as the match. The ranking after the
        screen is a rough one: a fit that turns out right can start far below the match and
        below another guess (edge drive 227, scan 474: 0.36 after 10 iterations, second of
        four, 0.47 after 30 against the match's 0.44)."""
        ranked = sorted(range(len(fits)), key=lambda k: -fits[k].score)
        better_half = set(ranked[:(len(fits) + 1) // 2])
        kept = []
        for k, fit in enumerate(fits):
            if k not in better_half and fit.score < match_score:
                continue
            if getattr(fit.result, 'n_iterations', screen) >= screen:  # not converged yet
                fit = self._turned_fit(fit.source_xyz, fit.source, fit.T_world_sensor,
                                       self.config.max_iterations - screen)
            kept.append(fit)
        return kept

    def reacquire(self, source_xyz: np.ndarray, T_pred: np.ndarray, stamp_ns: int,
                   retry: bool = False) -> Match:
        """Re-acquire against the map from a few initial guesses (the motion model's, from
        the last trusted pose). From each: a coarse ICP with a widened correspondence
        distance, then the normal one with more iterations. The plausible fit with the best
        score (`_reacquisition_score`) wins; no jump check (the guesses are rough). Only when
        no plain guess gives one, and their best fit is below `recovery_turn_relative_fitness`
        x the recent ones, are turned guesses tried; a turned fit must fit better than every
        plain guess's, refused ones included. With `reacquisition_beats_refused` no fit is
        taken when one refused for the bounds or the jump scores clearly better.

        `retry`: a second chance for a scan whose match from the prediction failed, with the
        current velocity as the one before the loss; the fit must pass every check a match
        does (relative fitness, the jump from the prediction too), and the velocity becomes
        the motion it implies."""
        cfg = self.config
        source, target = to_cloud(source_xyz), self.local_map.cloud
        wide_m = cfg.max_correspondence_distance_m * cfg.recovery_correspondence_factor
        best, best_score, status = None, -1.0, 'fallback_low_fitness'
        best_plain_fitness = 0.0  # of any fit from a plain guess, refused ones included
        best_plain_score = 0.0  # the same by the score fits are compared by
        best_refused_score = -1.0  # of the fits refused for the bounds or the jump
        for turned in (False, True):
            if turned and (best is not None or not self.trust.below_recent(
                    best_plain_fitness, cfg.recovery_turn_relative_fitness)):
                # The last resort, and only for a poor fit: a plain fit that explains the scan
                # as well as the recent matches was refused for the bounds or the jump, not a
                # missed turn (a platform beyond the speed bound: every scan lands here).
                break
            guesses = (self.motion.turn_guesses(stamp_ns, retry) if turned
                       else self.motion.reacquisition_guesses(stamp_ns, retry))
            for velocity, init in guesses:
                coarse = self.icp.register(source, target, init, wide_m)
                result = self.icp.register(source, target, np.asarray(coarse.transformation),
                                           cfg.max_correspondence_distance_m, recovery=True)
                T_est = np.asarray(result.transformation)
                if not np.all(np.isfinite(T_est)) or result.fitness < cfg.min_fitness:
                    continue
                score = self._reacquisition_score(source_xyz, T_est, float(result.fitness))
                if not turned:
                    best_plain_fitness = max(best_plain_fitness, float(result.fitness))
                    best_plain_score = max(best_plain_score, score)
                elif score <= best_plain_score:
                    continue  # a turned guess that fits no better is a local minimum
                if retry and self.trust.relatively_unfit(float(result.fitness)):
                    continue
                if retry and self.motion.jumped(T_pred, T_est, stamp_ns):
                    best_refused_score = max(best_refused_score, score)
                    continue
                if not self.motion.plausible_since_trusted(stamp_ns, T_est):
                    status = 'fallback_implausible'
                    best_refused_score = max(best_refused_score, score)
                    continue
                if best is None or score > best_score:
                    best, best_score = (result, T_est, velocity), score
        if best is not None and cfg.reacquisition_beats_refused and (
                best_score + cfg.turn_check_fitness_margin < best_refused_score):
            # A fit that explains the scan clearly better was refused: the reference it was
            # measured from (the last trusted pose) is the likelier error, not that fit.
            best, status = None, 'fallback_implausible'
        if best is None:
            return Match(status, T_pred, 0.0, 0.0, None)
        result, T_est, velocity = best
        if retry:
            velocity = self._implied_or(velocity, stamp_ns, T_est)
        return self._fitted('recovered', result, T_est, source_xyz, target, velocity)
