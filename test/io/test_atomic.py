"""One atomic writer: whole files or none, modes from the user's umask, no temp file left."""

from __future__ import annotations

import os
import stat

import pytest

from gft_odom.io.atomic import make_temp_dir, write_atomic, write_text_atomic


@pytest.fixture
def umask():
    """Set the process umask for one test, then restore it."""
    previous = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(previous)


def _mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize('mask, file_mode, dir_mode', [
    (0o022, 0o644, 0o755), (0o002, 0o664, 0o775), (0o077, 0o600, 0o700)])
def test_modes_follow_the_umask(umask, tmp_path, mask, file_mode, dir_mode):
    umask(mask)
    path = write_text_atomic(tmp_path / 'sub' / 'a.txt', 'hello\n')
    assert path.read_text() == 'hello\n'
    assert _mode(path) == file_mode
    folder = make_temp_dir(tmp_path, prefix='run.partial-')
    assert folder.name.startswith('run.partial-') and folder.is_dir()
    assert _mode(folder) == dir_mode


def test_replaces_whole_and_leaves_no_temp_file(tmp_path):
    path = tmp_path / 'a.bin'
    path.write_bytes(b'old')
    write_atomic(path, lambda f: f.write(b'new'))
    assert path.read_bytes() == b'new'
    assert list(tmp_path.iterdir()) == [path]


def test_a_failing_writer_keeps_the_old_file(tmp_path):
    path = tmp_path / 'a.txt'
    path.write_text('old')

    def half_then_fail(f):
        f.write(b'half')
        raise OSError(28, 'No space left on device')

    with pytest.raises(OSError, match='No space'):
        write_atomic(path, half_then_fail)
    assert path.read_text() == 'old'
    assert list(tmp_path.iterdir()) == [path]
