"""TUM trajectory files: `t x y z qx qy qz qw` per line, `#` comments, t in seconds.

Stamps go through their decimal text both ways, so nanosecond stamps survive a round trip
exactly (a float64 second holds only ~0.2 us at 1.7e9 s). Writing is atomic: a crash leaves
the old file or the new one, never half of one.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from gft_odom.core.geometry import xyz_quat_from_poses
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import GroundTruthError
from gft_odom.io._poses import ns_to_seconds_text, seconds_text_to_ns, trajectory_from_columns
from gft_odom.io.atomic import write_text_atomic

log = logging.getLogger(__name__)

TUM_COLUMNS = 8


def read_text_lines(path: str | Path) -> list[tuple[int, str]]:
    """(1-based line number, stripped text) of the non-empty, non-comment lines."""
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError as exc:
        raise GroundTruthError(f'trajectory file {path} does not exist') from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise GroundTruthError(f'cannot read trajectory file {path}: {exc}') from exc
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith('#'):
            rows.append((number, line))
    if not rows:
        raise GroundTruthError(f'trajectory file {path} holds no poses')
    return rows


def read_tum(path: str | Path) -> Trajectory:
    """A TUM file as a Trajectory; a bad row raises GroundTruthError naming its line."""
    path = Path(path)
    rows = read_text_lines(path)
    stamps_ns = np.empty(len(rows), dtype=np.int64)
    values = np.empty((len(rows), TUM_COLUMNS - 1))
    lines = np.array([number for number, _ in rows])
    for i, (number, line) in enumerate(rows):
        tokens = line.replace(',', ' ').split()
        if len(tokens) != TUM_COLUMNS:
            raise GroundTruthError(f'{path} line {number}: expected {TUM_COLUMNS} values '
                                   f'(t x y z qx qy qz qw), got {len(tokens)}')
        try:
            stamps_ns[i] = seconds_text_to_ns(tokens[0])
            values[i] = [float(t) for t in tokens[1:]]
        except (ValueError, OverflowError) as exc:
            raise GroundTruthError(f'{path} line {number}: {exc}') from exc
    if not np.isfinite(values).all():
        bad = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
        raise GroundTruthError(f'{path} line {lines[bad]}: non-finite value')
    return trajectory_from_columns(stamps_ns, values[:, :3], values[:, 3:], str(path),
                                   line_numbers=lines)


def format_tum(traj: Trajectory) -> str:
    """The TUM text of a trajectory (9-decimal exact stamps)."""
    xyz, quat = xyz_quat_from_poses(traj.poses)
    lines = [f'{ns_to_seconds_text(t)} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} '
             f'{q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f}'
             for t, p, q in zip(traj.stamps_ns.tolist(), xyz, quat)]
    return ''.join(line + '\n' for line in lines)


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write a trajectory as a TUM file (readable by `evo_ape tum`), atomically."""
    try:
        write_text_atomic(path, '# t x y z qx qy qz qw\n' + format_tum(traj))
    except OSError as exc:
        raise GroundTruthError(f'cannot write {path}: {exc}') from exc
    log.debug('wrote %d poses to %s', len(traj), path)
