"""TUM files: exact nanosecond round trip, comments, bad rows, atomic writes."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from gft_odom.core.geometry import poses_from_xyz_quat
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import GroundTruthError
from gft_odom.io.tum import read_tum, write_tum


def random_trajectory(seed: int, stamps_ns: np.ndarray) -> Trajectory:
    rng = np.random.default_rng(seed)
    n = stamps_ns.shape[0]
    quat = Rotation.random(n, random_state=seed).as_quat().reshape(-1, 4)
    return Trajectory(stamps_ns, poses_from_xyz_quat(rng.normal(0, 100, (n, 3)), quat))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(-2**62, 2**62), min_size=1, max_size=30, unique=True),
       st.integers(0, 2**31))
def test_round_trip_is_exact_in_ns(tmp_path_factory, stamps, seed):
    stamps_ns = np.sort(np.asarray(stamps, dtype=np.int64))
    traj = random_trajectory(seed, stamps_ns)
    path = tmp_path_factory.mktemp('tum') / 'traj.txt'
    write_tum(path, traj)
    back = read_tum(path)
    np.testing.assert_array_equal(back.stamps_ns, stamps_ns)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-9)


def test_stamps_that_floats_would_round(tmp_path):
    """1.7e9 s with ns digits: float64 seconds would lose the last digits."""
    stamps_ns = np.array([1_700_000_000_123_456_789, 1_700_000_000_123_456_790], np.int64)
    assert float(stamps_ns[0]) * 1e-9 == float(stamps_ns[1]) * 1e-9  # what we avoid
    path = tmp_path / 'traj.tum'
    write_tum(path, random_trajectory(0, stamps_ns))
    assert path.read_text().splitlines()[1].startswith('1700000000.123456789 ')
    np.testing.assert_array_equal(read_tum(path).stamps_ns, stamps_ns)


def test_reads_comments_blank_lines_and_other_precisions(tmp_path):
    path = tmp_path / 'evo.txt'
    path.write_text('# timestamp tx ty tz qx qy qz qw\n\n'
                    '1.5 1 2 3 0 0 0 1\n'
                    '  # a comment in the middle\n'
                    '2 4 5 6 0 0 0.7071067811865476 0.7071067811865476\n'
                    '2.0000000005 7 8 9 0 0 0 1\n'
                    '3e0 1 1 1 0 0 0 1\n')
    traj = read_tum(path)
    assert traj.stamps_ns.tolist() == [1_500_000_000, 2_000_000_000, 2_000_000_000,
                                       3_000_000_000]  # 0.5 ns rounds half to even
    np.testing.assert_allclose(traj.poses[1, :3, :3], Rotation.from_euler(
        'z', 90, degrees=True).as_matrix(), atol=1e-12)


@pytest.mark.parametrize('text, reason', [
    ('', 'holds no poses'),
    ('# only a comment\n', 'holds no poses'),
    ('1 2 3 4 0 0 0 1\n2 2 3 4 0 0 1\n', 'line 2: expected 8 values'),
    ('1 2 3 4 0 0 0 1\nabc 2 3 4 0 0 0 1\n', 'line 2'),
    ('1 2 3 4 0 0 0 1\n# c\n2 2 nan 4 0 0 0 1\n', 'line 3: non-finite'),
    ('inf 2 3 4 0 0 0 1\n', 'line 1'),
])
def test_bad_files_raise_with_the_line(refuses_file, text, reason):
    refuses_file(read_tum, text, GroundTruthError, reason)


def test_missing_file(tmp_path):
    with pytest.raises(GroundTruthError, match='does not exist'):
        read_tum(tmp_path / 'none.txt')


def test_write_is_atomic_and_replaces(tmp_path):
    path = tmp_path / 'out' / 'traj.txt'
    write_tum(path, random_trajectory(1, np.arange(5) * 10**8))
    write_tum(path, random_trajectory(2, np.arange(3) * 10**8))
    assert len(read_tum(path)) == 3
    assert os.listdir(path.parent) == ['traj.txt']  # no temp file left behind


def test_failed_write_leaves_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / 'traj.txt'
    write_tum(path, random_trajectory(1, np.arange(4) * 10**8))
    before = path.read_text()

    def broken_replace(src, dst):
        raise OSError('disk full')
    monkeypatch.setattr(os, 'replace', broken_replace)
    with pytest.raises(GroundTruthError, match='disk full'):
        write_tum(path, random_trajectory(2, np.arange(9) * 10**8))
    assert path.read_text() == before
    assert os.listdir(tmp_path) == ['traj.txt']


def test_evo_reads_what_we_write(tmp_path):
    from evo.tools import file_interface  # a test dependency: missing evo fails, not skips
    stamps_ns = np.array([1_700_000_000_000_000_000, 1_700_000_000_100_000_000], np.int64)
    traj = random_trajectory(3, stamps_ns)
    path = tmp_path / 'traj.txt'
    write_tum(path, traj)
    theirs = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(theirs.timestamps, stamps_ns * 1e-9)
    np.testing.assert_allclose(np.stack(theirs.poses_se3), traj.poses, atol=1e-9)
