"""`gft-odom frequencies` end to end: a simulated bag in, one PCD per scan out."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gft_odom.tools.cli import main

MAX_RANGE_M = 20.0  # crops part of every sweep, so the test sees the pipeline's crop


@pytest.fixture(scope='module')
def sim_run(tmp_path_factory):
    from gft_odom.sim import SimConfig, simulate_to_bag

    out = tmp_path_factory.mktemp('sim')
    config = dataclasses.replace(SimConfig(), azimuth_step_deg=1.0)
    return simulate_to_bag(out, 'row', 3, 5, config, topdown_png=False)


def _expected(bag_path, n_bands: int):
    """Per scan: stamp, the cropped scan and its frequencies, computed here independently."""
    from gft_odom.core.spectral import SpectralFilter
    from gft_odom.io.bags import ScanBagReader
    from gft_odom.params_file import load_config

    config = load_config(None, [f'spectral.n_bands={n_bands}',
                                f'spectral.band_mask={list(range(1, n_bands + 1))}'])
    spectral_filter = SpectralFilter.from_config(config.spectral)
    out = []
    with ScanBagReader([bag_path]) as reader:
        for scan in reader:
            r = np.linalg.norm(scan.points_xyz, axis=1)
            cropped = scan.select((r >= config.pipeline.min_range_m) & (r <= MAX_RANGE_M))
            out.append((scan.stamp_ns, cropped,
                        spectral_filter.frequencies(cropped.points_xyz, n_bands,
                                                    ring=cropped.ring)))
    return out


@pytest.mark.slow
def test_one_pcd_per_scan_that_open3d_reads(sim_run, tmp_path, capsys):
    import open3d as o3d  # a package dependency: missing open3d fails, not skips
    out = tmp_path / 'pcd'
    # A mask for 10 bands and n_bands 4: the mask plays no part and must not be refused.
    rc = main(['frequencies', str(sim_run.bag_path), '--out', str(out), '--quiet',
               '--set', 'spectral.n_bands=4', '--set', f'pipeline.max_range_m={MAX_RANGE_M}'])
    assert rc == 0
    assert 'wrote 3 PCD files' in capsys.readouterr().out
    expected = _expected(sim_run.bag_path, 4)
    assert sorted(p.name for p in out.iterdir()) == sorted(f'{s}.pcd' for s, _, _ in expected)
    for stamp_ns, scan, freqs in expected:
        pc = o3d.t.io.read_point_cloud(str(out / f'{stamp_ns}.pcd'))
        xyz = pc.point['positions'].numpy()
        assert xyz.shape[0] == len(scan) > 0
        assert np.linalg.norm(xyz, axis=1).max() <= MAX_RANGE_M + 1e-3
        np.testing.assert_allclose(xyz, scan.points_xyz, atol=1e-5)
        np.testing.assert_array_equal(pc.point['intensity'].numpy()[:, 0], scan.intensity)
        band = pc.point['band'].numpy()[:, 0]
        nu = pc.point['frequency'].numpy()[:, 0]
        assert band.dtype == np.uint8 and band.max() <= 4
        np.testing.assert_array_equal(band, freqs.band)
        np.testing.assert_allclose(nu, freqs.nu, rtol=1e-6, equal_nan=True)
        assert np.isnan(nu[band == 0]).all() and np.isfinite(nu[band > 0]).all()
        assert len(np.unique(band[band > 0])) > 1


@pytest.mark.slow
def test_pcd_folder_draws_figure_3(sim_run, tmp_path):
    out = tmp_path / 'pcd'
    assert main(['frequencies', str(sim_run.bag_path), '--out', str(out), '--quiet']) == 0
    png = tmp_path / 'fig3.png'
    assert main(['spectrum', '--pcd', str(out), '--gt', str(sim_run.gt_tum_path),
                 '--out', str(png)]) == 0
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


@pytest.mark.slow
def test_bad_input_is_one_line_and_exit_code_1(sim_run, tmp_path, caplog):
    cases = [
        ([str(tmp_path / 'missing_bag'), '--out', str(tmp_path / 'a')], 'does not exist'),
        ([str(sim_run.bag_path), '--out', str(tmp_path / 'b'), '--topic', '/nope'], '/nope'),
        ([str(sim_run.bag_path), '--out', str(tmp_path / 'c'), '--set', 'spectral.n_bands=0'],
         'n_bands'),
        ([str(sim_run.bag_path), '--out', str(tmp_path / 'd'), '--set', 'spectral.n_bands=300'],
         'uint8'),
    ]
    for args, word in cases:
        caplog.clear()
        assert main(['frequencies', '--quiet', *args]) == 1
        errors = [r.getMessage() for r in caplog.records if r.levelname == 'ERROR']
        assert len(errors) == 1 and '\n' not in errors[0] and word in errors[0], errors
    assert not any((tmp_path / d).exists() for d in 'abcd')
    assert main(['spectrum', '--gt', str(sim_run.gt_tum_path), '--out',
                 str(tmp_path / 'x.png')]) == 1
