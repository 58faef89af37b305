"""The benchmark of record: every method on the same long, varied drives, in one run.

A run is a list of `Entry` (a table label, a bench method of `runner.run_method`, and config
overrides for our own pipeline) over a list of drives. Every entry sees the same bags through
the same reader and clock; metrics are `replay.summarize`'s with KITTI's segment lengths
(100-800 m) plus 10 m, and CitrusFarm's own scoring beside the RMSE (mean position error after
the rigid alignment, and the end-point error). Results: one JSON, a Markdown page with the
per-drive and summary tables, and an ATE-over-distance figure.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from gft_odom.bench.runner import (
    ALL_METHODS,
    BenchSequence,
    MethodRun,
    method_config,
    run_method,
)
from gft_odom.config import GftOdomConfig, with_values
from gft_odom.core.metrics import STAMP_AUDIT_TOLERANCE_S, ate
from gft_odom.core.trajectory import Trajectory
from gft_odom.io.atomic import write_text_atomic
from gft_odom.io.ground_truth import read_ground_truth
from gft_odom.replay import estimate_for_ground_truth

# KITTI's segment lengths (as kiss-icp reports drift) and a short one for RPE per 10 m.
RPE_SHORT_M = 10.0
KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
RECORD_LENGTHS_M = (RPE_SHORT_M,) + KITTI_LENGTHS_M
STAMP_NOTE = (
    'Every method is stamped where its pose holds (ours: the stamp it deskews to; a sweep '
    'fitted as one rigid cloud: mid-sweep; kiss-icp: the sweep end it deskews to; CT-ICP: its '
    'begin pose). The stamp audit scores each run with its stamps shifted by -100..+100 ms in '
    '5 ms steps: the best shift is near 0 for a method stamped right; it cannot tell where a '
    'method whose error is metres holds.')
# The figure's log axis starts here: smaller errors are drawn at 1 mm.
ERROR_FLOOR_M = 1e-3
SCORING_NOTE = (
    'Every error is measured at the GPS antenna (the estimate moved there by the LiDAR -> GPS '
    'lever arm) after one rigid alignment of the positions. ATE RMSE is the root mean square '
    "of the position errors; mean error is their mean, CitrusFarm's own score (UCR-Robotics "
    'Odometry-Benchmark); end-point error is the distance between the aligned final '
    'positions.')


@dataclass(frozen=True)
class Entry:
    """One row of the record: `method` of the bench, our config with `overrides`."""

    label: str
    method: str
    overrides: tuple[tuple[str, object], ...] = ()

    def config(self, base: GftOdomConfig) -> GftOdomConfig:
        """The base config with the record's segment lengths and this entry's overrides."""
        values = {'evaluation.lengths_m': RECORD_LENGTHS_M, **dict(self.overrides)}
        return with_values(base, values)


@dataclass
class RecordRun:
    """What one record run measured: per (entry, drive) metrics and error-over-distance."""

    entries: list[Entry]
    sequences: list[BenchSequence]
    metrics: dict[tuple[str, str], dict] = field(default_factory=dict)
    # (label, drive) -> (distance travelled at each matched pose [m], ATE error there [m])
    error_curves: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict)


def kitti_drift_pct(metrics: dict, lengths_m: Sequence[float] = KITTI_LENGTHS_M) -> float:
    """Translation drift pooled over every segment of `lengths_m` (as the KITTI devkit)."""
    total = count = 0.0
    for length in lengths_m:
        n = metrics.get(f'rpe_count_{length:g}m') or 0
        value = metrics.get(f'rpe_drift_pct_{length:g}m')
        if n and value is not None:
            total += float(value) * n
            count += n
    return total / count if count else math.nan


def _error_curve(run: MethodRun) -> tuple[np.ndarray, np.ndarray]:
    """Distance along the estimate (a lost method's jitter lengthens it) and ATE error at each
    matched pose of one run. The cached curves of the record are kept this way."""
    ev = run.config.evaluation
    estimate = estimate_for_ground_truth(run.replay, run.config)
    result = ate(estimate, run.replay.ground_truth, mode='position', max_diff_s=ev.max_diff_s,
                 match=ev.match, max_gap_s=ev.max_gap_s)
    xyz = estimate.poses[result.est_idx, :3, 3]
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0),
                                                                axis=1))])
    return travelled, result.errors_m


def run_entry(entry: Entry, sequence: BenchSequence, base: GftOdomConfig
              ) -> tuple[dict, tuple[np.ndarray, np.ndarray], Trajectory]:
    """One entry on one drive: its flat metrics (plus KITTI drift), error curve and sensor
    trajectory (each pose stamped where it holds). A peer that dies inside its own library
    (GenZ-ICP's std::bad_alloc once its map runs away) is a result, `crashed`, not the end of
    the record; our own pipeline failing is a bug and raises."""
    try:
        run = run_method(entry.method, sequence, entry.config(base),
                         ground_truth=read_ground_truth(sequence.gt_path))
    except (MemoryError, RuntimeError) as exc:
        if _is_ours(entry.method):
            raise
        nothing = Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
        return ({'label': entry.label, 'crashed': f'{type(exc).__name__}: {exc}'},
                (np.zeros(0), np.zeros(0)), nothing)
    metrics = dict(run.metrics)
    metrics['label'] = entry.label
    metrics['kitti_drift_pct'] = kitti_drift_pct(metrics)
    metrics['rpe_10m_pct'] = metrics.get(f'rpe_drift_pct_{RPE_SHORT_M:g}m')
    return metrics, _error_curve(run), run.replay.sensor_trajectory


def _is_ours(method: str) -> bool:
    """Our pipeline (it has a registration mode) rather than a peer."""
    return ALL_METHODS[method][1] is not None


def cached_trajectory(cache_dir: Path, entry: Entry, sequence: BenchSequence,
                      base: GftOdomConfig | None = None) -> Trajectory | None:
    """The sensor trajectory a record run kept for (entry, drive); None when not kept."""
    path = pair_file(cache_dir, entry, sequence, base or GftOdomConfig())
    if not path.is_file():
        return None
    with np.load(path) as data:
        if 'stamps_ns' not in data:
            return None
        return Trajectory(data['stamps_ns'], data['poses'])


def pair_file(cache_dir: Path, entry: Entry, sequence: BenchSequence,
               base: GftOdomConfig) -> Path:
    """Where one (entry, drive) result is kept: named by label, method, drive and the whole
    config the method runs with, so a changed default is measured again, not reused. (A code
    change that leaves the config alone needs --fresh.)"""
    # kiss-icp's and the peers' odometry ignores our config; their scoring does not, so their
    # key holds the evaluation and ground-truth sections (a changed scoring re-measures them).
    config = method_config(entry.config(base), entry.method)
    keyed = (dataclasses.asdict(config) if _is_ours(entry.method) else
             [dataclasses.asdict(config.evaluation), dataclasses.asdict(config.ground_truth)])
    key = json.dumps([entry.label, entry.method, list(entry.overrides), keyed],
                     sort_keys=True, default=str)
    digest = hashlib.sha1(key.encode()).hexdigest()[:12]
    return Path(cache_dir) / f'{sequence.name}__{digest}.npz'


def _with_end_error(metrics: dict, curve: tuple[np.ndarray, np.ndarray]) -> dict:
    """`metrics` with `end_error_m` (a pair cached before it was measured has only its error
    curve: the curve's last value is the same figure, the rigid position alignment's)."""
    if metrics.get('end_error_m') is None and len(curve[1]):
        metrics = {**metrics, 'end_error_m': float(curve[1][-1])}
    return metrics


def _run_entry_job(args):
    entry, sequence, base, cache_dir, cached_only = args
    if cache_dir is not None:
        path = pair_file(cache_dir, entry, sequence, base)
        if path.is_file():  # measured before: reuse (a resumed or extended record)
            with np.load(path) as data:
                curve = (data['distance'], data['error'])
                return _with_end_error(json.loads(str(data['metrics'])), curve), curve
    if cached_only:
        return None
    metrics, curve, trajectory = run_entry(entry, sequence, base)
    if cache_dir is not None:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix('.partial.npz')
        np.savez(tmp, metrics=json.dumps(metrics, default=str), distance=curve[0],
                 error=curve[1], stamps_ns=trajectory.stamps_ns, poses=trajectory.poses)
        tmp.replace(path)
    return metrics, curve


def run_record(entries: Sequence[Entry], sequences: Sequence[BenchSequence],
               base: GftOdomConfig | None = None, jobs: int = 1,
               progress: Callable[[str, str], None] | None = None,
               cache_dir: Path | None = None, cached_only: bool = False) -> RecordRun:
    """Every entry on every drive; `jobs` > 1 runs (entry, drive) pairs in processes.

    With `cache_dir`, each pair's result is kept there and reused by later runs with the same
    label, method, overrides, drive and (for our methods) config, so a long record can be
    resumed or extended;
    `cached_only` reports what is there and measures nothing (missing pairs stay missing).
    """
    base = base or GftOdomConfig()
    for entry in entries:
        entry.config(base)  # a bad override fails before any work
    record = RecordRun(list(entries), list(sequences))
    if cached_only and cache_dir is None:
        raise ValueError('cached_only needs a cache_dir')
    work = [(entry, seq, base, cache_dir, cached_only) for seq in sequences
            for entry in entries]
    pool = ProcessPoolExecutor(max_workers=jobs) if jobs > 1 else None
    try:
        results = pool.map(_run_entry_job, work) if pool else map(_run_entry_job, work)
        for (entry, seq, *_), result in zip(work, results):
            if result is None:
                continue
            metrics, curve = result
            record.metrics[(entry.label, seq.name)] = metrics
            record.error_curves[(entry.label, seq.name)] = curve
            if progress is not None:
                progress(entry.label, seq.name)
    finally:
        if pool is not None:
            pool.shutdown()
    return record


def _table(header: list[str], rows: list[list[str]]) -> str:
    """A plain Markdown table, numbers right-aligned."""
    lines = ['| ' + ' | '.join(header) + ' |',
             '|---|' + '---:|' * (len(header) - 1)]
    lines += ['| ' + ' | '.join(row) + ' |' for row in rows]
    return '\n'.join(lines)


def _mean(values) -> float | None:
    clean = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(np.mean(clean)) if clean else None


def summarize_record(record: RecordRun) -> dict[str, dict]:
    """Per entry: means over drives (each drive once), latency medians pooled by drive."""
    out = {}
    for entry in record.entries:
        rows = [record.metrics[(entry.label, s.name)] for s in record.sequences
                if (entry.label, s.name) in record.metrics]
        out[entry.label] = {
            'ate_rmse_m': _mean(r.get('ate_rmse_m') for r in rows),
            'ate_mean_m': _mean(r.get('ate_mean_m') for r in rows),
            'end_error_m': _mean(r.get('end_error_m') for r in rows),
            'kitti_drift_pct': _mean(r.get('kitti_drift_pct') for r in rows),
            'rpe_10m_pct': _mean(r.get('rpe_10m_pct') for r in rows),
            'latency_median_ms': _mean(r.get('latency_median_ms') for r in rows),
            'latency_p95_ms': _mean(r.get('latency_p95_ms') for r in rows),
            'busy_mean_ms': _mean(r.get('busy_mean_ms') for r in rows),
            'latency_at_rate_p95_ms': _mean(r.get('latency_at_rate_p95_ms') for r in rows),
            'real_time_factor': _mean(r.get('real_time_factor') for r in rows),
            'fallbacks': int(sum(r.get('fallbacks') or 0 for r in rows)),
            'distance_m': float(sum(r.get('path_length_m') or 0.0 for r in rows)),
            'drives': len(rows),
            'crashed': sum(bool(r.get('crashed')) for r in rows),
            'best_on': sum(_is_best(record, entry.label, s.name) for s in record.sequences),
            **_stamp_summary(rows),
        }
    return out


def _is_best(record: RecordRun, label: str, drive: str) -> bool:
    """Whether `label` has the lowest ATE RMSE of every entry measured on `drive`."""
    scores = {e.label: record.metrics[(e.label, drive)].get('ate_rmse_m')
              for e in record.entries if (e.label, drive) in record.metrics}
    scores = {k: v for k, v in scores.items() if v is not None and math.isfinite(v)}
    return bool(scores) and label in scores and scores[label] == min(scores.values())


def _stamp_summary(rows: list[dict]) -> dict:
    """The stamp audit over drives: the median best shift and the drives outside the
    tolerance (a pose stamped away from where it holds)."""
    shifts = [r['stamp_best_shift_ms'] for r in rows if r.get('stamp_best_shift_ms') is not None]
    tolerance_ms = 1e3 * STAMP_AUDIT_TOLERANCE_S
    return {'stamp_best_shift_median_ms': float(np.median(shifts)) if shifts else None,
            'stamp_outside_tolerance': sum(abs(v) > tolerance_ms + 1e-9 for v in shifts)}


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return 'n/a'
    return f'{value:.{digits}f}' if isinstance(value, float) else str(value)


def summary_markdown(summary: dict[str, dict]) -> str:
    """The summary table: one row per entry."""
    header = ['method', 'drives', 'mean ATE RMSE [m]', 'best on', 'stamp shift, median [ms]',
              'drives off by > 10 ms', 'mean error [m]', 'end-point error [m]',
              'drift 100-800 m [%]', 'RPE 10 m [%]', 'latency median / p95 [ms]',
              'work a scan, mean [ms]', 'latency p95 at the sensor rate [ms]',
              'real-time factor', 'fallbacks']
    rows = [[label, _drives_cell(s), _fmt(s['ate_rmse_m']), str(s.get('best_on', 'n/a')),
             _fmt(s.get('stamp_best_shift_median_ms'), 0),
             str(s.get('stamp_outside_tolerance', 'n/a')), _fmt(s.get('ate_mean_m')),
             _fmt(s.get('end_error_m')), _fmt(s['kitti_drift_pct'], 2),
             _fmt(s['rpe_10m_pct'], 2),
             f"{_fmt(s['latency_median_ms'], 1)} / {_fmt(s['latency_p95_ms'], 1)}",
             _fmt(s.get('busy_mean_ms'), 1), _fmt(s.get('latency_at_rate_p95_ms'), 1),
             _fmt(s['real_time_factor'], 1), str(s['fallbacks'])]
            for label, s in summary.items()]
    return _table(header, rows)


def _drives_cell(summary: dict) -> str:
    """Drives run, and how many of them the method crashed on (no figure to average)."""
    crashed = summary.get('crashed') or 0
    return f"{summary['drives']} ({crashed} crashed)" if crashed else str(summary['drives'])


def per_drive_markdown(record: RecordRun, key: str = 'ate_rmse_m', digits: int = 3) -> str:
    """One row per drive, one column per entry, of metric `key`."""
    header = ['drive', 'length [m]'] + [e.label for e in record.entries]
    rows = []
    for seq in record.sequences:
        first = next((record.metrics[(e.label, seq.name)] for e in record.entries
                      if record.metrics.get((e.label, seq.name), {}).get('path_length_m')
                      is not None), {})
        cells = []
        for e in record.entries:
            metrics = record.metrics.get((e.label, seq.name), {})
            cells.append('crashed' if metrics.get('crashed') else _fmt(metrics.get(key), digits))
        rows.append([seq.name, _fmt(first.get('path_length_m'), 0)] + cells)
    return _table(header, rows)


def record_to_dict(record: RecordRun, settings: dict) -> dict:
    """Everything as JSON-ready data (NaN -> None)."""
    def clean(value):
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(v) for v in value]
        return value
    return clean({
        'settings': settings,
        'entries': [{'label': e.label, 'method': e.method, 'overrides': dict(e.overrides)}
                    for e in record.entries],
        'drives': [{'name': s.name, 'route': s.scenario, 'seed': s.seed, 'n_scans': s.n_scans}
                   for s in record.sequences],
        'summary': summarize_record(record),
        'runs': [record.metrics[k] for k in sorted(record.metrics)],
    })


def plot_error_over_distance(record: RecordRun, path: Path) -> Path:
    """ATE error against distance travelled, one panel per drive, one line per entry. Log
    scale: a lost method (tens of metres) and a good one (centimetres) share each panel."""
    from gft_odom.figures import pyplot
    plt = pyplot()
    n = len(record.sequences)
    cols = min(4, n)
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    colours = plt.rcParams['axes.prop_cycle'].by_key()['color']
    for i, seq in enumerate(record.sequences):
        ax = axes[i // cols][i % cols]
        for j, entry in enumerate(record.entries):
            curve = record.error_curves.get((entry.label, seq.name))
            if curve is None:
                continue
            ax.plot(curve[0], np.maximum(curve[1], ERROR_FLOOR_M), lw=1.0,
                    color=colours[j % len(colours)], label=entry.label)
        ax.set_title(seq.name, fontsize=9)
        ax.set_xlabel('distance travelled by the estimate [m]')
        ax.set_ylabel('position error [m]')
        ax.set_yscale('log')
        ax.grid(alpha=0.3, which='both')
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis('off')
    # Every entry drawn on any panel (one without results on the first drive too; none
    # at all when nothing was measured, as --cached-only may find).
    legend: dict[str, object] = {}
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    labels = list(legend)
    if labels:
        fig.legend(list(legend.values()), labels, loc='lower center',
                   ncol=min(len(labels), 5), fontsize=8)
    fig.tight_layout(rect=(0, 0.06 + 0.02 * (len(labels) > 5), 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_record(record: RecordRun, out_dir: Path, settings: dict, stem: str = 'record'
                 ) -> dict[str, Path]:
    """`<stem>.json`, `<stem>.md` and `<stem>_ate_over_distance.png` under `out_dir`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    document = record_to_dict(record, settings)
    json_path = out_dir / f'{stem}.json'
    write_text_atomic(json_path, json.dumps(document, indent=2, sort_keys=True) + '\n')
    png = plot_error_over_distance(record, out_dir / f'{stem}_ate_over_distance.png')
    md = '\n\n'.join([
        '## Summary (means over drives)', summary_markdown(document['summary']),
        SCORING_NOTE,
        '## ATE RMSE per drive [m]', per_drive_markdown(record),
        STAMP_NOTE,
        '## Stamp audit: the best shift of the stamps per drive [ms]',
        per_drive_markdown(record, 'stamp_best_shift_ms', 0),
        "## Mean position error per drive [m] (CitrusFarm's scoring)",
        per_drive_markdown(record, 'ate_mean_m'),
        '## End-point error per drive [m]', per_drive_markdown(record, 'end_error_m'),
        '## Drift over 100-800 m segments per drive [%]',
        per_drive_markdown(record, 'kitti_drift_pct', 2),
        '## Latency median per drive [ms]', per_drive_markdown(record, 'latency_median_ms', 1),
        f'![ATE over distance]({png.name})']) + '\n'
    md_path = out_dir / f'{stem}.md'
    write_text_atomic(md_path, md)
    return {'json': json_path, 'markdown': md_path, 'figure': png}
