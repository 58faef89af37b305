"""Command-line arguments the gft-odom sub-commands share (one spelling, one help text)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_bags(parser: argparse.ArgumentParser, help: str = 'bag file(s) or rosbag2 folder',
             nargs: str = '+') -> None:
    """The input bags (positional) and --topic."""
    parser.add_argument('bags', nargs=nargs, metavar='BAG', help=help)
    parser.add_argument('--topic', default='/velodyne_points', help='PointCloud2 topic')


def check_bags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """A missing "bag" spelled KEY=VALUE is a second override after one --set (`--set a=1
    b=2`): say so, rather than that no such bag exists."""
    for bag in getattr(args, 'bags', None) or ():
        if '=' in bag and not Path(bag).exists():
            parser.error(f'{bag!r} is not a bag but looks like a parameter: give each its own '
                         '--set (--set SECTION.KEY=VALUE --set SECTION.KEY2=VALUE2)')


def add_config(parser: argparse.ArgumentParser,
                         help: str = 'ROS params file (as for filter_odom_node --params-file)'
                         ) -> None:
    """--config / --set, shared by every sub-command that runs the pipeline."""
    parser.add_argument('--config', '--params-file', dest='config', metavar='YAML', help=help)
    parser.add_argument('--set', dest='overrides', action='append', default=[],
                        metavar='SECTION.KEY=VALUE',
                        help='override one parameter, e.g. --set spectral.band_mask=[1,9,10]')


def add_switches(parser: argparse.ArgumentParser, figures: bool = True) -> None:
    """--no-figures (when the command draws any) and --quiet."""
    if figures:
        parser.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    parser.add_argument('--quiet', action='store_true', help='no progress bars')
