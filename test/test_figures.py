"""Figures read on their own: crop to the path, quantile scales with distinct labels, legends
that name the run, and a word when there is nothing to colour."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom import figures
from gft_odom.core.trajectory import Trajectory


@pytest.fixture
def closed_figures(monkeypatch):
    """Every figure the code closes, kept for inspection."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    kept, close = [], plt.close

    def keep(fig=None):
        kept.append(fig)
    monkeypatch.setattr(plt, 'close', keep)
    yield kept
    for fig in kept:
        close(fig)


def _colourbar_labels(fig) -> list[str]:
    bar_ax = fig.axes[-1]
    return [t.get_text() for t in bar_ax.get_yticklabels() if t.get_text()]


def _straight_path(n: int = 20, length_m: float = 5.0) -> Trajectory:
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = np.linspace(0.0, length_m, n)
    return Trajectory(np.arange(n, dtype=np.int64) * 100_000_000, poses)


def _clustered_nu(n: int, rng) -> np.ndarray:
    """Most nu within 0.05 .. 0.0502, as the `signal` frequency measures: `:.3f` repeats."""
    nu = 0.05 + 2e-4 * rng.random(n)
    nu[: n // 20] = rng.random(n // 20)
    return nu


def test_distinct_labels_add_digits_only_where_needed():
    assert figures.distinct_labels([0.0, 0.5, 1.0]) == ['0.00', '0.50', '1.00']
    labels = figures.distinct_labels([0.0, 0.05, 0.0501, 0.05012, 0.054])
    assert len(set(labels)) == 5 and labels[0] == '0.00000'


def test_map_is_cropped_to_the_path_and_coloured_by_quantiles(tmp_path, closed_figures):
    rng = np.random.default_rng(0)
    points = rng.uniform(-60.0, 60.0, size=(20_000, 3))
    nu = _clustered_nu(len(points), rng)
    figures.plot_map(tmp_path / 'map.png', points, nu, _straight_path())
    fig = closed_figures[-1]
    ax = fig.axes[0]
    lo, hi = figures.path_window(np.array([[0.0, 0.0], [5.0, 0.0]]))
    assert ax.get_xlim() == pytest.approx((lo[0], hi[0]))
    assert ax.get_ylim() == pytest.approx((lo[1], hi[1]))
    labels = _colourbar_labels(fig)
    assert len(labels) == 11 and len(set(labels)) == len(labels)
    assert (tmp_path / 'map.png').stat().st_size > 10_000


def test_map_without_spectrum_says_so(tmp_path, closed_figures):
    points = np.random.default_rng(1).normal(size=(500, 3))
    figures.plot_map(tmp_path / 'map.png', points, np.full(500, np.nan), _straight_path())
    texts = ' '.join(t.get_text() for t in closed_figures[-1].axes[0].texts)
    assert 'spectrum was not computed' in texts
    figures.plot_map(tmp_path / 'map2.png', points, None, None)
    assert 'not computed' in ' '.join(t.get_text() for t in closed_figures[-1].axes[0].texts)


@pytest.mark.parametrize('metrics, expected', [
    ({'registration_mode': 'paper', 'use_spectral_filter': True, 'n_bands': 4,
      'band_mask': [3, 4]}, 'paper ICP + GFT filter (B=4 [3, 4])'),
    ({'registration_mode': 'default', 'use_spectral_filter': False, 'n_bands': 4,
      'band_mask': [3, 4]}, 'default ICP, filter off'),
    ({'registration_mode': 'default', 'use_spectral_filter': True, 'n_bands': 3,
      'band_mask': [1, 2, 3]}, 'default ICP, all-pass mask (B=3)'),
    (None, 'estimate'),
])
def test_run_label_names_mode_and_mask(metrics, expected):
    assert figures.run_label(metrics) == expected


def test_trajectory_legend_names_the_run(tmp_path, closed_figures):
    traj = _straight_path()
    traj.poses[:, 1, 3] = np.sin(np.linspace(0.0, 3.0, len(traj)))  # alignment needs a bend
    metrics = {'registration_mode': 'paper', 'use_spectral_filter': False, 'n_bands': 10,
               'band_mask': [1], 'ate_rmse_m': 0.0}
    figures.plot_trajectory(tmp_path / 't.png', traj, traj, metrics)
    legend = [t.get_text() for t in closed_figures[-1].axes[0].get_legend().get_texts()]
    assert legend == ['ground truth', 'paper ICP, filter off']


def test_spectrum_colourbar_labels_are_distinct(tmp_path, closed_figures):
    from gft_odom.tools.cmd_spectrum import draw

    rng = np.random.default_rng(2)
    points = rng.uniform(-10.0, 10.0, size=(5_000, 3))
    nu = _clustered_nu(len(points), rng)
    nu[:100] = np.nan
    draw(points, nu, np.zeros((2, 3)), tmp_path / 's.png', 'test')
    labels = _colourbar_labels(closed_figures[-1])
    assert len(labels) == 11 and len(set(labels)) == 11, labels
    assert (tmp_path / 's.png').is_file()


def test_topdown_is_cropped_to_the_path_with_a_quantile_scale(tmp_path, closed_figures):
    from gft_odom.sim.writer import TOPDOWN_MARGIN_M, render_topdown

    rng = np.random.default_rng(3)
    points = rng.uniform(-60.0, 60.0, size=(50_000, 3))
    height = np.where(rng.random(len(points)) < 0.8, 0.01 * rng.normal(size=len(points)),
                      rng.uniform(0.5, 4.0, size=len(points)))
    path = np.zeros((10, 3))
    path[:, 0] = np.linspace(0.0, 8.0, 10)
    render_topdown(tmp_path / 'top.png', points, height, path)
    fig = closed_figures[-1]
    x0, x1 = fig.axes[0].get_xlim()
    assert x0 >= -TOPDOWN_MARGIN_M - 1.0 and x1 <= 8.0 + TOPDOWN_MARGIN_M + 1.0
    labels = _colourbar_labels(fig)
    assert len(labels) >= 10 and len(set(labels)) == len(labels)
    assert (tmp_path / 'top.png').stat().st_size > 10_000
