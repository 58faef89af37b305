"""`gft-odom`: one command, one sub-command per task.

Each sub-command lives in its own module `gft_odom.tools.cmd_<name>` exposing
`HELP` (one line for the command list), `DESCRIPTION` (for its --help), `add_arguments(p)`
and `run(args) -> int`. Only the module of the command being run is imported (the others pull
in open3d, matplotlib, ...: `--help` took 3-7 s); the command list reads each module's `HELP`
without importing it. Only this module turns package errors into exit codes.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import logging
import sys
from pathlib import Path

from gft_odom.errors import GftOdomError
from gft_odom.tools.args import check_bags

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


class _IntermixedParser(argparse.ArgumentParser):
    """Sub-command parser that takes positionals after options (`BAG --gt GT BAG`)."""

    _inner = False

    def parse_known_args(self, args=None, namespace=None):
        if self._inner:  # parse_known_intermixed_args calls back into this method
            return super().parse_known_args(args, namespace)
        self._inner = True
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._inner = False


def _command_name(module: str) -> str:
    return module.replace('_', '-')


def _summary(module: str) -> str:
    """The module's `HELP` string, read from its source without importing the module."""
    path = Path(__file__).with_name(f'cmd_{module}.py')
    for node in ast.parse(path.read_text()).body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and getattr(node.targets[0], 'id', None) == 'HELP'):
            return ast.literal_eval(node.value)
    return ''


def _requested(argv: list[str]) -> str | None:
    """The sub-command named on the command line (the first word that is not an option)."""
    return next((a for a in argv if not a.startswith('-')), None)


def build_parser(requested: str | None = None) -> argparse.ArgumentParser:
    """The parser; only the `requested` sub-command gets its real (imported) sub-parser."""
    parser = argparse.ArgumentParser(
        prog='gft-odom',
        description='Graph-frequency filtered LiDAR odometry for orchards.')
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND',
                                parser_class=_IntermixedParser)
    for name in SUBCOMMAND_MODULES:
        if _command_name(name) == requested:
            module = importlib.import_module(f'gft_odom.tools.cmd_{name}')
            p = sub.add_parser(_command_name(name), help=module.HELP,
                               description=module.DESCRIPTION)
            module.add_arguments(p)
            p.set_defaults(_run=module.run)
        else:
            sub.add_parser(_command_name(name), help=_summary(name))
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the gft-odom command line; package errors become one log line and exit 1."""
    parser = build_parser(_requested(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    check_bags(parser, args)
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
