"""`gft-odom simulate`: write a synthetic orchard run as a CitrusFarm-like dataset."""

from __future__ import annotations

import argparse
import dataclasses
import logging

from gft_odom.sim.motion import SCENARIOS
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag

log = logging.getLogger(__name__)


HELP = 'simulate a VLP-16 on a Jackal driving through a citrus orchard'
DESCRIPTION = ('Simulate a VLP-16 on a Jackal in a synthetic citrus orchard and write a '
               'bag (/velodyne_points, /gps/fix/odometry), ground_truth/gt.csv, '
               'ground_truth/gt_sensor_tum.txt and topdown.png under --out.')


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `gft-odom simulate`."""
    p.add_argument('--scenario', choices=SCENARIOS, default='row',
                   help='row: straight between two rows; uturn: down one row and back along '
                        'the next; loop: around a block of rows (default: row)')
    p.add_argument('--scans', type=int, default=300, help='number of sweeps (10 Hz)')
    p.add_argument('--seed', type=int, default=0, help='orchard and noise seed')
    p.add_argument('--out', required=True, help='output directory')
    p.add_argument('--format', choices=('ros2', 'ros1'), default='ros2', dest='fmt',
                   help='rosbag2 folder (default) or ROS 1 .bag')
    p.add_argument('--no-distortion', action='store_true',
                   help='instantaneous sweeps (no motion within a sweep; time = 0)')
    p.add_argument('--legacy-fields', action='store_true',
                   help='ROS 1 PointXYZIR layout without the per-point time field '
                        '(as CitrusFarm records)')
    p.add_argument('--azimuth-step-deg', type=float, default=SimConfig.azimuth_step_deg,
                   help='horizontal resolution (0.2 = real VLP-16; coarser is faster)')
    p.add_argument('--no-png', action='store_true', help='skip topdown.png')


def run(args: argparse.Namespace) -> int:
    """Simulate the drive and write its bag and ground truth."""
    from tqdm import tqdm

    config = dataclasses.replace(SimConfig(), motion_distortion=not args.no_distortion,
                                 legacy_fields=args.legacy_fields,
                                 azimuth_step_deg=args.azimuth_step_deg)
    with tqdm(total=args.scans, unit='scan', desc=f'simulate {args.scenario}') as bar:
        result = simulate_to_bag(args.out, args.scenario, args.scans, args.seed, config,
                                 fmt=args.fmt, topdown_png=not args.no_png,
                                 progress=lambda done: bar.update(done - bar.n))
    print(f'bag:          {result.bag_path}')
    print(f'ground truth: {result.gt_csv_path}')
    print(f'sensor poses: {result.gt_tum_path}')
    if result.topdown_png_path is not None:
        print(f'top-down:     {result.topdown_png_path}')
    print(f'{result.n_scans} scans, median {result.median_seconds_per_scan:.3f} s per scan')
    return 0
