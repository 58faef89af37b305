"""The band search: exhaustive or smart, resumable, ranked in-sample, scored held-out.

Results are appended to `results.jsonl` in the output folder one line per mask as soon as the
mask is done; a restarted search reads them back and evaluates only what is missing (a line
cut short by a kill is ignored). `search.json` records what the results depend on, so results
of another configuration are never mixed in. The identity mask (every band) is always among
the candidates; the runs that measure the spread go to `spread.jsonl`, apart from the ranking.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from gft_odom.bands.analysis import correlation_at_nu, correlation_table
from gft_odom.bands.cache import SequenceCache, load_or_build
from gft_odom.bands.evaluate import BASELINE_KEY, evaluate_mask, score, shifted_key
from gft_odom.bands.executors import make_executor
from gft_odom.bands.masks import (
    exhaustive_masks,
    identity_masks,
    keep_fingerprint,
    mask_key,
    parse_mask_key,
)
from gft_odom.config import GftOdomConfig, flatten
from gft_odom.core.spectral.bands import BandMask
from gft_odom.errors import ConfigError

log = logging.getLogger(__name__)

STRATEGIES = ('exhaustive', 'smart')
IN_SAMPLE = 'in-sample (training bags: the mask was chosen on them)'
HELD_OUT = 'held-out (test bags: not used to choose the mask)'


@dataclass(frozen=True)
class BandSearchConfig:
    """How the search runs; the pipeline itself is configured by `GftOdomConfig`."""

    # The paper's range: B = 2..10, 2035 masks.
    min_bands: int = 2
    max_bands: int = 10
    strategy: str = 'exhaustive'
    # Smart search: exhaustive up to this B gives the per-band correlation that seeds a beam
    # search over the masks of `max_bands` bands (flip one band at a time).
    smart_seed_max_bands: int = 3
    beam_width: int = 2
    smart_max_rounds: int = 8
    # Figures 6 and 8 of the paper.
    top_k_figure: int = 10
    top_k_intervals: int = 20
    n_intervals: int = 1000
    # The spread's runs: every training scan shifted by these fractions of a source voxel
    # (x, y and z), the identity and the best mask run again (see `bands.choice`).
    spread_shifts: tuple[float, ...] = (1.0 / 3.0, 2.0 / 3.0)

    def validate(self) -> None:
        """Raise ConfigError naming the first setting that cannot work."""
        if not 1 <= self.min_bands <= self.max_bands:
            raise ConfigError(f'need 1 <= min_bands <= max_bands, got min_bands = '
                              f'{self.min_bands}, max_bands = {self.max_bands}')
        if self.strategy not in STRATEGIES:
            raise ConfigError(f'strategy must be one of {STRATEGIES}, got {self.strategy!r}')
        if self.strategy == 'exhaustive' and self.max_bands > 16:
            raise ConfigError(f'max_bands = {self.max_bands} is too many for an exhaustive '
                              'search (2^B masks per B); use strategy smart')
        if self.strategy == 'smart' and not (
                self.min_bands <= self.smart_seed_max_bands <= self.max_bands):
            raise ConfigError(f'smart_seed_max_bands ({self.smart_seed_max_bands}) must be in '
                              f'[min_bands, max_bands] = [{self.min_bands}, {self.max_bands}]')
        for name in ('beam_width', 'smart_max_rounds', 'top_k_figure', 'top_k_intervals',
                     'n_intervals'):
            if getattr(self, name) < 1:
                raise ConfigError(f'{name} must be >= 1, got {getattr(self, name)}')
        if not self.spread_shifts or not all(0.0 < f < 1.0 for f in self.spread_shifts):
            raise ConfigError(f'spread_shifts must be fractions of a voxel in (0, 1), got '
                              f'{self.spread_shifts}')


@dataclass(frozen=True)
class SequenceSpec:
    """One sequence: its bag file(s) and ground truth."""

    bags: tuple[str, ...]
    gt_path: str
    name: str = ''

    @property
    def label(self) -> str:
        """The name given, else the first bag's file name."""
        return self.name or Path(self.bags[0]).name


class SearchStopped(Exception):
    """Raised after `ResultsLog.limit` new results: a deliberate stop, like a kill."""


