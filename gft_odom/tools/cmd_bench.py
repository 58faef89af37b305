"""`gft-odom bench`: the five methods side by side on the same simulated sequences.

paper ICP and our default registration, each without and with the graph-frequency filter, and
kiss-icp: same scans, same clock, same metrics code. Writes a JSON under benchmarks/results/,
a Markdown page and plots under docs/.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import shutil
import sys
import tempfile
from pathlib import Path

from gft_odom.bench.kiss import KissIcpConfig, kiss_icp_version
from gft_odom.bench.report import (
    bench_to_dict,
    markdown_page,
    plot_figures,
    summary_table,
    write_json,
)
from gft_odom.bench.runner import (
    ALL_METHODS,
    METHODS,
    PEER_METHODS,
    profile_method,
    run_bench,
    simulate_sequences,
)
from gft_odom.core.spectral.bands import BandMask
from gft_odom.errors import ConfigError
from gft_odom.io.atomic import write_text_atomic
from gft_odom.params_file import load_config
from gft_odom.sim.motion import SCENARIOS
from gft_odom.sim.simulator import SimConfig
from gft_odom.tools.args import add_config, add_switches
from gft_odom.tools.progress import progress_bar

log = logging.getLogger(__name__)

# Benchmark seeds: disjoint from the seeds the band mask and kiss-icp's voxel were chosen on.
DEFAULT_SEEDS = (101, 102, 103)


def default_config_path() -> Path | None:
    """The package's config/filter_odom.yaml: source tree first, then the colcon install."""
    here = Path(__file__).resolve()
    candidates = [here.parents[2] / 'config' / 'filter_odom.yaml']
    candidates += [Path(p) / 'share' / 'gft_odom' / 'config' / 'filter_odom.yaml'
                   for p in _ament_prefixes()]
    return next((c for c in candidates if c.is_file()), None)


def _ament_prefixes() -> list[str]:
    import os
    return [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]


