"""Run every benchmark in benchmarks/ (and `gft-odom bench`), then collect their JSON results.

Usage:
  .venv/bin/python benchmarks/run_all.py [--only NAME ...] [--skip NAME ...]
      [--args NAME="--scans 60 ..."] [--dry-run]

NAME is a script's stem (`bench_spectral`, `bench_anchors`, `bench_sim`, ...) or `odometry`
for `gft-odom bench`. Each job runs in its own process, one after the other (the machine is
shared: never in parallel), with its own arguments or its defaults. Afterwards every
benchmarks/results/*.json is listed in benchmarks/results/index.json and index.md with the job
that ran, its exit code and wall time, so one file says what was measured when.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / 'results'
ODOMETRY_JOB = 'odometry'


def discover_jobs() -> dict[str, list[str]]:
    """Job name -> command line; every benchmarks/bench_*.py plus the odometry bench."""
    jobs = {p.stem: [sys.executable, str(p)] for p in sorted(HERE.glob('bench_*.py'))}
    jobs[ODOMETRY_JOB] = [sys.executable, '-m', 'gft_odom.tools.cli', 'bench', '--quiet']
    return jobs


def parse_job_args(items: list[str]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for item in items:
        name, sep, text = item.partition('=')
        if not sep:
            raise SystemExit(f'--args expects NAME="ARGS", got {item!r}')
        out[name.strip()] = shlex.split(text)
    return out


def collect_results(runs: list[dict]) -> dict:
    """Every results JSON: file, modification time, size, top-level keys."""
    files = []
    for path in sorted(RESULTS.glob('*.json')):
        if path.name == 'index.json':
            continue
        entry = {'file': path.name, 'bytes': path.stat().st_size,
                 'modified_utc': datetime.fromtimestamp(path.stat().st_mtime, timezone.utc)
                 .isoformat(timespec='seconds')}
        try:
            data = json.loads(path.read_text())
            entry['keys'] = sorted(data) if isinstance(data, dict) else [f'list[{len(data)}]']
        except (OSError, ValueError) as exc:
            entry['error'] = f'unreadable: {exc}'
        files.append(entry)
    return {'generated_utc': datetime.now(timezone.utc).isoformat(timespec='seconds'),
            'runs': runs, 'results': files}


def write_index(index: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / 'index.json').write_text(json.dumps(index, indent=2) + '\n')
    lines = ['# Benchmark results index', '', f'Generated {index["generated_utc"]} by '
             '`benchmarks/run_all.py`.', '', '| job | exit | wall s | command |',
             '|---|---:|---:|---|']
    for run in index['runs']:
        lines.append(f'| {run["job"]} | {run["exit_code"]} | {run["wall_s"]:.0f} | '
                     f'`{run["command"]}` |')
    lines += ['', '| results file | modified (UTC) | top-level keys |', '|---|---|---|']
    for f in index['results']:
        lines.append(f'| {f["file"]} | {f["modified_utc"]} | '
                     f'{", ".join(f.get("keys", [])) or f.get("error", "")} |')
    (RESULTS / 'index.md').write_text('\n'.join(lines) + '\n')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--only', nargs='+', metavar='NAME', help='run only these jobs')
    parser.add_argument('--skip', nargs='+', default=[], metavar='NAME', help='skip these jobs')
    parser.add_argument('--args', action='append', default=[], metavar='NAME="ARGS"',
                        help='extra arguments of one job, e.g. odometry="--scans 60"')
    parser.add_argument('--dry-run', action='store_true', help='print the commands only')
    args = parser.parse_args(argv)
    jobs = discover_jobs()
    extra = parse_job_args(args.args)
    unknown = (set(args.only or []) | set(args.skip) | set(extra)) - set(jobs)
    if unknown:
        parser.error(f'unknown job(s) {sorted(unknown)}; known: {sorted(jobs)}')
    selected = [name for name in jobs if (not args.only or name in args.only)
                and name not in args.skip]
    runs = []
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (str(REPO), os.environ.get('PYTHONPATH', '')) if p))
    for name in selected:
        command = jobs[name] + extra.get(name, [])
        printable = ' '.join(shlex.quote(c) for c in command)
        print(f'== {name}: {printable}', flush=True)
        if args.dry_run:
            continue
        t0 = time.perf_counter()
        code = subprocess.call(command, cwd=REPO, env=env)
        wall_s = time.perf_counter() - t0
        print(f'== {name}: exit {code} after {wall_s:.0f} s', flush=True)
        runs.append({'job': name, 'command': printable, 'exit_code': code, 'wall_s': wall_s})
    if args.dry_run:
        return 0
    write_index(collect_results(runs))
    print(f'wrote {RESULTS / "index.json"} and {RESULTS / "index.md"}')
    return 0 if all(r['exit_code'] == 0 for r in runs) else 1


if __name__ == '__main__':
    sys.exit(main())
