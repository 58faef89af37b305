"""The decision between the best mask and the identity: a mask is returned only when it beats
keeping every band in-sample by more than the spread its shifted runs measure."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gft_odom.bands.choice import decide, score_range
from gft_odom.bands.evaluate import score, shifted_key

FRACTIONS = (1.0 / 3.0, 2.0 / 3.0)
IDENTITY = 'B2:11'
BEST = 'B2:01'


def _row(key: str, ate: float | None, fingerprint: str | None = None) -> dict:
    return {'key': key, 'ate_rmse_m': ate, 'fingerprint': fingerprint or key}


def _shifted(values: dict[str, tuple[float | None, ...]]) -> dict[str, dict]:
    return {shifted_key(k, f): _row(shifted_key(k, f), v)
            for k, vs in values.items() for f, v in zip(FRACTIONS, vs)}


def test_a_win_within_the_spread_keeps_the_identity():
    # The best mask is 1.5 mm better; its own shifted runs move by 3 mm: no real win.
    shifted = _shifted({IDENTITY: (0.0210, 0.0195), BEST: (0.0200, 0.0215)})
    d = decide(_row(IDENTITY, 0.0200), _row(BEST, 0.0185), shifted, FRACTIONS)
    assert d['chosen'] == 'identity' and d['chosen_key'] == IDENTITY
    assert d['spread_m'] == pytest.approx(0.003)
    assert d['identity_ate_rmse_m'] == 0.0200 and d['best_ate_rmse_m'] == 0.0185
    assert 'not more than the spread' in d['reason']


def test_a_win_beyond_the_spread_returns_the_mask():
    shifted = _shifted({IDENTITY: (0.0210, 0.0195), BEST: (0.0130, 0.0145)})
    d = decide(_row(IDENTITY, 0.0200), _row(BEST, 0.0120), shifted, FRACTIONS)
    assert d['chosen'] == 'best' and d['chosen_key'] == BEST
    assert d['spread_m'] == pytest.approx(0.0025)  # the larger range: the best mask's
    assert d['scores_by_shift'][BEST] == [0.0120, 0.0130, 0.0145]


def test_the_best_masks_own_range_counts():
    """The identity barely moves, the lucky mask does: its range is the spread."""
    shifted = _shifted({IDENTITY: (0.0201, 0.0200), BEST: (0.0190, 0.0215)})
    d = decide(_row(IDENTITY, 0.0200), _row(BEST, 0.0185), shifted, FRACTIONS)
    assert d['chosen'] == 'identity'
    assert d['spread_m'] == pytest.approx(0.003)


def test_a_tie_or_the_same_points_keep_the_identity():
    same = _shifted({IDENTITY: (0.02, 0.02), BEST: (0.02, 0.02)})
    tie = decide(_row(IDENTITY, 0.02), _row(BEST, 0.02), same, FRACTIONS)
    assert tie['chosen'] == 'identity' and tie['spread_m'] == 0.0
    # A mask that drops only empty bands keeps the identity's points: not a filter at all.
    twin = decide(_row(IDENTITY, 0.02, 'fp'), _row('B3:110', 0.02, 'fp'),
                  _shifted({IDENTITY: (0.02, 0.02)}), FRACTIONS)
    assert twin['chosen'] == 'identity' and 'keeps every point' in twin['reason']


def test_runs_without_an_error():
    # A shifted run without an error: the spread is unknown, so no mask is trusted.
    lost = _shifted({IDENTITY: (0.02, None), BEST: (0.01, 0.01)})
    d = decide(_row(IDENTITY, 0.02), _row(BEST, 0.01), lost, FRACTIONS)
    assert d['chosen'] == 'identity' and d['spread_m'] is None
    # The identity itself without an error: any scored mask beats it.
    d = decide(_row(IDENTITY, None), _row(BEST, 0.01),
               _shifted({IDENTITY: (None, None), BEST: (0.01, 0.012)}), FRACTIONS)
    assert d['chosen'] == 'best'
    assert score_range([0.1, math.nan]) == math.inf


def test_the_returned_mask_never_loses_to_the_identity_in_sample():
    rng = np.random.default_rng(7)
    chosen_best = 0
    for _ in range(500):
        ident, best = rng.uniform(0.01, 0.03, 2)
        shifted = _shifted({IDENTITY: tuple(ident + rng.normal(0, 0.002, 2)),
                            BEST: tuple(best + rng.normal(0, 0.002, 2))})
        rows = {IDENTITY: _row(IDENTITY, ident), BEST: _row(BEST, best)}
        d = decide(rows[IDENTITY], rows[BEST], shifted, FRACTIONS)
        assert score(rows[d['chosen_key']]) <= ident
        if d['chosen'] == 'best':
            chosen_best += 1
            assert ident - best > d['spread_m']
    assert 0 < chosen_best < 500  # both outcomes were exercised
