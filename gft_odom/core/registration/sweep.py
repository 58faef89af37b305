"""One scan on its way through `ScanRegistration.register`: its checked input, what the steps
make of it, and the smoothness the map's anchors keep its points by."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from gft_odom.core.deferred import Deferred, resolved
from gft_odom.core.deskew import deskew_points
from gft_odom.core.geometry import finite_rows
from gft_odom.errors import RegistrationError, SpectralError

# A point's smoothness = its graph frequency nu / SMOOTH_NU, clipped to [0, 1] (ground and
# trunks ~0.5 on the scan-line graph, canopy ~0): what the map's anchors keep it by.
SMOOTH_NU = 0.4


@dataclass
class Sweep:
    """One scan on its way through `register`: the whole scan and what the steps make of it."""

    points_xyz: np.ndarray  # (N, 3) the whole scan, sensor frame
    time_offset_s: np.ndarray | None  # (N,) per-point times from the bag, if any
    nu: np.ndarray | Deferred | None  # (N,) per-point graph frequency, if any
    keep: np.ndarray | None = None  # indices of the downsampled points
    source_xyz: np.ndarray | None = None  # the points ICP matches (downsampled, deskewed)
    point_smoothness: np.ndarray | Deferred | None = None  # theirs, as the map keeps it
    offsets_s: np.ndarray | None = None  # (N,) point times; set only when deskewed
    dt_s: float = 0.0  # since the previous scan
    scan_motion: np.ndarray | None = None  # its own motion, when re-deskewed with it

    @property
    def n_used(self) -> int:
        """How many points ICP matches."""
        return int(self.source_xyz.shape[0])

    def deskewed(self, motion: np.ndarray) -> np.ndarray:
        """The downsampled points deskewed with `motion` over the scan's `dt_s` (needs
        `offsets_s`)."""
        return deskew_points(self.points_xyz[self.keep], self.offsets_s[self.keep], motion,
                             self.dt_s)


def checked_input(points_xyz, time_offset_s, nu=None):
    """The scan's finite points with their times and frequencies; RegistrationError when the
    shapes do not agree."""
    points = np.asarray(points_xyz, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise RegistrationError(f'points_xyz must have shape (N, 3), got {points.shape}')
    if isinstance(nu, Deferred):
        nu = nu.then(partial(_checked_nu, n_points=points.shape[0]))
    elif nu is not None:
        nu = _checked_nu(nu, points.shape[0])
    if time_offset_s is not None:
        time_offset_s = np.asarray(time_offset_s, dtype=float).reshape(-1)
        if time_offset_s.shape[0] != points.shape[0]:
            raise RegistrationError(
                f'time_offset_s has {time_offset_s.shape[0]} values for '
                f'{points.shape[0]} points')
    finite = finite_rows(points)
    if time_offset_s is not None:
        finite &= np.isfinite(time_offset_s)
    if not finite.all():
        points = points[finite]
        time_offset_s = None if time_offset_s is None else time_offset_s[finite]
        if isinstance(nu, Deferred):
            nu = nu.then(lambda values: values[finite])
        elif nu is not None:
            nu = nu[finite]
    return points, time_offset_s, nu


def smoothness_from_nu(nu: np.ndarray, unknown: float = np.nan) -> np.ndarray:
    """Each point's smoothness in [0, 1] from its graph frequency (`unknown` where nu is
    NaN: a point without a spectrum)."""
    nu = np.asarray(nu, dtype=np.float64)
    return np.clip(np.nan_to_num(nu / SMOOTH_NU, nan=unknown), 0.0, 1.0)


def _checked_nu(values, n_points: int) -> np.ndarray:
    """`values` as the (n_points,) float frequencies of a scan."""
    nu = np.asarray(values, dtype=float).reshape(-1)
    if nu.shape[0] != n_points:
        raise RegistrationError(f'nu has {nu.shape[0]} values for {n_points} points')
    return nu


def map_smoothness(nu: np.ndarray | Deferred, index: np.ndarray) -> np.ndarray | Deferred:
    """The smoothness the map keeps for the points `index` (NaN: unknown); deferred with
    `nu`."""
    if isinstance(nu, Deferred):
        return nu.then(lambda values: smoothness_from_nu(values[index]))
    return smoothness_from_nu(nu[index])


def smoothness_or_unknown(smoothness: np.ndarray | Deferred | None, n_points: int
                           ) -> np.ndarray | None:
    """A keyframe's smoothness; unknown (NaN) when its deferred frequencies failed: the
    keyframe still goes into the map, as it would without frequencies."""
    try:
        return resolved(smoothness)
    except SpectralError:  # its caller said so (OdometryPipeline.update_map)
        return np.full(n_points, np.nan)
