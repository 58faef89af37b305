"""Ground truth from whatever form a dataset ships it in, and the LiDAR -> GPS extrinsic.

CitrusFarm gives the RTK-GPS antenna track twice: `/gps/fix/odometry` in `gt.bag` and the
same in `gt.csv`. A TUM file (ours, evo's) holds sensor poses. `read_ground_truth` picks the
reader from the path; all of them return a time-sorted `Trajectory` or raise GroundTruthError.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gft_odom.core.constants import NS_PER_S
from gft_odom.core.geometry import make_transform
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import BagError, ConfigError, GroundTruthError
from gft_odom.io._poses import decimal_of, trajectory_from_columns
from gft_odom.io.tum import read_text_lines, read_tum

log = logging.getLogger(__name__)

# Stamps above this are nanoseconds (1e12 s would be year 33658; 1e12 ns is 16 minutes).
NS_STAMP_THRESHOLD = 1e12

_TIME_NAMES = ('field.header.stamp', 'header.stamp', 'timestamp', 'time', 'stamp', 't',
               '%time', '#timestamp', '#time', 'time_s', 'timestamp_s', 'timestamp_ns')
_AXIS_SUFFIXES = {
    'x': ('position.x', 'pos_x', 'tx', 'p_x', 'x'), 'y': ('position.y', 'pos_y', 'ty', 'p_y', 'y'),
    'z': ('position.z', 'pos_z', 'tz', 'p_z', 'z'),
    'qx': ('orientation.x', 'qx', 'q_x'), 'qy': ('orientation.y', 'qy', 'q_y'),
    'qz': ('orientation.z', 'qz', 'q_z'), 'qw': ('orientation.w', 'qw', 'q_w'),
}


@dataclass(frozen=True)
class GroundTruthConfig:
    """Where the GPS antenna sits in the LiDAR frame (CitrusFarm calibration, no rotation).

    The ground truth tracks the antenna, the odometry the LiDAR: comparing them needs this
    lever arm, or every turn shows up as error.
    """

    lidar_to_gps_xyz_m: tuple[float, float, float] = (-0.22, 0.0, 0.153)

    def validate(self) -> None:
        """Raise ConfigError unless the LiDAR -> GPS offset is 3 finite numbers."""
        xyz = self.lidar_to_gps_xyz_m
        if not isinstance(xyz, (tuple, list)) or len(xyz) != 3:
            raise ConfigError(f'ground_truth.lidar_to_gps_xyz_m needs 3 values, got {xyz!r}')
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in xyz):
            raise ConfigError(f'ground_truth.lidar_to_gps_xyz_m must be finite numbers, got '
                              f'{xyz!r}')
        if max(abs(v) for v in xyz) > 100.0:
            raise ConfigError(f'ground_truth.lidar_to_gps_xyz_m = {xyz!r} is over 100 m from '
                              'the LiDAR; give metres')

    def T_lidar_gps(self) -> np.ndarray:
        """Pose of the GPS antenna in the LiDAR frame (4x4)."""
        return make_transform(translation=np.asarray(self.lidar_to_gps_xyz_m, dtype=float))


def read_ground_truth(path: str | Path, topic: str = '/gps/fix/odometry') -> Trajectory:
    """A ground-truth trajectory from a bag (`topic`), a CitrusFarm-style CSV or a TUM file."""
    path = Path(path)
    if not path.exists():
        raise GroundTruthError(f'ground truth {path} does not exist')
    suffix = path.suffix.lower()
    if suffix in ('.bag', '.db3', '.mcap') or path.is_dir():
        from gft_odom.io.bags import read_odometry
        try:
            traj = read_odometry([path], topic=topic)
        except BagError as exc:
            raise GroundTruthError(f'ground truth bag {path}: {exc}') from exc
    elif suffix == '.csv':
        traj = read_ground_truth_csv(path)
    elif suffix in ('.txt', '.tum'):
        traj = read_tum(path)
    else:
        raise GroundTruthError(f'ground truth {path}: unknown format {suffix!r} (expected a '
                               '.bag or rosbag2 folder, .csv, .txt or .tum)')
    if len(traj) == 0:
        raise GroundTruthError(f'ground truth {path} holds no poses'
                               + (f' on {topic}' if suffix not in ('.csv', '.txt', '.tum')
                                  else ''))
    return traj


def _split(line: str) -> list[str]:
    return [t for t in re.split(r'[,\s;]+', line.strip()) if t]


def _column_map(header: list[str]) -> dict[str, int] | None:
    """Column index of time, x, y, z (and the quaternion when named) from a header line."""
    names = [h.strip().strip('"\'').lower() for h in header]
    found: dict[str, int] = {}
    for wanted in _TIME_NAMES:
        if wanted in names:
            found['t'] = names.index(wanted)
            break
    for key, suffixes in _AXIS_SUFFIXES.items():
        # Most specific name first: `pose.position.x` must win over `twist.linear.x`.
        for suffix in suffixes:
            hits = [i for i, name in enumerate(names)
                    if name == suffix or name.endswith('.' + suffix)]
            if hits:
                found[key] = hits[0]
                break
    if not all(k in found for k in ('t', 'x', 'y', 'z')):
        return None
    return found


def read_ground_truth_csv(path: str | Path) -> Trajectory:
    """CitrusFarm-style `gt.csv`: time x y z [qx qy qz qw], comma or space separated.

    An optional header line names the columns (matched by name, `rostopic echo -p` names
    included); without one the order above is assumed. Time is seconds, or nanoseconds when
    the values exceed 1e12; a missing quaternion means identity orientation.
    """
    path = Path(path)
    rows = read_text_lines(path)
    first = _split(rows[0][1])
    columns: dict[str, int] | None = None
    try:
        decimal_of(first[0])
        header = False
    except ValueError:
        header = True
    if header:
        columns = _column_map(first)
        if columns is None:
            raise GroundTruthError(f'{path} line {rows[0][0]}: header {first} does not name '
                                   'time, x, y and z columns')
        rows = rows[1:]
        if not rows:
            raise GroundTruthError(f'ground truth {path} has a header but no poses')
    else:
        width = len(first)
        if width not in (4, 8):
            raise GroundTruthError(f'{path} line {rows[0][0]}: expected 4 (t x y z) or 8 '
                                   f'(t x y z qx qy qz qw) columns, got {width}')
        columns = {'t': 0, 'x': 1, 'y': 2, 'z': 3}
        if width == 8:
            columns.update(qx=4, qy=5, qz=6, qw=7)
    has_quat = all(k in columns for k in ('qx', 'qy', 'qz', 'qw'))
    value_keys = ['x', 'y', 'z'] + (['qx', 'qy', 'qz', 'qw'] if has_quat else [])
    needed = max(columns.values()) + 1
    n_rows = len(rows)
    times = []
    values = np.empty((n_rows, len(value_keys)))
    lines = np.array([number for number, _ in rows])
    for i, (number, line) in enumerate(rows):
        tokens = _split(line)
        if len(tokens) < needed:
            raise GroundTruthError(f'{path} line {number}: expected at least {needed} values, '
                                   f'got {len(tokens)}')
        try:
            times.append(decimal_of(tokens[columns['t']]))
            values[i] = [float(tokens[columns[k]]) for k in value_keys]
        except ValueError as exc:
            raise GroundTruthError(f'{path} line {number}: {exc}') from exc
    if not np.isfinite(values).all():
        bad = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
        raise GroundTruthError(f'{path} line {lines[bad]}: non-finite value')
    in_ns = max(abs(t) for t in times) > NS_STAMP_THRESHOLD
    scale = 1 if in_ns else NS_PER_S
    stamps_ns = np.array([int((t * scale).to_integral_value()) for t in times], dtype=np.int64)
    quat = values[:, 3:7] if has_quat else np.tile([0.0, 0.0, 0.0, 1.0], (n_rows, 1))
    log.debug('%s: %d poses, time in %s, %s', path, n_rows, 'ns' if in_ns else 's',
              'with orientation' if has_quat else 'position only')
    return trajectory_from_columns(stamps_ns, values[:, :3], quat, str(path),
                                   line_numbers=lines)
