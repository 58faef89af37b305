"""A turn's onset, traced: each scan's match from the prediction, where ICP's iteration cap
stopped it, where it ends when carried on, and where it ends from the true heading; and each
scan's outcome (status, heading and position error, the speed a refused match implied).

docs/registration.md, session 30: on edge drive 226 the matches of scans 1136-1138 hit the cap
while still turning, 0.04-0.09 rad short of where they converge. Session 42: on edge drive
221 (scans 1095-1120) three good matches after a corner are refused for the speed bound.

    .venv/bin/python benchmarks/turn_onset_trace.py --drive edge_lawnmower-226 --scans 1133 1140

Heading errors are against the simulator's sensor poses (ground_truth/gt_sensor_tum.txt) in the
run's frame (both start at the first scan). The replay stops after the last scan asked for.
Writes benchmarks/results/turn_onset_<drive>.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gft_odom.bench.drives import default_cache_dir, ensure_drives
from gft_odom.core.geometry import invert_transform
from gft_odom.io.atomic import write_text_atomic
from gft_odom.io.tum import read_tum
from gft_odom.params_file import load_config
from gft_odom.pipeline import OdometryPipeline
from gft_odom.replay import run_replay

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_record import DRIVE_SETS, RESULTS  # noqa: E402


class _Done(Exception):
    """The last scan asked for is registered."""


def heading_error_rad(T, T_true: np.ndarray) -> float:
    """Yaw of `T` minus yaw of `T_true`, wrapped to [-pi, pi)."""
    T = np.asarray(T)
    difference = np.arctan2(T[1, 0], T[0, 0]) - np.arctan2(T_true[1, 0], T_true[0, 0])
    return float((difference + np.pi) % (2.0 * np.pi) - np.pi)


class TracingPipeline(OdometryPipeline):
    """The default pipeline; the main match of each scan in [first, last] is also run carried
    on and from the true heading (extra ICP calls whose results are only recorded)."""

    def __init__(self, config, truth, first: int, last: int, carry_on: int):
        super().__init__(config)
        self.truth, self.first, self.last, self.carry_on = truth, first, last, carry_on
        self.index, self.stamp_ns, self.rows, self.outcomes = -1, 0, [], []
        self.last_registration = None
        register = self.registration.register

        def kept(*args, **kwargs):
            self.last_registration = register(*args, **kwargs)
            return self.last_registration
        self.registration.register = kept
        icp = self.registration.icp
        plain = icp.register

        def traced(source, target, init, distance_m, **kwargs):
            result = plain(source, target, init, distance_m, **kwargs)
            if kwargs.get('prior') and self.first <= self.index <= self.last:
                self._trace(plain, source, target, init, distance_m, result)
            return result
        icp.register = traced

    def _true_pose(self) -> np.ndarray:
        return self.truth.pose_at(self.stamp_ns)

    def _trace(self, plain, source, target, init, distance_m, result) -> None:
        truth = self._true_pose()
        carried = plain(source, target, np.asarray(result.transformation), distance_m,
                        max_iterations=self.carry_on)
        at_truth = truth.copy()
        at_truth[:3, 3] = init[:3, 3]
        from_truth = plain(source, target, at_truth, distance_m)
        self.rows.append({
            'scan': self.index, 'prediction_rad': heading_error_rad(init, truth),
            'match_rad': heading_error_rad(result.transformation, truth),
            'match_iterations': int(getattr(result, 'n_iterations', -1)),
            'carried_on_rad': heading_error_rad(carried.transformation, truth),
            'carried_on_iterations': int(getattr(carried, 'n_iterations', -1)),
            'from_true_heading_rad': heading_error_rad(from_truth.transformation, truth)})

    def register_frame(self, scan, freqs=None):
        self.index += 1
        self.stamp_ns = int(scan.stamp_ns)
        self.last_registration = None
        result = super().register_frame(scan, freqs)
        if self.first <= self.index <= self.last and self.rows:
            self.rows[-1].setdefault('status', result.status)
            self.rows[-1].setdefault('final_rad', heading_error_rad(result.T_world_sensor,
                                                                    self._true_pose()))
        if self.first <= self.index <= self.last:
            truth, reg = self._true_pose(), self.last_registration
            self.outcomes.append({
                'scan': self.index, 'status': result.status,
                'heading_rad': heading_error_rad(result.T_world_sensor, truth),
                'position_m': float(np.linalg.norm(result.T_world_sensor[:3, 3]
                                                   - truth[:3, 3])),
                'fitness': None if reg is None else float(reg.fitness),
                'refused_speed_mps': None if reg is None else reg.refused_speed_mps})
        if self.index >= self.last:
            raise _Done
        return result


def main(argv=None) -> int:
    """Trace the scans of one drive; print and write one row per traced match."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    drives = {d.name: d for ds in DRIVE_SETS.values() for d in ds}
    p.add_argument('--drive', choices=sorted(drives), default='edge_lawnmower-226')
    p.add_argument('--scans', type=int, nargs=2, default=(1133, 1140), metavar=('FIRST', 'LAST'))
    p.add_argument('--carry-on', type=int, default=300, help='iterations of the carried-on ICP')
    p.add_argument('--set', nargs='*', default=[], metavar='KEY=VALUE',
                   help='config overrides, as `gft-odom replay --set`')
    p.add_argument('--cache', type=Path, default=None,
                   help=f'simulated drives (default {default_cache_dir()})')
    p.add_argument('--out', type=Path, default=RESULTS)
    args = p.parse_args(argv)
    first, last = args.scans
    if not 0 <= first <= last:
        p.error('--scans needs 0 <= FIRST <= LAST')
    sequence, = ensure_drives([drives[args.drive]], args.cache)
    folder = Path(sequence.gt_path).parent
    truth_world = read_tum(folder / 'gt_sensor_tum.txt')
    # The run's frame: world = the sensor at the first scan.
    truth = truth_world.transformed(invert_transform(truth_world.poses[0]))
    config = load_config(None, args.set)
    pipeline = TracingPipeline(config, truth, first, last, args.carry_on)
    try:
        run_replay([sequence.bag_path], config, pipeline=pipeline)
    except _Done:
        pass
    print('scan  prediction  match (iterations)  carried on (iterations)  from true heading'
          '  final  status')
    for r in pipeline.rows:
        print(f"{r['scan']:5d} {r['prediction_rad']:+10.3f} {r['match_rad']:+8.3f} "
              f"({r['match_iterations']:3d}) {r['carried_on_rad']:+13.3f} "
              f"({r['carried_on_iterations']:3d}) {r['from_true_heading_rad']:+17.3f} "
              f"{r.get('final_rad', float('nan')):+7.3f}  {r.get('status', '')}")
    print('scan  status                  heading  position  fitness  refused speed [m/s]')
    for r in pipeline.outcomes:
        speed = r['refused_speed_mps']
        print(f"{r['scan']:5d} {r['status']:23s} {r['heading_rad']:+7.3f} {r['position_m']:9.3f}"
              f"  {r['fitness'] if r['fitness'] is not None else float('nan'):7.3f}"
              f"  {'' if speed is None else f'{speed:.2f}'}")
    out = args.out / f'turn_onset_{args.drive}.json'
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, json.dumps({'drive': args.drive, 'scans': [first, last],
                                       'carry_on': args.carry_on, 'overrides': args.set,
                                       'rows': pipeline.rows, 'outcomes': pipeline.outcomes},
                                      indent=2))
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
