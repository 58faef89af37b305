"""benchmarks/run_all.py: finds every benchmark script and the odometry bench; --args parsing."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import load_script

RUN_ALL = Path(__file__).resolve().parents[2] / 'benchmarks' / 'run_all.py'


@pytest.fixture(scope='module')
def run_all():
    return load_script(RUN_ALL)


def test_discovers_every_bench_script_and_the_odometry_bench(run_all):
    jobs = run_all.discover_jobs()
    scripts = {p.stem for p in RUN_ALL.parent.glob('bench_*.py')}
    assert set(jobs) == scripts | {'odometry'}
    assert jobs['odometry'][-2:] == ['bench', '--quiet']


def test_job_args_are_split_like_a_shell(run_all):
    assert run_all.parse_job_args(['odometry=--scans 60 --seeds 1 2']) == {
        'odometry': ['--scans', '60', '--seeds', '1', '2']}
    with pytest.raises(SystemExit):
        run_all.parse_job_args(['odometry'])


def test_dry_run_refuses_unknown_jobs(run_all, capsys):
    assert run_all.main(['--dry-run', '--only', 'odometry']) == 0
    assert 'gft_odom.tools.cli bench' in capsys.readouterr().out
    with pytest.raises(SystemExit):
        run_all.main(['--dry-run', '--only', 'no_such_bench'])
