"""Equal frequency bands on nu = lambda / lambda_max and the masks that select them.

Band b (1-based, b = 1..B) covers nu in [(b-1)/B, b/B); nu = 1 belongs to band B. Band 0 is
reserved for points with no spectrum (isolated points, points outside the slicing z range).
A mask is written in configs as a list of band numbers (`[1, 9, 10]`) and shown as a 0/1 string
with band 1 first (`"1000000011"`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from gft_odom.errors import ConfigError

MAX_BANDS = 1000


def validate_n_bands(n_bands: int) -> int:
    """`n_bands` as an int, or ConfigError when it is not a usable band count."""
    if isinstance(n_bands, bool) or not isinstance(n_bands, (int, np.integer)):
        raise ConfigError(f'n_bands must be an integer, got {n_bands!r}')
    if not 1 <= int(n_bands) <= MAX_BANDS:
        raise ConfigError(f'n_bands must be in 1..{MAX_BANDS}, got {n_bands}')
    return int(n_bands)


def band_edges(n_bands: int) -> np.ndarray:
    """The B + 1 band edges on nu: 0, 1/B, ..., 1."""
    return np.linspace(0.0, 1.0, validate_n_bands(n_bands) + 1)


def band_centres(n_bands: int) -> np.ndarray:
    """Centre (b - 1/2) / B of every band b = 1..B, as a (B,) array."""
    n = validate_n_bands(n_bands)
    return (np.arange(n, dtype=np.float64) + 0.5) / n


def band_of_nu(nu: np.ndarray, n_bands: int) -> np.ndarray:
    """Band number 1..B of each normalised frequency (nu clipped to [0, 1]; NaN -> band 0)."""
    n = validate_n_bands(n_bands)
    nu = np.asarray(nu, dtype=np.float64)
    finite = np.isfinite(nu)
    band = np.zeros(nu.shape, dtype=np.int16)
    b = np.floor(np.clip(nu[finite], 0.0, 1.0) * n).astype(np.int64) + 1
    band[finite] = np.minimum(b, n)
    return band


@dataclass(frozen=True)
class BandMask:
    """A set of kept bands out of `n_bands` equal bands (band numbers 1..n_bands)."""

    n_bands: int
    bands: frozenset[int]

    def __post_init__(self) -> None:
        validate_n_bands(self.n_bands)
        if not self.bands:
            raise ConfigError('a band mask must keep at least one band, got an empty mask')
        bad = sorted(b for b in self.bands if not 1 <= b <= self.n_bands)
        if bad:
            raise ConfigError(f'band mask {sorted(self.bands)}: bands {bad} are outside '
                              f'1..{self.n_bands} (n_bands = {self.n_bands})')

    @classmethod
    def all_pass(cls, n_bands: int) -> 'BandMask':
        """The mask keeping every band."""
        return cls(validate_n_bands(n_bands), frozenset(range(1, int(n_bands) + 1)))

    @classmethod
    def parse(cls, spec: 'str | Iterable[int] | BandMask', n_bands: int | None = None
              ) -> 'BandMask':
        """Read `[1, 9, 10]`, `(1, 9, 10)`, `"1, 9, 10"`, `"[1, 9, 10]"` or `"1000000011"`.

        A 0/1 string fixes the band count by its length; when `n_bands` is given too they must
        agree. A list of band numbers needs `n_bands`.
        """
        if isinstance(spec, BandMask):
            if n_bands is not None and validate_n_bands(n_bands) != spec.n_bands:
                raise ConfigError(f'band mask {spec} has {spec.n_bands} bands, expected {n_bands}')
            return spec
        if isinstance(spec, str):
            text = spec.strip()
            if re.fullmatch(r'[01]+', text) and (len(text) > 1 or n_bands in (None, 1)):
                if n_bands is not None and validate_n_bands(n_bands) != len(text):
                    raise ConfigError(f'band mask "{text}" has {len(text)} digits but n_bands '
                                      f'is {n_bands}')
                bands = frozenset(i + 1 for i, c in enumerate(text) if c == '1')
                if not bands:
                    raise ConfigError(f'band mask "{text}" keeps no band')
                return cls(len(text), bands)
            inner = text.strip('[]() ')
            if not re.fullmatch(r'\s*\d+\s*(,\s*\d+\s*)*,?\s*', inner):
                raise ConfigError(f'cannot read band mask {spec!r}: expected a 0/1 string like '
                                  f'"1000000011" or band numbers like "[1, 9, 10]"')
            values = [int(v) for v in inner.split(',') if v.strip()]
        else:
            try:
                values = list(spec)
            except TypeError:
                raise ConfigError(f'cannot read band mask {spec!r}: expected a list of band '
                                  f'numbers or a 0/1 string') from None
            for v in values:
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                    raise ConfigError(f'band mask {values!r}: band numbers must be integers, '
                                      f'got {v!r}')
        if n_bands is None:
            raise ConfigError(f'band mask {values!r} given as band numbers needs n_bands')
        if len(set(values)) != len(values):
            raise ConfigError(f'band mask {values!r} repeats a band')
        return cls(validate_n_bands(n_bands), frozenset(int(v) for v in values))

    @property
    def is_all_pass(self) -> bool:
        """Every band kept."""
        return len(self.bands) == self.n_bands

    def as_list(self) -> list[int]:
        """Band numbers in increasing order, as written in configs."""
        return sorted(self.bands)

    def as_bitstring(self) -> str:
        """0/1 string, band 1 first."""
        return ''.join('1' if b in self.bands else '0' for b in range(1, self.n_bands + 1))

    def lookup(self) -> np.ndarray:
        """(B + 1,) bool table indexed by band number; entry 0 (band 0) is False."""
        table = np.zeros(self.n_bands + 1, dtype=bool)
        table[self.as_list()] = True
        return table

    def __str__(self) -> str:
        return self.as_bitstring()
