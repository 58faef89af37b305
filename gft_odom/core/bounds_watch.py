"""Motion bounds that speak up: told once when the bounds refuse a platform's real motion.

`registration.max_speed_mps` / `max_yaw_rate_rps` refuse a match that implies impossible motion
(`fallback_implausible`): a rotated or shifted copy of the map, a jump. A platform faster than
the bounds is refused the same way, scan after scan, and the odometry silently lags behind it
(a car at 4.4 m/s with the default 2 m/s bound: 65 of 154 matches refused, 25 m of a 71 m
drive). The two differ in one thing a single scan cannot show: refusals of a fast platform are
many and agree (the same speed each time); wrong matches scatter. `BoundsWatch` watches the
refusals and says so once, naming the parameter and the speed seen.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

log = logging.getLogger(__name__)

IMPLAUSIBLE_STATUS = 'fallback_implausible'
# Refusals that must agree, among the last WINDOW_SCANS registered scans.
REFUSALS_TO_TELL = 5
WINDOW_SCANS = 100
# They agree when the largest implied speed (or rate) is at most this times the smallest.
AGREEMENT_RATIO = 1.5
# And they are a real share of the recent scans: a platform beyond the bounds is refused
# again and again (the car: 65 of 154), while the paper's scan-to-scan ICP on a U-turn gave 5
# wrong matches in 66 scans that happened to agree on 3.3 m/s (`make demo`).
MIN_REFUSED_SHARE = 0.2


class BoundsWatch:
    """Feed it every registration's status and refused rates; `message` is set once due."""

    def __init__(self, max_speed_mps: float, max_yaw_rate_rps: float,
                 refusals: int = REFUSALS_TO_TELL, window_scans: int = WINDOW_SCANS,
                 agreement_ratio: float = AGREEMENT_RATIO) -> None:
        self.max_speed_mps = float(max_speed_mps)
        self.max_yaw_rate_rps = float(max_yaw_rate_rps)
        self.refusals = int(refusals)
        self.agreement_ratio = float(agreement_ratio)
        self._recent: deque[tuple[float, float] | None] = deque(maxlen=int(window_scans))
        self.message: str | None = None  # the line, once told (it stays for /diagnostics)

    def observe(self, status: str, refused_speed_mps: float | None,
                refused_rate_rps: float | None) -> str | None:
        """Take one scan's outcome; returns the line (and logs it) the one time it is due."""
        refused = (status == IMPLAUSIBLE_STATUS and refused_speed_mps is not None
                   and refused_rate_rps is not None)
        self._recent.append((float(refused_speed_mps), float(refused_rate_rps))
                            if refused else None)
        if self.message is not None or not refused:
            return None
        refusals = [r for r in self._recent if r is not None]
        seen = refusals[-self.refusals:]
        if len(seen) < self.refusals or len(refusals) < MIN_REFUSED_SHARE * len(self._recent):
            return None
        speeds, rates = np.array(seen).T
        parts = []
        if self._agree_beyond(speeds, self.max_speed_mps):
            parts.append(f'{np.median(speeds):.1f} m/s, above registration.max_speed_mps = '
                         f'{self.max_speed_mps:g}')
        if self._agree_beyond(rates, self.max_yaw_rate_rps):
            parts.append(f'{np.median(rates):.2f} rad/s, above registration.max_yaw_rate_rps = '
                         f'{self.max_yaw_rate_rps:g}')
        if not parts:
            return None
        n_refused = sum(r is not None for r in self._recent)
        names = ' / '.join(p.split('above ')[1].split(' =')[0] for p in parts)
        self.message = (f'motion bounds: {n_refused} of the last {len(self._recent)} matches '
                        f'fitted well but were refused as implausible, agreeing on '
                        f'{" and ".join(parts)}; if the platform moves that fast, raise '
                        f'{names} (the odometry lags the platform until then)')
        log.warning('%s', self.message)
        return self.message

    def _agree_beyond(self, values: np.ndarray, bound: float) -> bool:
        """All beyond `bound` and within `agreement_ratio` of each other."""
        return bool(np.all(np.isfinite(values)) and values.min() > bound
                    and values.max() <= self.agreement_ratio * values.min())
