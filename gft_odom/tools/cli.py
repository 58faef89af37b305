"""`gft-odom`: one command, one sub-command per task.

Each sub-command lives in its own module `gft_odom.tools.cmd_<name>` exposing
`HELP` (one line for the command list), `DESCRIPTION` (for its --help), `add_arguments(p)`
and `run(args) -> int`. Only this module turns package errors into exit codes.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from gft_odom.errors import GftOdomError

SUBCOMMAND_MODULES = (
    'simulate',
    'spectrum',
    'frequencies',
    'replay',
    'demo',
    'config',
    'search_bands',
    'bench',
)

log = logging.getLogger('gft_odom')


def build_parser() -> argparse.ArgumentParser:
    """The gft-odom parser with every sub-command."""
    parser = argparse.ArgumentParser(
        prog='gft-odom',
        description='Graph-frequency filtered LiDAR odometry for orchards.')
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')
    for name in SUBCOMMAND_MODULES:
        module = importlib.import_module(f'gft_odom.tools.cmd_{name}')
        p = sub.add_parser(name.replace('_', '-'), help=module.HELP,
                           description=module.DESCRIPTION)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the gft-odom command line; package errors become one log line and exit 1."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format='%(levelname)s %(name)s: %(message)s')
    try:
        return int(args._run(args) or 0)
    except GftOdomError as exc:
        log.error('%s', exc)
        return 1
    except KeyboardInterrupt:
        log.error('interrupted')
        return 130


if __name__ == '__main__':
    sys.exit(main())
