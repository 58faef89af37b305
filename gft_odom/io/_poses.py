"""Shared by the trajectory readers: exact decimal stamps and pose-table clean-up."""

from __future__ import annotations

import decimal
import logging

import numpy as np

from gft_odom.core.constants import NS_PER_S
from gft_odom.core.geometry import poses_from_xyz_quat
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import GroundTruthError

log = logging.getLogger(__name__)

# Up to this share of stamps may step back in time (recording glitches): they are sorted with
# a warning. More than that means the file is not a time series and is rejected.
MAX_UNORDERED_FRACTION = 0.01
MIN_UNORDERED_ALLOWED = 2


def decimal_of(text: str) -> decimal.Decimal:
    """A finite decimal from its text, or ValueError (no float on the way: no drift)."""
    try:
        value = decimal.Decimal(text.strip())
    except decimal.InvalidOperation:
        raise ValueError(f'{text!r} is not a number') from None
    if not value.is_finite():
        raise ValueError(f'{text!r} is not finite')
    return value


def seconds_text_to_ns(text: str) -> int:
    """'1700000000.123456789' -> 1700000000123456789 exactly (rounded half-even past 1 ns)."""
    return int((decimal_of(text) * NS_PER_S).to_integral_value(decimal.ROUND_HALF_EVEN))


def ns_to_seconds_text(stamp_ns: int) -> str:
    """1700000000123456789 -> '1700000000.123456789' (9 decimals, exact, sign-correct)."""
    stamp_ns = int(stamp_ns)
    sign = '-' if stamp_ns < 0 else ''
    sec, nsec = divmod(abs(stamp_ns), NS_PER_S)
    return f'{sign}{sec}.{nsec:09d}'


def trajectory_from_columns(stamps_ns: np.ndarray, xyz: np.ndarray, quat_xyzw: np.ndarray,
                            what: str, drop_nonfinite: bool = False,
                            line_numbers: np.ndarray | None = None) -> Trajectory:
    """A Trajectory from pose columns, cleaned the same way for every source.

    Non-finite positions are dropped with a warning (`drop_nonfinite`, bag streams) or
    rejected; a zero or non-finite quaternion (GPS fixes carry no orientation) becomes the
    identity; a few stamps out of order are sorted with a warning, many are an error.
    """
    def where(index: int) -> str:
        return f'line {int(line_numbers[index])}' if line_numbers is not None else f'pose #{index}'

    stamps_ns = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    quat_xyzw = np.array(quat_xyzw, dtype=np.float64).reshape(-1, 4)
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        if not drop_nonfinite:
            raise GroundTruthError(f'{what}: {where(int(np.argmin(finite)))} has a non-finite '
                                   'position')
        log.warning('%s: dropping %d pose(s) with a non-finite position', what,
                    int((~finite).sum()))
        stamps_ns, xyz, quat_xyzw = stamps_ns[finite], xyz[finite], quat_xyzw[finite]
        line_numbers = None
    norm = np.linalg.norm(quat_xyzw, axis=1)
    no_rotation = ~np.isfinite(norm) | (norm < 1e-9)
    if no_rotation.any():
        log.info('%s: %d pose(s) without a valid orientation get the identity', what,
                 int(no_rotation.sum()))
        quat_xyzw[no_rotation] = (0.0, 0.0, 0.0, 1.0)
    steps_back = np.flatnonzero(np.diff(stamps_ns) < 0)
    if steps_back.size:
        allowed = max(MIN_UNORDERED_ALLOWED, int(MAX_UNORDERED_FRACTION * stamps_ns.size))
        first = where(int(steps_back[0]) + 1)
        if steps_back.size > allowed:
            raise GroundTruthError(f'{what}: time goes backwards {steps_back.size} times (first '
                                   f'at {first}); not a time-ordered trajectory')
        log.warning('%s: time goes backwards %d time(s) (first at %s); sorting by time',
                    what, steps_back.size, first)
        order = np.argsort(stamps_ns, kind='stable')
        stamps_ns, xyz, quat_xyzw = stamps_ns[order], xyz[order], quat_xyzw[order]
    return Trajectory(stamps_ns, poses_from_xyz_quat(xyz, quat_xyzw))
