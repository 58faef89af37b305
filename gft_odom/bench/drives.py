"""The long drives of the benchmark of record: which ones, and their simulated cache.

- TRAINING_DRIVES (seeds 111-125): the only drives choices of the registration were made on.
- RECORD_DRIVES (201-206, 211-214): ten varied drives, every route, only ever reported.
- NEVER_USED_DRIVES (231-234): four more, run only to confirm what the record suggested.
- EDGE_DRIVES (221-228, 241-244, 251-254, 261-264): twenty fast lawn-mowers that start on the
  block's edge and turn out into an open headland. EDGE_TUNED_SEEDS are the ones a rule of
  the turn check or of a slid match was chosen on; the others were only reported.
- STRESS_DRIVES (301-306): the stress family, every quantity outside the varied ranges.

Each drive is simulated once with `simulate_to_bag(..., vary=True)` into a cache outside the
repository (default `~/.cache/gft_odom/drives`, or `$GFT_ODOM_DRIVES`); a drive whose
`sim_metadata.json` is complete is reused.
"""

from __future__ import annotations

import json
import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from gft_odom.bench.runner import BenchSequence
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import METADATA_FILE, bag_path_for, simulate_to_bag


@dataclass(frozen=True)
class Drive:
    """One route of about `distance_m` in the orchard of `seed`, drawn from `family` ('varied',
    or 'stress': outside every varied range, sim/variation.STRESS_RANGES)."""

    route: str
    seed: int
    distance_m: float
    family: str = 'varied'

    @property
    def name(self) -> str:
        """Folder and table name, e.g. `lawnmower-201`."""
        return f'{self.route}-{self.seed}'


# 118, 121 and 125 are the first seeds after 114 whose draw is fast (> 1.4 m/s), turns fast
# (> 1 rad/s) and pivots (turn radius < 0.5 m): none of 111-114 pivots.
TRAINING_DRIVES = (Drive('lawnmower', 111, 200.0), Drive('spiral', 112, 200.0),
                   Drive('every_other_row', 113, 200.0), Drive('out_and_back', 114, 200.0),
                   Drive('every_other_row', 118, 150.0), Drive('lawnmower', 121, 150.0),
                   Drive('every_other_row', 125, 150.0))
RECORD_DRIVES = tuple(Drive(route, seed, 280.0) for route, seed in (
    ('lawnmower', 201), ('every_other_row', 202), ('spiral', 203), ('out_and_back', 204),
    ('lawnmower', 205), ('spiral', 206), ('lawnmower', 211), ('every_other_row', 212),
    ('spiral', 213), ('out_and_back', 214)))
NEVER_USED_DRIVES = tuple(Drive(route, seed, 280.0) for route, seed in (
    ('lawnmower', 231), ('every_other_row', 232), ('spiral', 233), ('out_and_back', 234)))
EDGE_DRIVES = tuple(Drive('edge_lawnmower', seed, 280.0) for seed in (
    221, 222, 223, 224, 225, 226, 227, 228, 241, 242, 243, 244, 251, 252, 253, 254,
    261, 262, 263, 264))
EDGE_TUNED_SEEDS = (221, 222, 223, 224, 226, 227, 242, 243)
STRESS_DRIVES = tuple(Drive(route, seed, 260.0, 'stress') for route, seed in (
    ('lawnmower', 301), ('every_other_row', 302), ('spiral', 303), ('out_and_back', 304),
    ('lawnmower', 305), ('every_other_row', 306)))


def default_cache_dir() -> Path:
    """Where simulated drives are kept between runs (never inside the repository)."""
    env = os.environ.get('GFT_ODOM_DRIVES')
    return Path(env) if env else Path.home() / '.cache' / 'gft_odom' / 'drives'


def _drive_dir(cache_dir: Path, drive: Drive) -> Path:
    return Path(cache_dir) / drive.name


def drive_sequence(cache_dir: Path, drive: Drive) -> BenchSequence:
    """The bench sequence of a cached drive (its bag and GPS ground truth)."""
    folder = _drive_dir(cache_dir, drive)
    meta = json.loads((folder / METADATA_FILE).read_text())
    return BenchSequence(drive.route, drive.seed, int(meta['n_scans']),
                         bag_path_for(folder, drive.route, drive.seed, 'ros2'),
                         folder / 'ground_truth' / 'gt.csv')


def _simulate(cache_dir: Path, drive: Drive, config: SimConfig) -> str:
    folder = _drive_dir(cache_dir, drive)
    if folder.exists():  # an interrupted run: start that drive again
        shutil.rmtree(folder)
    partial = folder.with_name(folder.name + '.partial')
    if partial.exists():
        shutil.rmtree(partial)
    simulate_to_bag(partial, drive.route, None, drive.seed, config, topdown_png=True,
                    distance_m=drive.distance_m, vary=True, family=drive.family)
    # The bag's folder name does not depend on the parent, so one rename publishes it.
    partial.rename(folder)
    return drive.name


def ensure_drives(drives: Sequence[Drive], cache_dir: Path | None = None,
                  config: SimConfig | None = None, jobs: int = 1,
                  progress: Callable[[str], None] | None = None) -> list[BenchSequence]:
    """Simulate every drive not yet in the cache (`jobs` at a time); their sequences."""
    cache_dir = Path(cache_dir or default_cache_dir())
    cache_dir.mkdir(parents=True, exist_ok=True)
    config = config or SimConfig()
    missing = [d for d in drives if not (_drive_dir(cache_dir, d) / METADATA_FILE).is_file()]
    if missing and jobs > 1:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            for name in pool.map(_simulate, [cache_dir] * len(missing), missing,
                                 [config] * len(missing)):
                if progress is not None:
                    progress(name)
    else:
        for drive in missing:
            _simulate(cache_dir, drive, config)
            if progress is not None:
                progress(drive.name)
    return [drive_sequence(cache_dir, d) for d in drives]
