"""Where along a drive the error accrues, for gft_odom, a peer and gft_odom with one part off.

Each method runs on one cached drive of the record; its poses (each stamped where it holds)
are compared with the simulator's sensor poses at the same stamps. The drive is cut into 5 m
pieces of travel, each labelled by what the robot did in it: `turn` (turning faster than
0.1 rad/s anywhere in the piece: a pivot covers no ground), else what it did over most of it,
`row` (inside the block, driving straight) or `headland` (straight, outside the rows). Per
label: the pieces' mean relative translation error in % of their length (the pose at the
piece's end seen from its start, as RPE) and their mean absolute heading error, the two
things ATE grows from.

    .venv/bin/python benchmarks/where_it_accrues.py --drive spiral-303 --peer GenZ-ICP

`--peer` names a row of the record (bench_record.ENTRIES). `--parts` adds our default with one
part switched off or set otherwise at a time (the window, the kernel, deskew, the source
voxel). Runs go through the record's cache: a pair the record measured is read back
with its trajectory, a new one is measured and kept. Writes
benchmarks/results/accrual_<drive>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from gft_odom.bench.drives import default_cache_dir, ensure_drives
from gft_odom.bench.record import Entry, cached_trajectory, pair_file, run_record
from gft_odom.config import GftOdomConfig
from gft_odom.core.geometry import invert_transform
from gft_odom.core.trajectory import Trajectory
from gft_odom.io.atomic import write_text_atomic
from gft_odom.io.tum import read_tum
from gft_odom.sim.simulator import ScanSimulator, SimConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_record import DRIVE_SETS, ENTRIES, RESULTS  # noqa: E402

PIECE_M = 5.0
TURN_RATE_RPS = 0.1
LABELS = ('row', 'turn', 'headland')
# One part of the default switched off (or set to what a peer does) at a time.
PARTS = {
    'window of 20 keyframes': {'registration.map_keyframes': 20},
    'window of 120 keyframes': {'registration.map_keyframes': 120,
                                'registration.map_max_points': 160000},
    'kernel 3x wider (Tukey 0.9 m)': {'registration.robust_kernel_scale_m': 0.9},
    'no deskew': {'registration.deskew': False},
    'source voxel 0.3 m': {'registration.voxel_size_m': 0.3},
}


def find_drive(name: str):
    """The record's drive called `name` (any drive set)."""
    for drives in DRIVE_SETS.values():
        for drive in drives:
            if drive.name == name:
                return drive
    raise SystemExit(f'no drive {name!r} in the record; sets: {sorted(DRIVE_SETS)}')


def phase_labels(drive, truth: Trajectory) -> np.ndarray:
    """row / turn / headland at each ground-truth pose, from the drive's own orchard."""
    sim, _ = ScanSimulator.for_drive(SimConfig(azimuth_step_deg=2.0), drive.route, drive.seed,
                                     distance_m=drive.distance_m, vary=True,
                                     family=drive.family)
    orchard = sim.orchard
    yaw = np.unwrap(np.arctan2(truth.poses[:, 1, 0], truth.poses[:, 0, 0]))
    rate = np.abs(np.gradient(yaw, truth.stamps_s))
    uv = (truth.positions_xyz[:, :2] - orchard.origin_xy_m) @ orchard.rotation_2d
    inside = (uv[:, 0] >= orchard.row_start_u_m) & (uv[:, 0] <= orchard.row_end_u_m)
    return np.where(rate > TURN_RATE_RPS, 'turn', np.where(inside, 'row', 'headland'))


def truth_at(truth: Trajectory, stamps_ns: np.ndarray) -> np.ndarray:
    """Ground-truth poses at `stamps_ns` (interpolated)."""
    return np.array([truth.pose_at(int(s)) for s in stamps_ns])