HELP = 'benchmark paper ICP, our registration (each +/- filter) and kiss-icp'
DESCRIPTION = ('Simulate orchard drives (every scenario x seed), replay each through the '
               'five methods with the same clock and metrics; write JSON, a Markdown page '
               'and plots. The band mask comes from --config (chosen on other seeds).')


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `gft-odom bench`."""
    p.add_argument('--seeds', type=int, nargs='+', default=list(DEFAULT_SEEDS),
                   help=f'simulator seeds (default {" ".join(map(str, DEFAULT_SEEDS))}); keep '
                        'them disjoint from those the band mask was chosen on')
    p.add_argument('--scenarios', nargs='+', default=list(SCENARIOS), choices=SCENARIOS)
    p.add_argument('--scans', type=int, default=150, help='scans per sequence (default 150)')
    p.add_argument('--azimuth-step-deg', type=float, default=0.2,
                   help='simulated VLP-16 azimuth step (0.2 = the real sensor; coarser only to '
                        'make tests cheap)')
    p.add_argument('--methods', nargs='+', default=list(METHODS), choices=list(ALL_METHODS),
                   help='default: the five methods; the evalio peers '
                        f'({", ".join(PEER_METHODS)}) run when named')
    add_config(p, help="params file with the band mask (default: the package's "
                                 'config/filter_odom.yaml)')
    p.add_argument('--mask-provenance', default='',
                   help='one sentence for the page: how and on which seeds the mask was chosen')
    p.add_argument('--json', default='benchmarks/results/bench.json', help='JSON output')
    p.add_argument('--markdown', default='benchmarks/results/benchmarks_short_drives.md',
                   help='Markdown page output')
    p.add_argument('--figures-dir', help="PNG folder (default: the Markdown page's folder)")
    p.add_argument('--work-dir', help='keep the simulated bags here (default: a temporary '
                                      'folder, deleted at the end)')
    p.add_argument('--profile-scans', type=int, default=0,
                   help='after the timed runs, cProfile each filtered method and kiss-icp on '
                        'this many scans of the first sequence (0: no profile)')
    p.add_argument('--notes', default='', help='Markdown paragraph added to the page')
    p.add_argument('--notes-file', help='Markdown file whose text is added to the page')
    g = p.add_argument_group('kiss-icp (defaults suit a VLP-16)')
    d = KissIcpConfig()
    g.add_argument('--kiss-voxel-size-m', type=float, default=d.voxel_size_m)
    g.add_argument('--kiss-max-range-m', type=float, default=d.max_range_m)
    g.add_argument('--kiss-min-range-m', type=float, default=d.min_range_m)
    g.add_argument('--kiss-no-deskew', action='store_true')
    g.add_argument('--kiss-threads', type=int, default=d.max_num_threads,
                   help='0 = all cores (kiss-icp default)')
    add_switches(p)


def run(args: argparse.Namespace) -> int:
    """Configure, measure every method on the simulated sequences, write and print results."""
    config_path, base_config, kiss_config, sim_config = _configs(args)
    version = kiss_icp_version() if 'kiss-icp' in args.methods else 'not run'
    bench = _measure(args, base_config, kiss_config, sim_config)
    document = bench_to_dict(bench, _settings(args, config_path, base_config, kiss_config,
                                              version))
    _write_and_print(args, bench, document)
    return 0


def _configs(args: argparse.Namespace):
    """(config path, pipeline config, kiss-icp config, simulator config), all validated."""
    if args.scans < 2:
        raise ConfigError(f'--scans must be >= 2, got {args.scans}')
    config_path = Path(args.config) if args.config else default_config_path()
    base_config = load_config(config_path, args.overrides)
    kiss_config = KissIcpConfig(
        max_range_m=args.kiss_max_range_m, min_range_m=args.kiss_min_range_m,
        voxel_size_m=args.kiss_voxel_size_m, deskew=not args.kiss_no_deskew,
        max_num_threads=args.kiss_threads)
    kiss_config.validate()
    sim_config = SimConfig(azimuth_step_deg=args.azimuth_step_deg)
    sim_config.validate()
    return config_path, base_config, kiss_config, sim_config


def _measure(args: argparse.Namespace, base_config, kiss_config: KissIcpConfig,
             sim_config: SimConfig):
    """Simulate the sequences, run every method on them, profile if asked; the bench run."""
    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix='gft_bench_'))
    try:
        n_seq = len(args.seeds) * len(args.scenarios)
        with progress_bar(n_seq, 'simulate', unit='seq', enabled=not args.quiet) as update:
            done = []
            sequences = simulate_sequences(
                work, args.scenarios, args.seeds, args.scans, sim_config,
                progress=lambda name: (done.append(name), update(len(done))))
        with progress_bar(n_seq * len(args.methods), 'bench', unit='run',
                          enabled=not args.quiet) as update:
            bench = run_bench(sequences, base_config, args.methods, kiss_config,
                              progress=lambda m, s, k, n: update(k))
        if args.profile_scans > 0:
            for method in args.methods:
                if method.endswith('+gft') or method == 'kiss-icp':
                    bench.profiles[method] = profile_method(
                        method, sequences[0], base_config, kiss_config,
                        max_scans=args.profile_scans)
    finally:
        if not args.work_dir:
            shutil.rmtree(work, ignore_errors=True)
    return bench


def _settings(args: argparse.Namespace, config_path, base_config, kiss_config: KissIcpConfig,
              version: str) -> dict:
    """What the run was asked to do, for the JSON and the page."""
    spectral = base_config.spectral
    mask = BandMask.parse(spectral.band_mask, spectral.n_bands)
    return {
        'command': 'gft-odom bench ' + ' '.join(shlex.quote(a) for a in sys.argv[2:])
        if len(sys.argv) > 1 and sys.argv[1] == 'bench' else 'gft-odom bench (API)',
        'seeds': list(args.seeds), 'scenarios': list(args.scenarios), 'n_scans': args.scans,
        'azimuth_step_deg': args.azimuth_step_deg, 'methods': list(args.methods),
        'config_path': str(config_path) if config_path else 'built-in defaults',
        'overrides': list(args.overrides),
        'n_bands': spectral.n_bands, 'band_mask': list(spectral.band_mask),
        'band_mask_bits': mask.as_bitstring(),
        'mask_provenance': args.mask_provenance or 'Provenance of the mask not given '
                                                    '(--mask-provenance).',
        'evaluation': base_config.evaluation.mode,
        'evaluation_config': {'mode': base_config.evaluation.mode,
                              'match': base_config.evaluation.match,
                              'max_diff_s': base_config.evaluation.max_diff_s,
                              'max_gap_s': base_config.evaluation.max_gap_s},
        'kiss_icp_version': version,
        'evalio_version': _evalio_version(args.methods),
        'kiss_icp_config': _as_dict(kiss_config),
        'kiss_icp_config_text': _kiss_text(kiss_config),
        'registration_config': _as_dict(base_config.registration),
        'spectral_config': _as_dict(spectral),
    }


def _write_and_print(args: argparse.Namespace, bench, document: dict) -> None:
    """JSON, figures and the Markdown page; the summary table and targets on stdout."""
    json_path = write_json(Path(args.json), document)
    md_path = Path(args.markdown)
    figures = {}
    if not args.no_figures:
        fig_dir = Path(args.figures_dir) if args.figures_dir else md_path.parent
        paths = plot_figures(bench, document, fig_dir)
        figures = {title: _relative(path, md_path.parent) for title, path in paths.items()}
    notes = args.notes
    if args.notes_file:
        notes = Path(args.notes_file).read_text() + ('\n' + notes if notes else '')
    write_text_atomic(md_path, markdown_page(document, figures, notes))
    print(summary_table(document['summary']))
    for t in document['targets']:
        print(f'[{"met" if t["met"] else "MISSED"}] {t["target"]}: {t["measured"]}')
    print(f'wrote {json_path}, {md_path}' + ''.join(f', {p}' for p in figures.values()))


def _evalio_version(methods) -> str:
    """evalio's version when a peer runs, else 'not run'."""
    from gft_odom.bench.peers import PEERS
    if not any(m in PEERS for m in methods):
        return 'not run'
    from gft_odom.bench.peers import evalio_version
    return evalio_version()


def _as_dict(cfg) -> dict:
    import dataclasses
    return {f.name: (list(v) if isinstance(v := getattr(cfg, f.name), tuple) else v)
            for f in dataclasses.fields(cfg)}


def _kiss_text(cfg: KissIcpConfig) -> str:
    return (f'max_range {cfg.max_range_m:g} m (VLP-16 rated range), min_range '
            f'{cfg.min_range_m:g} m (the robot body, as our crop), voxel_size '
            f'{cfg.voxel_size_m:g} m, max_points_per_voxel {cfg.max_points_per_voxel}, deskew '
            f'{"on with the per-point `time` field" if cfg.deskew else "off"}, adaptive '
            f'threshold (initial {cfg.initial_threshold_m:g} m, min motion '
            f'{cfg.min_motion_threshold_m:g} m), {cfg.max_num_iterations} iterations max, '
            f'convergence {cfg.convergence_criterion:g}, threads '
            f'{cfg.max_num_threads or "all (0)"}.')


def _relative(path: Path, start: Path) -> str:
    import os
    return os.path.relpath(Path(path).resolve(), Path(start).resolve())
