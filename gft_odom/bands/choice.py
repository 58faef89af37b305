"""Which mask the search returns: the best one only when it beats the identity (every band
kept) in-sample by more than the search's own run-to-run spread; the identity otherwise.

A mask ranked first out of thousands on a few training bags is partly ranked first by luck;
keeping every band costs nothing to trust. The spread measures that luck: the identity and
the best mask are run again with every training scan shifted by fractions of a source voxel
along x, y and z (`BandSearchConfig.spread_shifts`, 1/3 and 2/3 by default). The points and
the masks are the same; only where the registration's voxel grids (source and map) cut them
moves, and the poses are mapped back to the sensor exactly (`evaluate.run_sequence`). Each
mask's range is max - min over its unshifted and shifted scores; the spread is the larger of
the two ranges (the best mask's counts: a mask picked as the lowest of many is the one most
flattered by where the grid happened to fall). The rule is strict, so a tie keeps every band,
and the mask returned never scores worse in-sample than the identity.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from gft_odom.bands.analysis import ranked
from gft_odom.bands.evaluate import score, shifted_key
from gft_odom.bands.masks import mask_key
from gft_odom.core.spectral.bands import BandMask

SPREAD_METHOD = ('max - min of the in-sample ATE RMSE of the identity and of the best mask, '
                 'each run unshifted and with every scan shifted by {} of a source voxel '
                 '(x, y, z); the larger range')


def identity_key(min_bands: int) -> str:
    """Key of the identity the decision uses (all its band counts keep the same points)."""
    return mask_key(BandMask.all_pass(min_bands))


def score_range(scores: Sequence[float]) -> float:
    """max - min of one mask's scores; inf when one of them could not be scored."""
    values = np.asarray(scores, dtype=np.float64)
    return float(values.max() - values.min()) if np.isfinite(values).all() else math.inf


def keeps_the_same_points(row: dict, identity: dict) -> bool:
    """Whether `row` is the identity, or keeps exactly its points in every training scan."""
    fp = row.get('fingerprint')
    return row['key'] == identity['key'] or (fp is not None and fp == identity.get('fingerprint'))


def decide(identity: dict, best: dict, shifted: dict[str, dict],
           fractions: Sequence[float]) -> dict:
    """The decision between `best` and `identity` (result rows) with `shifted` holding their
    runs at each of `fractions` (keys from `shifted_key`): which is chosen, why, both scores
    and the spread."""
    same = keeps_the_same_points(best, identity)
    rows = [identity] if same else [identity, best]
    scores = {r['key']: [score(r), *(score(shifted[shifted_key(r['key'], f)])
                                     for f in fractions)] for r in rows}
    ranges = {k: score_range(v) for k, v in scores.items()}
    spread = max(ranges.values())
    s_id, s_best = score(identity), score(best)
    if same:
        chosen, reason = 'identity', 'the best mask is the identity (it keeps every point)'
    elif math.isfinite(s_best) and not math.isfinite(s_id):
        chosen, reason = 'best', 'the identity could not be scored on the training bags'
    elif not math.isfinite(spread):
        chosen, reason = 'identity', 'the spread could not be measured (a run has no error)'
    elif s_best < s_id - spread:
        chosen = 'best'
        reason = (f'the best mask beats the identity by {s_id - s_best:.4g} m, more than the '
                  f'spread {spread:.4g} m')
    else:
        chosen = 'identity'
        reason = (f'the best mask beats the identity by {s_id - s_best:.4g} m, not more than '
                  f'the spread {spread:.4g} m')
    return {
        'chosen': chosen, 'chosen_key': best['key'] if chosen == 'best' else identity['key'],
        'reason': reason,
        'identity_key': identity['key'], 'identity_ate_rmse_m': _finite(s_id),
        'best_key': best['key'], 'best_ate_rmse_m': _finite(s_best),
        'spread_m': _finite(spread),
        'spread_method': SPREAD_METHOD.format(', '.join(f'{f:.3g}' for f in fractions)),
        'shift_voxel_fractions': list(fractions),
        'scores_by_shift': {k: [_finite(x) for x in v] for k, v in scores.items()},
    }


def choose(search, rows: dict[str, dict], min_bands: int,
           fractions: Sequence[float]) -> tuple[dict, dict]:
    """(chosen row, decision) of a finished search (`search`: its `BandSearch`, which runs
    the shifted evaluations, resumed from `spread.jsonl`)."""
    identity = rows[identity_key(min_bands)]
    best = ranked(list(rows.values()))[0]
    keys = [identity['key']] + ([] if keeps_the_same_points(best, identity) else [best['key']])
    decision = decide(identity, best, search.evaluate_shifted(keys, fractions), fractions)
    return (best if decision['chosen'] == 'best' else identity), decision


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None
