"""Band masks: both written forms, validation, and the band of a frequency."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gft_odom.core.spectral.bands import BandMask, band_centres, band_of_nu
from gft_odom.errors import ConfigError


def test_both_forms_parse_to_the_same_mask():
    a = BandMask.parse([1, 9, 10], 10)
    b = BandMask.parse('1000000011')
    c = BandMask.parse('[1, 9, 10]', 10)
    assert a == b == c
    assert a.as_list() == [1, 9, 10]
    assert a.as_bitstring() == '1000000011'
    assert str(a) == '1000000011'
    np.testing.assert_array_equal(np.flatnonzero(a.lookup()), [1, 9, 10])


@given(st.integers(1, 12).flatmap(
    lambda n: st.tuples(st.just(n), st.sets(st.integers(1, n), min_size=1))))
def test_round_trip(case):
    n, bands = case
    mask = BandMask.parse(sorted(bands), n)
    assert BandMask.parse(mask.as_bitstring()) == mask
    assert BandMask.parse(str(mask.as_list()), n) == mask


@pytest.mark.parametrize('spec,n_bands,match', [
    ([], 10, 'at least one'),
    ('0000', None, 'keeps no band'),
    ([0, 3], 10, 'outside'),
    ([11], 10, 'outside'),
    ('101', 4, '3 digits'),
    ('1,x', 4, 'cannot read'),
    ([1, 1], 4, 'repeats'),
    ([1.5], 4, 'integers'),
    ([1, 2], None, 'needs n_bands'),
])
def test_invalid_masks_raise_config_error(spec, n_bands, match):
    with pytest.raises(ConfigError, match=match):
        BandMask.parse(spec, n_bands)


def test_all_pass_and_band_edges():
    assert BandMask.all_pass(4).as_bitstring() == '1111'
    nu = np.array([0.0, 0.0999, 0.1, 0.95, 1.0, np.nan, -0.2, 1.3])
    np.testing.assert_array_equal(band_of_nu(nu, 10), [1, 1, 2, 10, 10, 0, 1, 10])
    np.testing.assert_allclose(band_centres(4), [0.125, 0.375, 0.625, 0.875])
