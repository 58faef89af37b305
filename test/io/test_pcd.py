"""PCD files: what we write, Open3D (the reader PCL and CloudCompare users share) reads."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.io.pcd import (
    FREQUENCY_CLOUD_DTYPE,
    PcdError,
    frequency_cloud,
    pcd_header,
    read_pcd,
    write_pcd,
)


def _cloud(n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    nu = rng.random(n).astype(np.float32)
    band = np.minimum((nu * 4).astype(np.uint8) + 1, 4)
    nu[:7], band[:7] = np.nan, 0  # no spectrum
    return frequency_cloud(rng.normal(scale=10.0, size=(n, 3)), rng.random(n) * 100.0, nu, band)


def test_header_names_the_map_layout():
    header = pcd_header(FREQUENCY_CLOUD_DTYPE, 3)
    assert 'FIELDS x y z intensity frequency band\n' in header
    assert 'SIZE 4 4 4 4 4 1\n' in header
    assert 'TYPE F F F F F U\n' in header
    assert 'COUNT 1 1 1 1 1 1\n' in header
    assert 'WIDTH 3\nHEIGHT 1\n' in header and 'POINTS 3\n' in header
    assert header.endswith('DATA binary\n')


def test_binary_body_is_packed_records(tmp_path):
    cloud = _cloud(10)
    write_pcd(tmp_path / 'a.pcd', cloud)
    raw = (tmp_path / 'a.pcd').read_bytes()
    assert len(raw) == len(pcd_header(cloud.dtype, 10)) + 10 * 21
    assert not list(tmp_path.glob('.*.tmp'))


def test_round_trip_through_our_reader(tmp_path):
    cloud = _cloud()
    write_pcd(tmp_path / 'a.pcd', cloud)
    back = read_pcd(tmp_path / 'a.pcd')
    assert back.dtype.names == cloud.dtype.names
    for name in cloud.dtype.names:
        np.testing.assert_array_equal(back[name], cloud[name])


def test_open3d_reads_every_field(tmp_path):
    import open3d as o3d  # a package dependency: missing open3d fails, not skips
    cloud = _cloud()
    write_pcd(tmp_path / 'a.pcd', cloud)
    pc = o3d.t.io.read_point_cloud(str(tmp_path / 'a.pcd'))
    xyz = np.stack([cloud['x'], cloud['y'], cloud['z']], axis=1)
    np.testing.assert_array_equal(pc.point['positions'].numpy(), xyz)
    for name in ('intensity', 'frequency', 'band'):
        got = pc.point[name].numpy()[:, 0]
        assert got.dtype == cloud[name].dtype
        np.testing.assert_array_equal(got, cloud[name])


def test_ascii_pcd_is_read(tmp_path):
    path = tmp_path / 'a.pcd'
    path.write_text(pcd_header(np.dtype([('x', '<f4'), ('band', 'u1')]), 2, 'ascii')
                    + '1.5 3\n-2 0\n')
    back = read_pcd(path)
    np.testing.assert_array_equal(back['x'], [1.5, -2.0])
    np.testing.assert_array_equal(back['band'], [3, 0])


def test_bad_files_raise_pcd_error(tmp_path):
    cloud = _cloud(10)
    write_pcd(tmp_path / 'a.pcd', cloud)
    raw = (tmp_path / 'a.pcd').read_bytes()
    (tmp_path / 'cut.pcd').write_bytes(raw[:-5])
    with pytest.raises(PcdError, match='truncated'):
        read_pcd(tmp_path / 'cut.pcd')
    with pytest.raises(PcdError, match='cannot read'):
        read_pcd(tmp_path / 'missing.pcd')
    with pytest.raises(PcdError, match='frequencies'):
        frequency_cloud(np.zeros((3, 3)), None, np.zeros(2), np.zeros(3, np.uint8))
    with pytest.raises(PcdError, match='uint8'):
        frequency_cloud(np.zeros((1, 3)), None, np.zeros(1), np.array([300]))
    with pytest.raises(PcdError, match='scalar'):
        pcd_header(np.dtype([('v', '<f4', (3,))]), 1)