def accrual(estimate: Trajectory, truth: Trajectory, labels: np.ndarray) -> dict:
    """Per label: pieces, metres, mean relative translation error [%] and heading error
    [deg] over 5 m pieces of travel."""
    keep = (estimate.stamps_ns >= truth.stamps_ns[0]) & (estimate.stamps_ns <= truth.stamps_ns[-1])
    est = estimate.poses[keep]
    stamps = estimate.stamps_ns[keep]
    ref = truth_at(truth, stamps)
    label = labels[np.clip(np.searchsorted(truth.stamps_ns, stamps), 0, len(labels) - 1)]
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(
        np.diff(ref[:, :3, 3], axis=0), axis=1))])
    edges = np.searchsorted(travelled, np.arange(0.0, travelled[-1], PIECE_M))
    out = {name: {'pieces': 0, 'metres': 0.0, 'drift_pct': [], 'heading_deg': []}
           for name in LABELS}
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        # A turn covers little ground (a pivot none): a piece with any turning in it is a turn.
        names, counts = np.unique(label[a:b + 1], return_counts=True)
        name = 'turn' if 'turn' in names else str(names[int(np.argmax(counts))])
        d_est = invert_transform(est[a]) @ est[b]
        d_ref = invert_transform(ref[a]) @ ref[b]
        error = invert_transform(d_ref) @ d_est
        length = travelled[b] - travelled[a]
        out[name]['pieces'] += 1
        out[name]['metres'] += float(length)
        out[name]['drift_pct'].append(100.0 * float(np.linalg.norm(error[:3, 3])) / length)
        out[name]['heading_deg'].append(abs(math.degrees(math.atan2(error[1, 0],
                                                                    error[0, 0]))))
    for value in out.values():
        value['drift_pct'] = float(np.mean(value['drift_pct'])) if value['drift_pct'] else None
        value['heading_deg'] = (float(np.mean(value['heading_deg'])) if value['heading_deg']
                                else None)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--drive', required=True, help='a record drive, e.g. spiral-303')
    p.add_argument('--peer', action='append', default=[],
                   help='a row of the record (repeat): GenZ-ICP, CT-ICP, ...')
    p.add_argument('--parts', action='store_true', help='our default with one part off')
    p.add_argument('--cache', type=Path, default=None)
    p.add_argument('--out', type=Path, default=RESULTS)
    args = p.parse_args(argv)
    drive = find_drive(args.drive)
    cache = args.cache or default_cache_dir()
    sequence = ensure_drives([drive], cache)[0]
    truth = read_tum(Path(sequence.gt_path).parent / 'gt_sensor_tum.txt')
    labels = phase_labels(drive, truth)
    record = {e.label: e for e in ENTRIES}
    unknown = [peer for peer in args.peer if peer not in record]
    if unknown:
        p.error(f'no record row {unknown}; rows: {list(record)}')
    entries = [record['gft_odom']] + [record[peer] for peer in args.peer]
    if args.parts:
        entries += [Entry(f'gft_odom, {name}', 'default+gft', tuple(values.items()))
                    for name, values in PARTS.items()]
    runs_dir = cache / 'record_runs'
    rows = {}
    for entry in entries:
        if cached_trajectory(runs_dir, entry, sequence) is None:
            # Not measured, or measured before the record kept trajectories: measure again.
            pair_file(runs_dir, entry, sequence, GftOdomConfig()).unlink(missing_ok=True)
        metrics = run_record([entry], [sequence], cache_dir=runs_dir).metrics[
            (entry.label, sequence.name)]
        trajectory = cached_trajectory(runs_dir, entry, sequence)
        rows[entry.label] = {'ate_rmse_m': metrics['ate_rmse_m'],
                             'stamp_best_shift_ms': metrics.get('stamp_best_shift_ms'),
                             **accrual(trajectory, truth, labels)}
        print(f'{entry.label}: ATE {rows[entry.label]["ate_rmse_m"]:.4f} m', flush=True)
    header = ['method', 'ATE RMSE [m]'] + [f'{name} {what}' for name in LABELS
                                           for what in ('drift [%]', 'heading [deg]')]
    lines = ['| ' + ' | '.join(header) + ' |', '|---|' + '---:|' * (len(header) - 1)]
    for label, row in rows.items():
        cells = [f'{row["ate_rmse_m"]:.4f}']
        for name in LABELS:
            for key, fmt in (('drift_pct', '{:.2f}'), ('heading_deg', '{:.3f}')):
                value = row[name][key]
                cells.append('n/a' if value is None else fmt.format(value))
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    metres = {name: next(iter(rows.values()))[name]['metres'] for name in LABELS}
    text = (f'Drive {drive.name}: ' + ', '.join(f'{name} {metres[name]:.0f} m'
                                                for name in LABELS)
            + ' (5 m pieces).\n\n' + '\n'.join(lines) + '\n')
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / f'accrual_{drive.name}.md', text)
    write_text_atomic(args.out / f'accrual_{drive.name}.json',
                      json.dumps(rows, indent=2, sort_keys=True) + '\n')
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
