"""The `gft-odom` command: every sub-command is there, errors become one line and exit 1."""

from __future__ import annotations

import subprocess
import sys

import pytest

from gft_odom.tools.cli import build_parser, main

COMMANDS = {'simulate', 'spectrum', 'replay', 'demo', 'config', 'search-bands', 'bench'}


def test_every_sub_command_is_registered():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == 'command')
    assert COMMANDS <= set(sub.choices)


def test_package_error_is_one_line_and_exit_code_1(caplog):
    assert main(['config', '--set', 'spectral.tau_m=-1.0']) == 1
    errors = [r for r in caplog.records if r.levelname == 'ERROR']
    assert len(errors) == 1
    assert 'tau_m' in errors[0].getMessage() and '\n' not in errors[0].getMessage()


@pytest.mark.slow
def test_console_script_runs(tmp_path):
    out = tmp_path / 'p.yaml'
    proc = subprocess.run([sys.executable, '-m', 'gft_odom.tools.cli', 'config', '--set',
                           'spectral.band_mask=[1, 9, 10]', '--out', str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert 'band_mask: [1, 9, 10]' in out.read_text()
