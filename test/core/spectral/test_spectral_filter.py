"""The spectral filter on a small synthetic orchard scene."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gft_odom.core.spectral import BandMask, SpectralConfig, SpectralFilter, keep_mask
from gft_odom.errors import ConfigError, SpectralError


@pytest.fixture(scope='module')
def orchard_points() -> np.ndarray:
    """Trunk circles, canopy blobs, a patch of ground and scattered noise (sensor frame)."""
    rng = np.random.default_rng(42)
    parts = []
    for cx, cy in [(3.0, 3.0), (6.5, 3.1), (3.2, -3.0), (6.4, -2.9)]:
        angle = rng.uniform(-np.pi, 0.0, 60) + np.arctan2(cy, cx)
        z = rng.uniform(-0.7, 0.1, 60)
        parts.append(np.column_stack([cx + 0.12 * np.cos(angle), cy + 0.12 * np.sin(angle), z]))
        blob = rng.normal([cx, cy, 1.3], [0.6, 0.6, 0.4], (150, 3))
        parts.append(blob)
    gx, gy = np.meshgrid(np.linspace(-2.0, 2.0, 20), np.linspace(-2.0, 2.0, 20))
    ground = np.column_stack([gx.ravel(), gy.ravel(), rng.normal(-0.7, 0.02, gx.size)])
    parts.append(ground)
    parts.append(rng.uniform([-10, -10, -1.0], [10, 10, 3.0], (30, 3)))
    return np.concatenate(parts)


def small_filter(**overrides) -> SpectralFilter:
    """The `signal` definition on the slice graph (these tests check that path)."""
    settings = {'method': 'signal', 'graph': 'slice', **overrides}
    cfg = dataclasses.replace(SpectralConfig(), tau_m=0.3, sigma_m=0.15, **settings)
    return SpectralFilter.from_config(cfg)


def test_default_config_is_valid_and_ros_friendly():
    cfg = SpectralConfig()
    cfg.validate()
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        assert isinstance(value, (bool, int, float, str, tuple)), f.name
        if isinstance(value, tuple):
            assert value and all(isinstance(v, type(value[0])) for v in value), f.name
    assert BandMask.parse(cfg.band_mask, cfg.n_bands) == BandMask.all_pass(cfg.n_bands)


@pytest.mark.parametrize('field,value,match', [
    ('tau_m', 0.0, 'tau_m'),
    ('sigma_m', -1.0, 'sigma_m'),
    ('z_max_m', -2.0, 'z_max_m'),
    ('band_mask', (1, 11), 'outside'),
    ('n_bands', 0, 'n_bands'),
    ('method', 'loudest', 'method'),
    ('solver', 'magic', 'solver'),
    ('chebyshev_order', 0, 'chebyshev_order'),
    ('tau_m', 0.04, "slice graph's node size"),
    ('scan_line_weight', 'loudness', 'scan_line_weight'),
])
def test_invalid_config_raises_config_error(field, value, match):
    with pytest.raises(ConfigError, match=match):
        dataclasses.replace(SpectralConfig(), **{field: value}).validate()


def test_all_pass_keeps_every_point_and_bands_partition(orchard_points):
    filt = small_filter()
    result = filt.apply(orchard_points)
    assert result.keep.shape == (len(orchard_points),)
    assert result.keep.all()
    freqs = filt.frequencies(orchard_points)
    # Every point is in exactly one band 0..B; band 0 is exactly the points with no spectrum.
    assert np.all((freqs.band >= 0) & (freqs.band <= freqs.n_bands))
    no_spectrum = freqs.isolated | ~freqs.in_range
    np.testing.assert_array_equal(freqs.band == 0, no_spectrum)
    np.testing.assert_array_equal(np.isnan(freqs.nu), no_spectrum)
    assert np.all((freqs.nu[~no_spectrum] >= 0.0) & (freqs.nu[~no_spectrum] <= 1.0))
    assert freqs.isolated.any()  # the scattered noise points
    kept = [filt.keep_mask(freqs, BandMask(10, frozenset({b}))) & ~no_spectrum
            for b in range(1, 11)]
    np.testing.assert_array_equal(np.sum(kept, axis=0), (~no_spectrum).astype(int))
    assert set(result.timings_s) >= {'graph', 'lambda_max', 'prepare', 'total'}


def test_cached_frequencies_refilter_with_any_mask(orchard_points):
    filt = small_filter(keep_isolated=False)
    freqs = filt.frequencies(orchard_points)
    low = filt.keep_mask(freqs, BandMask.parse('1100000000'))
    high = filt.keep_mask(freqs, BandMask.parse('0000000011'))
    assert not np.any(low & high)
    np.testing.assert_array_equal(low, np.isin(freqs.band, [1, 2]) | ~freqs.in_range)
    both = keep_mask(freqs, BandMask.parse('1100000011'), False)
    np.testing.assert_array_equal(both, low | high)
    assert 0 < both.sum() < len(orchard_points)
    with pytest.raises(ConfigError, match='n_bands'):
        filt.keep_mask(freqs, BandMask.parse('11111'))


def test_isolated_points_are_kept_on_request_and_out_of_range_ones_always(orchard_points):
    pts = np.vstack([orchard_points, [[50.0, 50.0, 0.0], [0.0, 0.0, 9.0], [np.nan, 0.0, 0.0]]])
    mask = BandMask.parse([1], 10)
    for keep_iso in (True, False):
        filt = small_filter(keep_isolated=keep_iso)
        freqs = filt.frequencies(pts)
        keep = filt.keep_mask(freqs, mask)
        assert freqs.isolated[-3] and not freqs.in_range[-2] and not freqs.in_range[-1]
        assert keep[-3] == keep_iso and keep[-2]  # never looked at: never dropped
        assert not keep[-1]  # non-finite points are never kept


def test_fast_path_agrees_with_exact_path(orchard_points):
    fast = small_filter(chebyshev_order=60).frequencies(orchard_points)
    exact = small_filter(solver='exact').frequencies(orchard_points)
    has = fast.band > 0
    np.testing.assert_array_equal(exact.band > 0, has)
    assert np.mean(fast.band[has] == exact.band[has]) > 0.9
    assert np.median(np.abs(fast.nu[has] - exact.nu[has])) < 0.02


def test_responses_on_request_match_the_bands(orchard_points):
    filt = small_filter()
    freqs = filt.frequencies(orchard_points, with_response=True)
    assert filt.frequencies(orchard_points).response is None
    has = freqs.band > 0
    assert freqs.response.shape == (len(orchard_points), 10)
    np.testing.assert_array_equal(np.argmax(freqs.response[has], axis=1) + 1, freqs.band[has])
    assert np.all(freqs.response[~has] == 0.0)


def test_frequencies_multi_matches_single_calls(orchard_points):
    filt = small_filter()
    multi = filt.frequencies_multi(orchard_points, (3, 10))
    for n in (3, 10):
        single = filt.frequencies(orchard_points, n_bands=n)
        np.testing.assert_array_equal(multi[n].band, single.band)
        np.testing.assert_allclose(multi[n].nu, single.nu, equal_nan=True)


def test_degenerate_inputs_do_not_crash():
    filt = small_filter()
    empty = filt.apply(np.zeros((0, 3)))
    assert empty.keep.shape == (0,) and empty.n_slices == 0
    one = filt.frequencies(np.array([[1.0, 2.0, 0.0]]))
    assert one.band[0] == 0 and one.isolated[0]
    far = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
    assert np.all(filt.frequencies(far).band == 0)
    freqs = filt.frequencies(np.zeros((5, 3)))  # coincident points: perfectly smooth
    np.testing.assert_array_equal(freqs.band, 1)
    np.testing.assert_allclose(freqs.nu, 0.0)
    pair = filt.frequencies(np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]))
    assert np.all(pair.band == 10)  # two joined points: the only non-zero mode is the top one
    with pytest.raises(SpectralError, match='shape'):
        filt.apply(np.zeros((4, 2)))
