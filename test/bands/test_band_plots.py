"""The band-search figures render on small inputs and say what their axes are."""

from __future__ import annotations

import numpy as np

from gft_odom.bands.plots import plot_band_correlation, plot_interval_counts


def test_fig7_has_an_x_label(tmp_path, closed_figures):
    table = {2: np.array([0.9, -0.5]), 3: np.array([0.8, np.nan, -0.2])}
    plot_band_correlation(tmp_path / 'fig7.png', table, 'test')
    fig = closed_figures[-1]
    assert 'band' in fig.get_supxlabel()
    assert [ax.get_title() for ax in fig.axes] == ['B = 2', 'B = 3']
    assert (tmp_path / 'fig7.png').stat().st_size > 5_000


def test_fig8_renders(tmp_path, closed_figures):
    plot_interval_counts(tmp_path / 'fig8.png', np.arange(1000) % 7, 20, 'test')
    assert 'nu' in closed_figures[-1].axes[0].get_xlabel()
