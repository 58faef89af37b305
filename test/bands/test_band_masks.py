"""Mask enumeration, keys, content dedupe and the paper's analysis on hand-made rows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gft_odom.bands.analysis import band_correlation, correlation_at_nu, interval_counts, ranked
from gft_odom.bands.masks import (
    band_ranges,
    exhaustive_masks,
    keep_fingerprint,
    mask_key,
    narrow_interval_membership,
    parse_mask_key,
)
from gft_odom.core.spectral.bands import BandMask
from gft_odom.core.spectral.filter import PointFrequencies, keep_mask
from gft_odom.errors import ConfigError


def test_exhaustive_count_matches_the_paper():
    masks = exhaustive_masks(2, 10)
    assert len(masks) == sum(2 ** b - 1 for b in range(2, 11)) == 2035
    assert len({mask_key(m) for m in masks}) == len(masks)


def test_exhaustive_rejects_bad_ranges():
    with pytest.raises(ConfigError):
        exhaustive_masks(4, 3)
    with pytest.raises(ConfigError):
        exhaustive_masks(2, 20)


@pytest.mark.parametrize('key', ['B2:01', 'B10:1000000011', 'B5:11111'])
def test_mask_key_round_trip(key):
    assert mask_key(parse_mask_key(key)) == key


def test_bad_mask_key_is_a_config_error():
    with pytest.raises(ConfigError):
        parse_mask_key('nonsense')


def _frequencies(band: np.ndarray) -> PointFrequencies:
    n = band.size
    return PointFrequencies(nu=np.full(n, np.nan, np.float32), band=band, n_bands=4,
                            isolated=band == 0, in_range=np.ones(n, bool),
                            finite=np.ones(n, bool), n_slices=1)


def test_fingerprint_equal_only_for_identical_kept_points():
    rng = np.random.default_rng(1)
    # Bands at B = 4 where band 4 is never used: {1,2,3} keeps the same points as all-pass.
    freqs = [_frequencies(rng.integers(0, 4, size=50).astype(np.int16)) for _ in range(3)]
    fp = {m: keep_fingerprint(keep_mask(f, BandMask(4, frozenset(m))) for f in freqs)
          for m in [(1, 2, 3), (1, 2, 3, 4), (1, 2), (1, 2, 4)]}
    assert fp[(1, 2, 3)] == fp[(1, 2, 3, 4)]
    assert fp[(1, 2)] == fp[(1, 2, 4)]
    assert fp[(1, 2)] != fp[(1, 2, 3)]


def test_narrow_intervals_follow_band_ranges():
    counts = narrow_interval_membership([BandMask(2, frozenset({1})),
                                         BandMask(4, frozenset({1, 4}))], 1000)
    assert counts[:250].tolist() == [2] * 250
    assert counts[250:500].tolist() == [1] * 250
    assert counts[500:750].tolist() == [0] * 250
    assert counts[750:].tolist() == [1] * 250
    assert band_ranges(BandMask(4, frozenset({1, 2, 4}))) == [(0.0, 0.5), (0.75, 1.0)]


def _row(mask: BandMask, err: float) -> dict:
    return {'key': mask_key(mask), 'n_bands': mask.n_bands, 'bands': mask.as_list(),
            'mask': mask.as_bitstring(), 'ate_rmse_m': err, 'points_kept_fraction': 0.5}


def test_correlation_sign_and_ranking():
    rng = np.random.default_rng(0)
    rows = []
    for mask in exhaustive_masks(4, 4):
        # Keeping band 2 lowers the error, band 4 raises it, bands 1 and 3 are noise.
        err = 1.0 - 0.5 * (2 in mask.bands) + 0.3 * (4 in mask.bands) + 0.01 * rng.random()
        rows.append(_row(mask, err))
    corr = band_correlation(rows, 4)
    assert corr[1] < -0.8 and corr[3] > 0.5
    assert abs(corr[0]) < 0.3 and abs(corr[2]) < 0.3
    best = ranked(rows)[0]
    assert 2 in best['bands'] and 4 not in best['bands']
    nu_corr = correlation_at_nu({4: corr}, np.array([0.3, 0.9]))
    assert nu_corr[0] == pytest.approx(corr[1]) and nu_corr[1] == pytest.approx(corr[3])
    top = interval_counts(rows, top_k=3, n_intervals=8)
    assert top[2] == top[3] == 3 and top[6] == top[7] == 0


def test_ranking_puts_failed_masks_last_and_skips_duplicates():
    a, b, c = (BandMask(2, frozenset(s)) for s in ({1}, {2}, {1, 2}))
    rows = [_row(a, None), _row(b, 0.2), dict(_row(c, 0.1), duplicate_of='B2:01')]
    order = ranked(rows)
    assert [r['key'] for r in order] == ['B2:01', 'B2:10']
    assert math.isnan(band_correlation(rows, 2)[0])
