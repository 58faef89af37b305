"""Whether a match is trusted: its fitness against the recent matches, and the run of
fallbacks that ends tracking."""

from __future__ import annotations

import logging
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from gft_odom.core.registration.motion import MotionModel

log = logging.getLogger(__name__)

# Fitness = the share of the scan's points with a pair; below this a match is not trusted.
MIN_FITNESS = 0.3
# Scan-to-map fitness is steady (0.8-0.97 on the simulated drives): below this share of the
# recent matches' median it is not trusted either (a copy of a scan rotated 90 deg still
# reached 0.48 near the prediction, enough for MIN_FITNESS).
MIN_RELATIVE_FITNESS = 0.7
# The recent matches that median is over (and the fewest it needs).
RECENT_FITNESS_WINDOW = 10
RECENT_FITNESS_MIN = 3
# This many fallbacks in a row drop the velocity: the next scan is re-acquired.
MAX_CONSECUTIVE_FALLBACKS = 3


def below_recent_median(value: float, recent, ratio: float) -> bool:
    """Below `ratio` x the median of `recent` (False while it holds fewer than
    RECENT_FITNESS_MIN values to tell)."""
    return len(recent) >= RECENT_FITNESS_MIN and value < ratio * float(np.median(recent))


class TrustPolicy:
    """Whether a match is trusted (its fitness, the motion bounds, the jump from the
    prediction), and the run of fallbacks that ends tracking.

    A fitness is judged against the recent trusted matches as well as MIN_FITNESS (in default
    mode): scan-to-map fitness is steady, and a wrong fit near the prediction can still pass
    the absolute bound.
    """

    def __init__(self, motion: MotionModel, relative_fitness: bool = True):
        self.motion = motion  # the bounds and the jump a match's pose must keep
        # Paper mode judges the fitness by MIN_FITNESS alone (its scan-to-scan fitness varies).
        self.relative_fitness = relative_fitness
        self.reset()

    def reset(self) -> None:
        """No match yet, no fallback."""
        self.recent_fitness: deque[float] = deque(maxlen=RECENT_FITNESS_WINDOW)  # trusted
        self.n_fallbacks = 0
        self.consecutive_fallbacks = 0

    def relatively_unfit(self, fitness: float) -> bool:
        """Below MIN_RELATIVE_FITNESS x the median fitness of the recent trusted matches."""
        return self.below_recent(fitness, MIN_RELATIVE_FITNESS)

    def below_recent(self, fitness: float, ratio: float) -> bool:
        """Below `ratio` x the median fitness of the recent trusted matches (False while
        there are too few to tell)."""
        return below_recent_median(fitness, self.recent_fitness, ratio)

    def trusted(self, fitness: float | None) -> None:
        """A trusted pose ends the fallback run; a match's `fitness` joins the recent ones."""
        if fitness is not None:
            self.recent_fitness.append(fitness)
        self.consecutive_fallbacks = 0

    def fell_back(self) -> bool:
        """Count a fallback; True once the run is long enough to drop the velocity."""
        self.n_fallbacks += 1
        self.consecutive_fallbacks += 1
        return self.consecutive_fallbacks >= MAX_CONSECUTIVE_FALLBACKS

    def refusal(self, T_est: np.ndarray, fitness: float, T_pred: np.ndarray,
                stamp_ns: int) -> str | None:
        """Why a match's pose `T_est` is not trusted (its fallback status), or None: every
        check a match passes (the turn check's fits pass the same)."""
        if not np.all(np.isfinite(T_est)):
            return 'fallback_diverged'
        if fitness < MIN_FITNESS or (self.relative_fitness and self.relatively_unfit(fitness)):
            return 'fallback_low_fitness'
        if not self.motion.plausible_since_trusted(stamp_ns, T_est):
            log.debug('ICP implies motion beyond the bounds since the last trusted pose')
            return 'fallback_implausible'
        if self.motion.jumped(T_pred, T_est, stamp_ns):
            return 'fallback_diverged'
        return None
