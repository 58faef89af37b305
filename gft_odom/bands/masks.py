"""Band masks to try, their keys, and which of them provably select the same points.

Deduplication is by content, not by arithmetic on band edges: with `band_assignment='argmax'`
(the default) a point's band at B is the argmax of its B band responses, so band 1 at B = 2 is
NOT the union of bands 1-2 at B = 4 (the responses are re-binned, and the argmax moves). Two
masks are treated as one only when they keep exactly the same points in every cached scan:
the pipeline is deterministic, so identical inputs give identical trajectories. That covers
the interval case of `dominant` frequencies, the all-pass masks of every B, and masks that
differ only in bands no point falls into.
"""

from __future__ import annotations

import hashlib
import itertools
from typing import Iterable, Sequence

import numpy as np

from gft_odom.core.spectral.bands import BandMask, band_edges, band_of_nu
from gft_odom.errors import ConfigError


def mask_key(mask: BandMask) -> str:
    """Stable text key of a mask, e.g. 'B4:1001' (band 1 first)."""
    return f'B{mask.n_bands}:{mask.as_bitstring()}'


def parse_mask_key(key: str) -> BandMask:
    """Inverse of `mask_key`."""
    try:
        head, bits = key.split(':', 1)
        n_bands = int(head.lstrip('B'))
    except ValueError:
        raise ConfigError(f'cannot read mask key {key!r}: expected like "B4:1001"') from None
    return BandMask.parse(bits, n_bands)


def exhaustive_masks(min_bands: int, max_bands: int) -> list[BandMask]:
    """Every non-empty band combination for each B in [min_bands, max_bands] (2035 for 2..10).

    Ordered by B, then by the number of kept bands, then lexicographically."""
    if not 1 <= min_bands <= max_bands:
        raise ConfigError(f'need 1 <= min_bands <= max_bands, got {min_bands}..{max_bands}')
    if max_bands > 16:
        raise ConfigError(f'max_bands = {max_bands}: 2^B masks per B is too many for an '
                          'exhaustive search above 16 bands; use the smart search')
    masks = []
    for n in range(min_bands, max_bands + 1):
        for k in range(1, n + 1):
            for combo in itertools.combinations(range(1, n + 1), k):
                masks.append(BandMask(n, frozenset(combo)))
    return masks


def identity_masks(band_counts: Iterable[int]) -> list[BandMask]:
    """The identity (every band kept) at each band count: the candidate a filter must beat."""
    return [BandMask.all_pass(n) for n in sorted(set(band_counts))]


def keep_fingerprint(keeps: Iterable[np.ndarray]) -> str:
    """Hash of the points a mask keeps, one (n,) bool array per scan (the caller's order)."""
    digest = hashlib.blake2b(digest_size=16)
    for keep in keeps:
        digest.update(np.packbits(keep).tobytes())
        digest.update(np.int64(keep.size).tobytes())
    return digest.hexdigest()


def narrow_interval_membership(masks: Sequence[BandMask], n_intervals: int = 1000
                               ) -> np.ndarray:
    """(n_intervals,) count of masks whose kept bands cover each narrow nu interval.

    Interval i covers nu in [i/n, (i+1)/n); it belongs to band floor(centre * B) + 1, the band
    whose nu range contains it (exact for interval-assigned frequencies, the paper's reading;
    with argmax assignment a band is the set of points whose response peaks there, so this is
    the band's nominal nu range)."""
    centres = (np.arange(n_intervals) + 0.5) / n_intervals
    counts = np.zeros(n_intervals, dtype=np.int64)
    for mask in masks:
        counts += mask.lookup()[band_of_nu(centres, mask.n_bands)]
    return counts


def band_ranges(mask: BandMask) -> list[tuple[float, float]]:
    """(lo, hi) nu range of each kept band, merged where adjacent."""
    edges = band_edges(mask.n_bands)
    ranges: list[tuple[float, float]] = []
    for b in mask.as_list():
        lo, hi = float(edges[b - 1]), float(edges[b])
        if ranges and abs(ranges[-1][1] - lo) < 1e-12:
            ranges[-1] = (ranges[-1][0], hi)
        else:
            ranges.append((lo, hi))
    return ranges
