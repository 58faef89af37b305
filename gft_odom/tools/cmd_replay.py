"""`gft-odom replay`: recorded bags through the pipeline, results folder out."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from gft_odom.tools.args import add_bags, add_config, add_switches
from gft_odom.tools.progress import progress_bar

log = logging.getLogger(__name__)


HELP = 'replay bags through the odometry pipeline'
DESCRIPTION = ('Replay LiDAR scans from ROS 1 .bag files (split parts in time order) or '
               'rosbag2 folders through the pipeline; write TUM poses, metrics.json, the '
               'effective config and figures to --out.')


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `gft-odom replay`."""
    add_bags(p)
    p.add_argument('--out', required=True, help='results folder')
    p.add_argument('--gt', help='ground truth: gt.csv, gt.bag (/gps/fix/odometry) or TUM file')
    add_config(p)
    p.add_argument('--no-filter', action='store_true',
                   help='bypass the spectral filter (same registration): the baseline')
    p.add_argument('--max-scans', type=int, help='stop after this many scans')
    p.add_argument('--through-node', action='store_true',
                   help='run the colcon-installed filter_odom_node as its own process and feed '
                        'it over DDS (with /clock) instead of in-process')
    p.add_argument('--node-exe', help='path of filter_odom_node for --through-node '
                   '(default: <prefix>/lib/gft_odom/filter_odom_node from AMENT_PREFIX_PATH)')
    p.add_argument('--save-map', nargs='?', const='', metavar='DIR',
                   help='write the final map (binary PCD with per-point frequency) and the '
                        "trajectory (TUM), odom frame, as the node's ~/save_map does, into "
                        'DIR (default: <out>/map)')
    p.add_argument('--map', metavar='PCD',
                   help='localise every scan in this map (one ~/save_map or --save-map wrote) '
                        'beside the odometry; writes trajectory_map_tum.txt (map frame)')
    p.add_argument('--initial-pose', default='0,0,0', metavar='X,Y,YAW',
                   help='with --map: where base_link is in the map at the first scan '
                        '(metres, metres, radians; default 0,0,0: where the map run started)')
    add_switches(p)


def parse_initial_pose(text: str) -> tuple[float, float, float]:
    """'x,y,yaw' -> (x, y, yaw); ConfigError with the reason."""
    import math

    from gft_odom.errors import ConfigError
    try:
        x, y, yaw = (float(v) for v in text.split(','))
    except ValueError:
        raise ConfigError(f'--initial-pose wants x,y,yaw (three numbers), got {text!r}') from None
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        raise ConfigError(f'--initial-pose wants finite numbers, got {text!r}')
    return x, y, yaw


def run(args: argparse.Namespace) -> int:
    """Replay the bags and write the results folder."""
    from gft_odom.params_file import load_config
    from gft_odom.replay import run_replay, write_results

    overrides = list(args.overrides)
    if args.no_filter:
        overrides.append('pipeline.use_spectral_filter=false')
    if args.map is not None:
        x, y, yaw = parse_initial_pose(args.initial_pose)
        overrides += [f'localisation.map_file={Path(args.map).expanduser().resolve()}',
                      f'localisation.initial_pose_xy_yaw=[{x!r}, {y!r}, {yaw!r}]']
    config = load_config(args.config, overrides)
    save_map = args.save_map
    if save_map is not None:
        save_map = Path(save_map or Path(args.out) / 'map')
    if args.through_node:
        from gft_odom.ros.through_node import replay_through_node
        replay_fn = replay_through_node
        # The node's log goes with the results (the temporary folder is removed).
        Path(args.out).mkdir(parents=True, exist_ok=True)
        extra = {'node_exe': args.node_exe, 'log_path': Path(args.out) / 'node.log'}
    else:
        replay_fn, extra = run_replay, {}
    if save_map is not None:
        extra['save_map_dir'] = save_map
    with progress_bar(None, 'replay', enabled=not args.quiet) as update:
        replay = replay_fn(args.bags, config, gt_path=args.gt, topic=args.topic,
                           max_scans=args.max_scans, progress=update, **extra)
    paths = write_results(replay, config, args.out, figures=not args.no_figures)
    print(json.dumps(replay.metrics, indent=2, sort_keys=True))
    if 'ate_rmse_m' in replay.metrics:
        from gft_odom.tables import accuracy_line
        print(accuracy_line(replay.metrics))
    print('wrote ' + ', '.join(str(p) for p in paths.values()))
    return 0
