"""Where mask evaluations run: in-process, a local process pool, or an existing Ray cluster.

Every executor takes mask keys and yields result rows as they finish (any order); the search
appends each row to its results file at once, so nothing finished is lost. Workers get the
cached sequences once (the pool loads the .npz files in its initializer, Ray puts them in the
object store), then each task is one mask.
"""

from __future__ import annotations

import logging
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Iterable, Iterator, Sequence

from gft_odom.bands.cache import SequenceCache
from gft_odom.bands.evaluate import BASELINE_KEY, evaluate_mask, shift_vector, split_shifted_key
from gft_odom.bands.masks import parse_mask_key
from gft_odom.config import GftOdomConfig
from gft_odom.errors import ConfigError, GftOdomError

log = logging.getLogger(__name__)


def evaluate_key(sequences: Sequence[SequenceCache], config: GftOdomConfig, key: str) -> dict:
    """Evaluate a mask given by its key ('baseline' for the unfiltered pipeline; a shifted
    key, 'B2:11@0.333', runs the scans shifted by that fraction of a source voxel)."""
    base, fraction = split_shifted_key(key)
    mask = None if base == BASELINE_KEY else parse_mask_key(base)
    if fraction is None:
        return evaluate_mask(sequences, config, mask)
    row = evaluate_mask(sequences, config, mask, shift_vector(config, fraction))
    row.update(key=key, shift_voxel_fraction=fraction)
    return row


class InProcessExecutor:
    """One mask after the other in this process (workers = 1)."""

    def __init__(self, sequences: Sequence[SequenceCache], config: GftOdomConfig) -> None:
        self.sequences = list(sequences)
        self.config = config

    def run(self, keys: Iterable[str]) -> Iterator[dict]:
        """Evaluate each mask key here, one after the other; rows in key order."""
        for key in keys:
            yield evaluate_key(self.sequences, self.config, key)

    def close(self) -> None:
        """Nothing to release."""


_WORKER_STATE: dict = {}


def _init_worker(cache_paths: list[str], config: GftOdomConfig) -> None:
    _WORKER_STATE['sequences'] = [SequenceCache.load(p) for p in cache_paths]
    _WORKER_STATE['config'] = config


def _pool_task(key: str) -> dict:
    return evaluate_key(_WORKER_STATE['sequences'], _WORKER_STATE['config'], key)


class ProcessPoolMaskExecutor:
    """A local pool of `workers` processes, each loading the cache files once."""

    def __init__(self, cache_paths: Sequence[str | Path], config: GftOdomConfig,
                 workers: int) -> None:
        if workers < 1:
            raise ConfigError(f'workers must be >= 1, got {workers}')
        self.workers = workers
        self.pool = ProcessPoolExecutor(max_workers=workers, initializer=_init_worker,
                                        initargs=([str(p) for p in cache_paths], config))

    def run(self, keys: Iterable[str]) -> Iterator[dict]:
        """Evaluate the mask keys in the worker processes; rows as they finish."""
        pending = set()
        keys = iter(keys)
        # At most 2 tasks per worker in flight, so an interrupted search wastes little.
        for key in keys:
            pending.add(self.pool.submit(_pool_task, key))
            if len(pending) >= 2 * self.workers:
                break
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                yield future.result()
                nxt = next(keys, None)
                if nxt is not None:
                    pending.add(self.pool.submit(_pool_task, nxt))

    def close(self) -> None:
        """Stop the workers, dropping tasks not started."""
        self.pool.shutdown(wait=True, cancel_futures=True)


class RayMaskExecutor:
    """Tasks on an existing Ray cluster (`address` as for `ray.init`, e.g. '127.0.0.1:6379').

    The cluster's workers must import `gft_odom` (same install on every node). The cached
    sequences go to the object store once and are shared by every task.
    """

    def __init__(self, sequences: Sequence[SequenceCache], config: GftOdomConfig,
                 address: str, max_in_flight: int | None = None) -> None:
        try:
            import ray
        except ImportError as exc:
            raise ConfigError('--ray-address needs the `ray` package (pip install ray)') from exc
        self.ray = ray
        self._owns = not ray.is_initialized()
        if self._owns:
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=False,
                         logging_level=logging.WARNING)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                raise GftOdomError(f'cannot connect to the Ray cluster at {address}: {exc}'
                                   ) from exc
        cpus = int(ray.cluster_resources().get('CPU', 1))
        self.max_in_flight = max_in_flight or max(2, 2 * cpus)
        self.refs = [ray.put(seq) for seq in sequences]
        self.config_ref = ray.put(config)
        self.task = ray.remote(num_cpus=1)(_ray_task)
        log.info('Ray cluster at %s: %d CPUs', address, cpus)

    def run(self, keys: Iterable[str]) -> Iterator[dict]:
        """Evaluate the mask keys as Ray tasks; rows as they finish."""
        ray = self.ray
        keys = iter(keys)
        pending = []
        for key in keys:
            pending.append(self.task.remote(self.config_ref, key, *self.refs))
            if len(pending) >= self.max_in_flight:
                break
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                yield ray.get(ref)
                nxt = next(keys, None)
                if nxt is not None:
                    pending.append(self.task.remote(self.config_ref, nxt, *self.refs))

    def close(self) -> None:
        """Disconnect from Ray when this executor started the connection."""
        if self._owns:
            self.ray.shutdown()


def _ray_task(config: GftOdomConfig, key: str, *sequences: SequenceCache) -> dict:
    return evaluate_key(list(sequences), config, key)


def make_executor(sequences: Sequence[SequenceCache], cache_paths: Sequence[str | Path] | None,
                  config: GftOdomConfig, workers: int = 1, ray_address: str | None = None):
    """Ray when an address is given, else a process pool (workers > 1) or in-process."""
    if ray_address:
        return RayMaskExecutor(sequences, config, ray_address)
    if workers > 1:
        if not cache_paths:
            raise ConfigError('a process pool needs the frequency cache saved to disk')
        return ProcessPoolMaskExecutor(cache_paths, config, workers)
    return InProcessExecutor(sequences, config)
