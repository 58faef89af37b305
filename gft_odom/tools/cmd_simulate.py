"""`gft-odom simulate`: write a synthetic orchard run as a CitrusFarm-like dataset."""

from __future__ import annotations

import argparse
import dataclasses
import logging

from gft_odom.errors import ConfigError
from gft_odom.sim.motion import ROUTES, SCENARIOS
from gft_odom.sim.simulator import ScanSimulator, SimConfig
from gft_odom.sim.writer import simulate_to_bag
from gft_odom.tools.args import add_switches
from gft_odom.tools.progress import progress_bar

log = logging.getLogger(__name__)


HELP = 'simulate a VLP-16 on a Jackal driving through a citrus orchard'
DESCRIPTION = ('Simulate a VLP-16 on a Jackal in a synthetic citrus orchard and write a '
               'bag (/velodyne_points, /gps/fix/odometry), ground_truth/gt.csv, '
               'ground_truth/gt_sensor_tum.txt and topdown.png under --out.')


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `gft-odom simulate`."""
    p.add_argument('--scenario', choices=SCENARIOS + ROUTES, default='row',
                   help='row: straight between two rows; uturn: down one row and back along '
                        'the next; loop: around a block of rows (default: row). Routes over '
                        "many rows, like CitrusFarm's: lawnmower, every_other_row, spiral, "
                        'out_and_back (about --distance-m long); edge_lawnmower: a fast '
                        'lawn-mower from the block edge, turning in open ground')
    p.add_argument('--scans', type=int, default=None,
                   help='number of sweeps (10 Hz); default 300, or the whole route')
    p.add_argument('--distance-m', type=float, default=300.0,
                   help='length of a route in metres (default 300)')
    p.add_argument('--vary', action='store_true',
                   help='draw orchard, terrain, speeds, turns, mount and wind from the seed '
                        '(ranges in docs/benchmarks.md); recorded in sim_metadata.json')
    p.add_argument('--stress', action='store_true',
                   help='with --vary: the stress family, every quantity drawn outside the '
                        'varied ranges (other canopy models, spacings, mount, speed, wobble)')
    p.add_argument('--seed', type=int, default=0, help='orchard and noise seed')
    p.add_argument('--day', type=int, default=0,
                   help='with --vary: 0 the map day; N >= 1 a later day in the same block '
                        '(same trees, posts, ground; its own canopy, route and driving)')
    p.add_argument('--map-route', choices=ROUTES,
                   help='the route the block was mapped with on day 0 (default: --scenario)')
    p.add_argument('--map-distance-m', type=float,
                   help="day 0's distance, which sizes the block (default: --distance-m)")
    p.add_argument('--canopy', choices=('same', 'grown', 'hedged', 'changed'), default='changed',
                   help="a later day's canopy against day 0's (changed: grown or hedged)")
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
    add_switches(p, figures=False)


def run(args: argparse.Namespace) -> int:
    """Simulate the drive and write its bag and ground truth."""
    config = dataclasses.replace(SimConfig(), motion_distortion=not args.no_distortion,
                                 legacy_fields=args.legacy_fields,
                                 azimuth_step_deg=args.azimuth_step_deg)
    if args.stress and not args.vary:
        raise ConfigError('--stress draws a variation: give --vary with it')
    family = 'stress' if args.stress else 'varied'
    scans = args.scans
    if scans is None and args.scenario not in ROUTES:
        scans = 300
    total = scans
    if scans is None and args.day > 0:
        from gft_odom.sim.later_day import simulate_day
        total = simulate_day(config, args.seed, args.map_route or args.scenario, args.day,
                             args.scenario, args.canopy, args.map_distance_m or args.distance_m,
                             args.distance_m)[0].n_scans_in_drive
    elif scans is None:  # the whole route: its length is known once it is planned (cheap)
        total = ScanSimulator.for_drive(config, args.scenario, args.seed, None,
                                        args.distance_m, args.vary,
                                        family)[0].n_scans_in_drive
    # The bar shows on a terminal only: `simulate ... > log 2>&1` writes no bar into the log.
    with progress_bar(total, f'simulate {args.scenario}', enabled=not args.quiet) as update:
        result = simulate_to_bag(args.out, args.scenario, scans, args.seed, config,
                                 fmt=args.fmt, topdown_png=not args.no_png,
                                 progress=lambda done: update(done),
                                 distance_m=args.distance_m, vary=args.vary,
                                 family=family, day=args.day, map_route=args.map_route,
                                 canopy=args.canopy, map_distance_m=args.map_distance_m)
    print(f'bag:          {result.bag_path}')
    print(f'ground truth: {result.gt_csv_path}')
    print(f'sensor poses: {result.gt_tum_path}')
    if result.topdown_png_path is not None:
        print(f'top-down:     {result.topdown_png_path}')
    print(f'{result.n_scans} scans, median {result.median_seconds_per_scan:.3f} s per scan')
    return 0
