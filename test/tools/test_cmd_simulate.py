"""`gft-odom simulate`: the progress bar goes to a terminal only, never into a log file."""

from __future__ import annotations

import fcntl
import os
import pty
import struct
import subprocess
import sys
import termios

import pytest

# Five coarse sweeps: a few seconds, enough for the bar to be drawn several times.
ARGS = ['simulate', '--scenario', 'row', '--scans', '5', '--azimuth-step-deg', '1.0',
        '--no-png']


def _simulate(out, stderr) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'gft_odom.tools.cli', *ARGS, '--out', str(out)],
                          stdout=subprocess.PIPE, stderr=stderr, text=True, timeout=300)


@pytest.mark.slow
def test_stderr_to_a_file_gets_log_lines_and_no_progress_bar(tmp_path):
    log = tmp_path / 'log.txt'
    with log.open('w') as err:
        proc = _simulate(tmp_path / 'sim', err)
    assert proc.returncode == 0
    assert '5 scans' in proc.stdout
    text = log.read_text()
    assert 'simulating 5 scans' in text  # the log lines still arrive
    # A tqdm bar is '\r'-separated updates like 'simulate row:  40%|####  | 2/5 [...]'.
    assert '\r' not in text and '%|' not in text and '/5 [' not in text, text


@pytest.mark.slow
def test_on_a_terminal_the_bar_is_drawn_unless_quiet(tmp_path):
    for quiet in (False, True):
        leader, follower = pty.openpty()
        # A terminal 100 columns wide (a fresh pty has 0, where tqdm draws nothing).
        fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack('HHHH', 24, 100, 0, 0))
        try:
            extra = ['--quiet'] if quiet else []
            proc = subprocess.Popen(
                [sys.executable, '-m', 'gft_odom.tools.cli', *ARGS, *extra,
                 '--out', str(tmp_path / f'sim{quiet}')],
                stdout=subprocess.DEVNULL, stderr=follower)
            os.close(follower)
            chunks = []
            while True:
                try:
                    chunk = os.read(leader, 4096)
                except OSError:  # the child closed the terminal
                    break
                if not chunk:
                    break
                chunks.append(chunk)
            assert proc.wait(timeout=300) == 0
        finally:
            os.close(leader)
        text = b''.join(chunks).decode(errors='replace')
        assert ('5/5' in text) is not quiet, text
        assert 'simulating 5 scans' in text  # log lines above the bar
