"""The ament baseline style (99 columns, single quotes, sorted imports) and a docstring on every
public module, class and function of gft_odom/ (pydocstyle D1), checked by ruff (ruff.toml)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    ruff = shutil.which('ruff') or str(Path(sys.executable).with_name('ruff'))
    proc = subprocess.run([ruff, 'check', 'gft_odom', 'test', 'benchmarks', 'launch'],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
