"""Benchmark figures on a hand-made run: a diverging method must not take over the view, the
best run is on top, ATE bars carry their spread over seeds, latency ticks are plain ms."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gft_odom.bench.report import plot_figures
from gft_odom.bench.runner import BenchRun, BenchSequence, MethodRun
from gft_odom.config import GftOdomConfig
from gft_odom.core.trajectory import Trajectory
from gft_odom.replay import ReplayResult


def _trajectory(xy: np.ndarray) -> Trajectory:
    poses = np.repeat(np.eye(4)[None], len(xy), axis=0)
    poses[:, :2, 3] = xy
    return Trajectory(np.arange(len(xy), dtype=np.int64) * 100_000_000, poses)


def _bench() -> tuple[BenchRun, dict]:
    t = np.linspace(0.0, np.pi, 40)
    gt_xy = np.stack([10.0 * np.sin(t), 4.0 * (1.0 - np.cos(t))], axis=1)  # a U-turn
    config = GftOdomConfig()
    sequences, runs = [], []
    errors = {'good': 0.05, 'fair': 0.5, 'diverges': 40.0}
    for seed in (1, 2):
        seq = BenchSequence('uturn', seed, 40, Path('bag'), Path('gt'))
        sequences.append(seq)
        for k, (method, error) in enumerate(errors.items()):
            # The diverging run walks off along a spiral; the others wobble about the truth.
            drift = error * np.stack([np.cos(3 * t + k), np.sin(5 * t + seed)], axis=1)
            if method == 'diverges':
                drift = error * np.stack([t, t ** 2], axis=1)
            traj = _trajectory(gt_xy + drift)
            replay = ReplayResult(
                sensor_trajectory=traj, base_trajectory=traj,
                latency_s=np.full(40, 0.004 * (k + 1) * seed), stage_s={},
                points_in=np.full(40, 100), points_kept=np.full(40, 100), statuses=['ok'] * 40,
                metrics={'ate_rmse_m': error * seed}, ground_truth=_trajectory(gt_xy))
            runs.append(MethodRun(method, seq, replay, config))
    ev = config.evaluation
    document = {'summary': {m: {} for m in errors},
                'settings': {'evaluation_config': {'mode': ev.mode, 'max_diff_s': ev.max_diff_s,
                                                   'match': ev.match,
                                                   'max_gap_s': ev.max_gap_s}}}
    return BenchRun(sequences, runs), document


def test_bench_figures_read_on_their_own(tmp_path, closed_figures):
    bench, document = _bench()
    paths = plot_figures(bench, document, tmp_path)
    assert all(p.stat().st_size > 5_000 for p in paths.values())
    ate_fig, latency_fig, traj_fig = closed_figures[-3:]

    ax = ate_fig.axes[0]
    assert len(ax.containers) >= 3 and any(
        getattr(c, 'errorbar', None) is not None and c.errorbar is not None
        for c in ax.containers)
    legend_box = ax.get_legend().get_window_extent(ate_fig.canvas.get_renderer())
    assert legend_box.x0 >= ax.get_window_extent().x1  # off the bars

    labels = [t.get_text() for t in latency_fig.axes[0].get_yticklabels() if t.get_text()]
    assert labels and all('$' not in s and '^' not in s for s in labels)
    assert {'10', '50', '100'} <= set(labels)

    ax = traj_fig.axes[0]
    x0, x1 = ax.get_xlim()
    assert -5.0 < x0 and x1 < 15.0  # the ground truth (0..10 m) plus a margin, not 60 m
    lines = [ln for ln in ax.get_lines()
             if not ln.get_label().startswith(('_', 'ground truth'))]
    top = max(lines, key=lambda ln: ln.get_zorder())
    assert top.get_label().startswith('good')
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(s.startswith('diverges') and 'leaves the view' in s for s in legend)
    assert not any(s.startswith('good') and 'leaves' in s for s in legend)
