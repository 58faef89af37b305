"""Whether a match is trusted: its fitness against the recent matches, and the run of
fallbacks that ends tracking."""

from __future__ import annotations

import logging
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from gft_odom.core.motion_model import MotionModel
    from gft_odom.core.registration_config import RegistrationConfig

log = logging.getLogger(__name__)

# Matches whose median fitness min_relative_fitness refers to (and the fewest it needs).
RECENT_FITNESS_WINDOW = 10
RECENT_FITNESS_MIN = 3


def below_recent_median(value: float, recent, ratio: float) -> bool:
    """Below `ratio` x the median of `recent` (False while it holds fewer than
    RECENT_FITNESS_MIN values to tell)."""
    return len(recent) >= RECENT_FITNESS_MIN and value < ratio * float(np.median(recent))


class TrustPolicy:
    """Whether a match is trusted (its fitness, the motion bounds, the jump from the
    prediction), and the run of fallbacks that ends tracking.

    A fitness is judged against the recent trusted matches as well as `min_fitness`:
    scan-to-map fitness is steady, and a wrong fit near the prediction can still pass the
    absolute bound.
    """

    def __init__(self, config: RegistrationConfig, motion: MotionModel):
        self.config = config
        self.motion = motion  # the bounds and the jump a match's pose must keep
        self.reset()

    def reset(self) -> None:
        """No match yet, no fallback."""
        self.recent_fitness: deque[float] = deque(maxlen=RECENT_FITNESS_WINDOW)  # trusted
        self.n_fallbacks = 0
        self.consecutive_fallbacks = 0

    def relatively_unfit(self, fitness: float) -> bool:
        """Below `min_relative_fitness` x the median fitness of the recent trusted matches."""
        return self.below_recent(fitness, self.config.min_relative_fitness)

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
        return self.consecutive_fallbacks >= self.config.max_consecutive_fallbacks

    def refusal(self, T_est: np.ndarray, fitness: float, T_pred: np.ndarray,
                stamp_ns: int) -> str | None:
        """Why a match's pose `T_est` is not trusted (its fallback status), or None: every
        check a match passes (the turn check's fits pass the same)."""
        if not np.all(np.isfinite(T_est)):
            return 'fallback_diverged'
        if fitness < self.config.min_fitness or (self.config.mode == 'default'
                                                 and self.relatively_unfit(fitness)):
            return 'fallback_low_fitness'
        if not self.motion.plausible_since_trusted(stamp_ns, T_est):
            log.debug('ICP implies motion beyond the bounds since the last trusted pose')
            return 'fallback_implausible'
        if (self.motion.jumped(T_pred, T_est, stamp_ns)
                and not self.motion.vouched_by_refused(stamp_ns, T_est)):
            # (A match that agrees with the last refused one is judged by that agreement:
            # the prediction was extrapolated from the pose the two of them disown.)
            return 'fallback_diverged'
        return None
