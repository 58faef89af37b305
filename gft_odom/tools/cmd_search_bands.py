"""`gft-odom search-bands`: offline band-mask search with held-out scoring."""

from __future__ import annotations

import argparse
import logging

from gft_odom.errors import ConfigError
from gft_odom.tools.args import add_bags, add_config, add_switches
from gft_odom.tools.progress import progress_bar

log = logging.getLogger(__name__)


HELP = 'search band masks on training bags, score the best held-out'
DESCRIPTION = ('Rank band masks by trajectory error on the training bags (in-sample), '
               'report the chosen mask on --test bags (held-out) beside the unfiltered '
               'baseline, and write best_mask.yaml for filter_odom_node --params-file. '
               'BAG i pairs with GT i; with a single --gt all BAGs are the split parts of '
               'one sequence. Results are appended as they finish: rerun the same command '
               'to resume.')


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `gft-odom search-bands`."""
    add_bags(p, help='training bag(s)')
    # One file per --gt (repeat it): `nargs='+'` swallowed a BAG written after it.
    p.add_argument('--gt', action='append', required=True, metavar='GT',
                   help='ground truth of a training bag (gt.csv, gt.bag or TUM); repeat it, '
                        'in the order of the BAGs')
    p.add_argument('--out', required=True, help='output folder (also the resume state)')
    p.add_argument('--min-bands', type=int, default=2)
    p.add_argument('--max-bands', type=int, default=10)
    p.add_argument('--mode', choices=('paper', 'default'),
                   help='registration mode (default: from --config, else default)')
    p.add_argument('--strategy', choices=('exhaustive', 'smart'), default='exhaustive',
                   help='every combination, or correlation-seeded beam search')
    p.add_argument('--test', action='append', default=[], metavar='BAG',
                   help='a held-out bag; repeat it')
    p.add_argument('--test-gt', action='append', default=[], metavar='GT',
                   help='ground truth of a held-out bag; repeat it, in the order of --test')
    p.add_argument('--workers', type=int, default=1, help='local worker processes')
    p.add_argument('--ray-address', metavar='ADDR',
                   help='run on an existing Ray cluster (e.g. 127.0.0.1:6379)')
    add_config(p)
    p.add_argument('--max-scans', type=int, help='use the first N scans of each sequence')
    add_switches(p)


def pair_sequences(bags: list[str], gts: list[str], what: str):
    """BAG i with GT i, or all BAGs as one split sequence when a single GT is given."""
    from gft_odom.bands.search import SequenceSpec
    if not bags and not gts:
        return []
    if len(gts) == len(bags):
        return [SequenceSpec((b,), g) for b, g in zip(bags, gts)]
    if len(gts) == 1:
        return [SequenceSpec(tuple(bags), gts[0])]
    raise ConfigError(f'{what}: {len(bags)} bag(s) but {len(gts)} ground truth file(s); give '
                      'one per bag, or one for a sequence split over several bags')


def run(args: argparse.Namespace) -> int:
    """Search the masks and write the results and best_mask.yaml."""
    from gft_odom.bands.run import run_band_search, summary_markdown
    from gft_odom.bands.search import BandSearchConfig
    from gft_odom.params_file import load_config

    overrides = list(args.overrides)
    if args.mode:
        overrides.append(f'registration.mode={args.mode}')
    config = load_config(args.config, overrides)
    train = pair_sequences(args.bags, args.gt, 'training set')
    test = pair_sequences(args.test, args.test_gt, '--test')
    search_cfg = BandSearchConfig(min_bands=args.min_bands, max_bands=args.max_bands,
                                  strategy=args.strategy,
                                  smart_seed_max_bands=min(3, args.max_bands))
    if args.workers < 1:
        raise ConfigError(f'--workers must be >= 1, got {args.workers}')
    with progress_bar(None, 'search-bands', unit='mask', enabled=not args.quiet) as update:
        state = {'stage': None}

        def progress(stage: str, done: int, total: int) -> None:
            if stage != state['stage']:
                state['stage'] = stage
                log.info('%s: %d to do', stage, total)
            update(done, total)

        summary = run_band_search(train, config, args.out, search_cfg, test=test,
                                  workers=args.workers, ray_address=args.ray_address,
                                  topic=args.topic, max_scans=args.max_scans,
                                  figures=not args.no_figures,
                                  progress=None if args.quiet else progress)
    print(summary_markdown(summary))
    print(f'wrote {args.out}/ranking.csv, summary.json, best_mask.yaml')
    return 0