class ResultsLog:
    """`results.jsonl`: one JSON object a line, appended and flushed per result."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.rows: dict[str, dict] = {}
        self.limit: int | None = None  # stop after this many appends (None: never)
        self.appended = 0
        if self.path.exists():
            self._read()

    def _read(self) -> None:
        lines = self.path.read_text().splitlines()
        good = 0
        for n, line in enumerate(lines):
            try:
                row = json.loads(line)
            except json.JSONDecodeError as exc:
                if n == len(lines) - 1:
                    log.warning('%s: last line is incomplete (search killed mid-write); '
                                'that mask will be evaluated again', self.path)
                    break
                raise ConfigError(f'{self.path}: line {n + 1} is not JSON') from exc
            self.rows[row['key']] = row
            good += 1
        # Drop a torn tail so the next append starts on a fresh line.
        text = ''.join(line + '\n' for line in lines[:good])
        if text != self.path.read_text():
            self.path.write_text(text)

    def __contains__(self, key: str) -> bool:
        return key in self.rows

    def append(self, row: dict) -> None:
        """Add one result row to the log, flushed to disk at once (a kill keeps it)."""
        with self.path.open('a') as f:
            f.write(json.dumps(row, sort_keys=True, default=_json_default) + '\n')
            f.flush()
            os.fsync(f.fileno())
        self.rows[row['key']] = row
        self.appended += 1
        if self.limit is not None and self.appended >= self.limit:
            raise SearchStopped(f'stopped after {self.appended} new results')


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f'{type(value).__name__} is not JSON serialisable')


def search_key(config: GftOdomConfig, caches: Sequence[SequenceCache]) -> str:
    """What results depend on: every parameter but the mask and the ROS-only `node` section,
    and the cached inputs."""
    flat = {k: v for k, v in flatten(config).items()
            if k not in ('spectral.n_bands', 'spectral.band_mask',
                         'pipeline.use_spectral_filter') and not k.startswith('node.')}
    text = json.dumps({'config': flat, 'caches': [c.key for c in caches]}, sort_keys=True,
                      default=list)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


class BandSearch:
    """Evaluates masks on the training sequences: dedupe, resume, executor, results log."""

    def __init__(self, train: Sequence[SequenceCache], config: GftOdomConfig, out_dir: str | Path,
                 cache_paths: Sequence[Path] | None = None, workers: int = 1,
                 ray_address: str | None = None) -> None:
        self.train = list(train)
        self.config = config
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.cache_paths = cache_paths
        self.workers = workers
        self.ray_address = ray_address
        self._check_meta()
        self.log = ResultsLog(self.out / 'results.jsonl')
        self.spread_log = ResultsLog(self.out / 'spread.jsonl')
        self._fingerprints: dict[str, str] = {}
        self._by_fingerprint: dict[str, str] = {
            r['fingerprint']: k for k, r in self.log.rows.items()
            if r.get('fingerprint') and not r.get('duplicate_of')}
        self._executor = None
        self.n_evaluated = 0  # masks actually run by this object (not resumed, not duplicates)

    def _check_meta(self) -> None:
        meta_path = self.out / 'search.json'
        meta = {'search_key': search_key(self.config, self.train),
                'train': [s.name for s in self.train],
                'registration_mode': self.config.registration.mode}
        if meta_path.exists():
            old = json.loads(meta_path.read_text())
            if old.get('search_key') != meta['search_key']:
                raise ConfigError(f'{self.out} holds results of a search with other inputs or '
                                  f'parameters (train {old.get("train")}, mode '
                                  f'{old.get("registration_mode")}); use another --out')
        else:
            meta_path.write_text(json.dumps(meta, indent=2) + '\n')

    def fingerprint(self, mask: BandMask) -> str:
        """Hash of the points `mask` keeps in every training scan (equal: same result)."""
        key = mask_key(mask)
        if key not in self._fingerprints:
            flags = (self.config.spectral.keep_isolated,)
            self._fingerprints[key] = keep_fingerprint(
                seq.keep(i, mask, *flags) for seq in self.train for i in range(len(seq)))
        return self._fingerprints[key]

    def evaluate(self, masks: Sequence[BandMask | None],
                 progress: Callable[[int, int], None] | None = None) -> dict[str, dict]:
        """Rows of `masks` (None: the baseline), evaluating only what is not in the log yet."""
        wanted = {(BASELINE_KEY if m is None else mask_key(m)): m for m in masks}
        todo: list[str] = []
        duplicates: dict[str, list[str]] = {}
        for key, mask in wanted.items():
            if key in self.log:
                continue
            if mask is not None:
                fp = self.fingerprint(mask)
                rep = self._by_fingerprint.get(fp)
                if rep is not None and rep != key:
                    if rep in self.log:
                        self.log.append(self._duplicate_row(self.log.rows[rep], mask, fp))
                    else:
                        duplicates.setdefault(rep, []).append(key)
                    continue
                self._by_fingerprint[fp] = key
            todo.append(key)
        total = len(wanted)
        done = total - len(todo) - sum(map(len, duplicates.values()))
        if progress is not None:
            progress(done, total)
        if todo:
            executor = self._get_executor()
            for row in executor.run(todo):
                if row['key'] != BASELINE_KEY:
                    row['fingerprint'] = self.fingerprint(parse_mask_key(row['key']))
                row['evaluated_on'] = 'train'
                self.log.append(row)
                self.n_evaluated += 1
                done += 1
                for dup in duplicates.pop(row['key'], []):
                    self.log.append(self._duplicate_row(row, parse_mask_key(dup),
                                                        row['fingerprint']))
                    done += 1
                if progress is not None:
                    progress(done, total)
        return {k: self.log.rows[k] for k in wanted}

    def evaluate_shifted(self, keys: Sequence[str], fractions: Sequence[float]
                         ) -> dict[str, dict]:
        """Rows of the masks `keys` run with every scan shifted by each of `fractions` of a
        source voxel, keyed by `shifted_key`; evaluated only when not in `spread.jsonl`."""
        wanted = [shifted_key(k, f) for k in keys for f in fractions]
        todo = [k for k in dict.fromkeys(wanted) if k not in self.spread_log]
        if todo:
            for row in self._get_executor().run(todo):
                row['evaluated_on'] = 'train'
                self.spread_log.append(row)
        return {k: self.spread_log.rows[k] for k in wanted}

    @staticmethod
    def _duplicate_row(rep: dict, mask: BandMask, fp: str) -> dict:
        row = dict(rep, key=mask_key(mask), n_bands=mask.n_bands, mask=mask.as_bitstring(),
                   bands=mask.as_list(), n_kept_bands=len(mask.bands), duplicate_of=rep['key'],
                   fingerprint=fp, eval_s=0.0)
        return row

    def _get_executor(self):
        if self._executor is None:
            self._executor = make_executor(self.train, self.cache_paths, self.config,
                                           self.workers, self.ray_address)
        return self._executor

    def close(self) -> None:
        """Release the executor (worker processes, Ray connection)."""
        if self._executor is not None:
            self._executor.close()
            self._executor = None

    # -- strategies ----------------------------------------------------------------------------

    def exhaustive(self, min_bands: int, max_bands: int,
                   progress: Callable[[int, int], None] | None = None) -> dict[str, dict]:
        """Every non-empty combination for B in [min_bands, max_bands], plus the baseline;
        the identities first, so the identity of min_bands stands for every all-pass twin."""
        counts = range(min_bands, max_bands + 1)
        return self.evaluate([None, *identity_masks(counts),
                              *exhaustive_masks(min_bands, max_bands)], progress)

    def smart(self, cfg: BandSearchConfig,
              progress: Callable[[int, int], None] | None = None) -> dict[str, dict]:
        """Exhaustive for small B, then a beam search over masks of `max_bands` bands, started
        from the bands the correlation says lower the error and moved one band flip at a time.
        Returns every row it evaluated."""
        rows = dict(self.exhaustive(cfg.min_bands, cfg.smart_seed_max_bands, progress))
        n = cfg.max_bands
        if n > cfg.smart_seed_max_bands:
            table = correlation_table(list(rows.values()))
            centres = (np.arange(n) + 0.5) / n
            corr = correlation_at_nu(table, centres)
            helpful = [b + 1 for b in range(n) if np.isfinite(corr[b]) and corr[b] < 0.0]
            if not helpful:
                helpful = [int(np.nanargmin(np.where(np.isfinite(corr), corr, np.inf))) + 1]
            starts = [BandMask(n, frozenset(helpful)), BandMask.all_pass(n)]
            rows.update(self.evaluate(starts))
            beam = sorted({mask_key(m) for m in starts}, key=lambda k: score(rows[k]))
            beam = beam[:cfg.beam_width]
            best = min(score(rows[k]) for k in beam)
            for _ in range(cfg.smart_max_rounds):
                neighbours = []
                for key in beam:
                    bands = parse_mask_key(key).bands
                    for b in range(1, n + 1):
                        flipped = bands ^ {b}
                        if flipped:
                            neighbours.append(BandMask(n, frozenset(flipped)))
                rows.update(self.evaluate(neighbours))
                pool = set(beam) | {mask_key(m) for m in neighbours}
                beam = sorted(pool, key=lambda k: (score(rows[k]), k))[:cfg.beam_width]
                new_best = score(rows[beam[0]])
                if not new_best < best:
                    break
                best = new_best
        return rows


def prepare_caches(specs: Sequence[SequenceSpec], config: GftOdomConfig,
                   band_counts: Sequence[int], cache_dir: str | Path | None,
                   topic: str = '/velodyne_points', max_scans: int | None = None,
                   progress: Callable[[str, int, int], None] | None = None
                   ) -> tuple[list[SequenceCache], list[Path] | None]:
    """Load or build the frequency cache of each sequence (saved under `cache_dir`)."""
    caches, paths = [], []
    names = _unique_names(specs)
    for spec, name in zip(specs, names):
        path = Path(cache_dir) / f'{name}.npz' if cache_dir is not None else None
        cb = (lambda d, t, name=name: progress(name, d, t)) if progress else None
        caches.append(load_or_build(path, spec.bags, spec.gt_path, config, band_counts,
                                    name=name, topic=topic, max_scans=max_scans, progress=cb))
        paths.append(path)
    return caches, (paths if cache_dir is not None else None)


def _unique_names(specs: Sequence[SequenceSpec]) -> list[str]:
    names: list[str] = []
    for spec in specs:
        name = spec.label.replace('/', '_')
        base, k = name, 2
        while name in names:
            name, k = f'{base}_{k}', k + 1
        names.append(name)
    return names


def held_out(test: Sequence[SequenceCache], config: GftOdomConfig, mask: BandMask) -> dict:
    """The chosen mask and the unfiltered baseline on the test sequences."""
    return {'chosen': evaluate_mask(test, config, mask),
            'baseline': evaluate_mask(test, config, None)}


def improvement_pct(row: dict, baseline: dict) -> float:
    """Relative ATE RMSE change against the baseline (negative: the mask is better)."""
    a, b = score(row), score(baseline)
    return 100.0 * (a - b) / b if math.isfinite(a) and b > 0 and math.isfinite(b) else math.nan


def summarise(rows: dict[str, dict], held: dict | None, mode: str, strategy: str,
              n_evaluated: int, chosen: dict, decision: dict) -> dict:
    """The JSON summary: the chosen mask beside the baseline in-sample and held-out, and the
    decision against the identity (both scores, the spread, why)."""
    base = rows.get(BASELINE_KEY)
    summary = {
        'registration_mode': mode,
        'strategy': strategy,
        'masks_considered': sum(1 for k in rows if k != BASELINE_KEY),
        'masks_evaluated': sum(1 for r in rows.values()
                               if r['key'] != BASELINE_KEY and not r.get('duplicate_of')),
        'masks_evaluated_this_run': n_evaluated,
        'chosen_mask': {'n_bands': chosen['n_bands'], 'band_mask': chosen['bands'],
                        'bitstring': chosen['mask'], 'is_identity':
                        decision['chosen'] == 'identity'},
        'decision': decision,
        'in_sample': {'label': IN_SAMPLE, 'chosen': _brief(chosen),
                      'best': _brief(rows[decision['best_key']]),
                      'identity': _brief(rows[decision['identity_key']]),
                      'baseline': _brief(base) if base else None,
                      'change_vs_baseline_pct': improvement_pct(chosen, base) if base else None},
    }
    if held is not None:
        summary['held_out'] = {'label': HELD_OUT, 'chosen': _brief(held['chosen']),
                               'baseline': _brief(held['baseline']),
                               'change_vs_baseline_pct': improvement_pct(held['chosen'],
                                                                         held['baseline'])}
    return summary


def _brief(row: dict) -> dict:
    keys = ('key', 'ate_rmse_m', 'ate_mean_m', 'paper_mse_m2', 'points_kept_fraction',
            'fallbacks')
    out = {k: row.get(k) for k in keys}
    out['per_sequence'] = {n: {k: v.get(k) for k in ('ate_rmse_m', 'ate_mean_m',
                                                     'paper_mse_m2', 'fallbacks')}
                           for n, v in row.get('per_sequence', {}).items()}
    return out


def band_counts_for(cfg: BandSearchConfig) -> list[int]:
    """The band counts B the search covers: min_bands..max_bands."""
    return list(range(cfg.min_bands, cfg.max_bands + 1))
