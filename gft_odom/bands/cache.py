"""Per-point frequencies of a whole sequence, computed once and re-filtered by every mask.

The frequencies of a scan do not depend on the mask, and one graph/Lanczos/Chebyshev pass
serves every band count (`SpectralFilter.frequencies_multi`), so a sequence is analysed once
for B = min..max. The cache holds the cropped scans (what the pipeline's filter sees), each
point's band for every B, the band-0 flags and the ground truth, and is saved as one .npz in
the search folder so a restarted search, and every worker process, loads it instead of
recomputing it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from gft_odom.config import GftOdomConfig
from gft_odom.core.spectral.bands import BandMask
from gft_odom.core.spectral.filter import PointFrequencies, SpectralFilter, keep_mask
from gft_odom.core.trajectory import Trajectory
from gft_odom.core.types import Scan
from gft_odom.errors import BagError
from gft_odom.io.atomic import write_atomic
from gft_odom.io.bags import ScanBagReader
from gft_odom.io.ground_truth import read_ground_truth
from gft_odom.pipeline import OdometryPipeline
from gft_odom.replay import is_gps_ground_truth

log = logging.getLogger(__name__)

CACHE_VERSION = 1


@dataclass
class SequenceCache:
    """Cropped scans of one sequence (bags + ground truth) and their bands for several B."""

    name: str
    key: str
    stamps_ns: np.ndarray  # (S,) int64
    offsets: np.ndarray  # (S + 1,) int64 into the point arrays
    points_xyz: np.ndarray  # (P, 3) float64, cropped as the pipeline crops
    time_offset_s: np.ndarray | None  # (P,) float32
    bands: dict[int, np.ndarray]  # B -> (P,) int16
    nu: dict[int, np.ndarray]  # B -> (P,) float32
    isolated: np.ndarray  # (P,) bool
    in_range: np.ndarray  # (P,) bool
    finite: np.ndarray  # (P,) bool
    n_slices: np.ndarray  # (S,) int64
    ground_truth: Trajectory
    ground_truth_is_gps: bool
    points_in: np.ndarray  # (S,) points before the crop

    def __len__(self) -> int:
        return int(self.stamps_ns.size)

    @property
    def band_counts(self) -> tuple[int, ...]:
        """The band counts B with cached frequencies, ascending."""
        return tuple(sorted(self.bands))

    def _span(self, i: int) -> slice:
        return slice(int(self.offsets[i]), int(self.offsets[i + 1]))

    def scan(self, i: int) -> Scan:
        """Cropped scan i as the pipeline saw it (stamp, points, per-point times)."""
        s = self._span(i)
        offsets = None if self.time_offset_s is None else self.time_offset_s[s]
        return Scan(int(self.stamps_ns[i]), self.points_xyz[s], time_offset_s=offsets)

    def frequencies(self, i: int, n_bands: int) -> PointFrequencies:
        """The cached `PointFrequencies` of cropped scan i for `n_bands` bands."""
        if n_bands not in self.bands:
            raise KeyError(f'sequence {self.name}: no frequencies cached for n_bands = '
                           f'{n_bands} (have {list(self.band_counts)})')
        s = self._span(i)
        return PointFrequencies(nu=self.nu[n_bands][s], band=self.bands[n_bands][s],
                                n_bands=n_bands, isolated=self.isolated[s],
                                in_range=self.in_range[s], finite=self.finite[s],
                                n_slices=int(self.n_slices[i]))

    def per_scan(self, array: np.ndarray) -> list[np.ndarray]:
        """Split a (P,) array over all cached points into one array per scan."""
        return [array[self._span(i)] for i in range(len(self))]

    def keep(self, i: int, mask: BandMask, keep_isolated: bool) -> np.ndarray:
        """(n,) points of cropped scan i that `mask` keeps (`keep_mask` on the cached data)."""
        return keep_mask(self.frequencies(i, mask.n_bands), mask, keep_isolated)

    # -- persistence ---------------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write one .npz atomically (temp file + rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {
            'stamps_ns': self.stamps_ns, 'offsets': self.offsets, 'points_xyz': self.points_xyz,
            'isolated': self.isolated, 'in_range': self.in_range, 'finite': self.finite,
            'n_slices': self.n_slices, 'points_in': self.points_in,
            'gt_stamps_ns': self.ground_truth.stamps_ns, 'gt_poses': self.ground_truth.poses,
        }
        if self.time_offset_s is not None:
            arrays['time_offset_s'] = self.time_offset_s
        for n in self.bands:
            arrays[f'band_{n}'] = self.bands[n]
            arrays[f'nu_{n}'] = self.nu[n]
        meta = {'version': CACHE_VERSION, 'name': self.name, 'key': self.key,
                'band_counts': list(self.band_counts), 'gps': self.ground_truth_is_gps}
        arrays['meta'] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        return write_atomic(path, lambda f: np.savez(f, **arrays))

    @classmethod
    def load(cls, path: str | Path) -> 'SequenceCache':
        """Read a cache written by `save`."""
        with np.load(path) as data:
            meta = json.loads(bytes(data['meta']).decode())
            counts = meta['band_counts']
            return cls(
                name=meta['name'], key=meta['key'], stamps_ns=data['stamps_ns'],
                offsets=data['offsets'], points_xyz=data['points_xyz'],
                time_offset_s=data['time_offset_s'] if 'time_offset_s' in data else None,
                bands={int(n): data[f'band_{n}'] for n in counts},
                nu={int(n): data[f'nu_{n}'] for n in counts},
                isolated=data['isolated'], in_range=data['in_range'], finite=data['finite'],
                n_slices=data['n_slices'],
                ground_truth=Trajectory(data['gt_stamps_ns'], data['gt_poses']),
                ground_truth_is_gps=bool(meta['gps']), points_in=data['points_in'])

    @staticmethod
    def read_key(path: str | Path) -> str | None:
        """The key stored in a cache file, None when it cannot be read."""
        try:
            with np.load(path) as data:
                meta = json.loads(bytes(data['meta']).decode())
            return meta['key'] if meta.get('version') == CACHE_VERSION else None
        except (OSError, ValueError, KeyError):
            return None


def cache_key(bags: Sequence[str | Path], gt_path: str | Path, config: GftOdomConfig,
              band_counts: Sequence[int], topic: str, max_scans: int | None) -> str:
    """What the cached frequencies depend on: inputs, crop, spectral parameters (not the mask)."""
    spectral = dataclasses.asdict(config.spectral)
    spectral.pop('n_bands')
    spectral.pop('band_mask')
    files = []
    for p in [*bags, gt_path]:
        p = Path(p)
        size = sum(f.stat().st_size for f in p.rglob('*') if f.is_file()) if p.is_dir() else (
            p.stat().st_size if p.exists() else -1)
        files.append([str(p.resolve()), size])
    text = json.dumps({'v': CACHE_VERSION, 'files': files, 'topic': topic,
                       'max_scans': max_scans, 'crop': dataclasses.asdict(config.pipeline),
                       'spectral': spectral, 'band_counts': sorted(set(band_counts))},
                      sort_keys=True, default=list)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def build_sequence_cache(bags: Sequence[str | Path], gt_path: str | Path,
                         config: GftOdomConfig, band_counts: Sequence[int], name: str = '',
                         topic: str = '/velodyne_points', max_scans: int | None = None,
                         progress: Callable[[int, int], None] | None = None) -> SequenceCache:
    """Read the scans, crop them as the pipeline does, compute bands for every B once."""
    counts = sorted(set(int(n) for n in band_counts))
    spectral = SpectralFilter.from_config(config.spectral)
    cropper = OdometryPipeline(config, record_trajectory=False)
    ground_truth = read_ground_truth(gt_path)
    stamps, points, offsets_t, points_in, n_slices = [], [], [], [], []
    flags = {'isolated': [], 'in_range': [], 'finite': []}
    bands = {n: [] for n in counts}
    nus = {n: [] for n in counts}
    has_time = True
    with ScanBagReader(list(bags), topic=topic) as reader:
        total = len(reader) if max_scans is None else min(len(reader), max_scans)
        for i, scan in enumerate(reader):
            if i >= total:
                break
            cropped = cropper._crop(scan)
            freqs = spectral.frequencies_multi(cropped.points_xyz, counts, ring=cropped.ring)
            first = freqs[counts[0]]
            stamps.append(int(scan.stamp_ns))
            points.append(np.asarray(cropped.points_xyz, dtype=np.float64))
            has_time = has_time and cropped.time_offset_s is not None
            offsets_t.append(cropped.time_offset_s)
            points_in.append(len(scan))
            n_slices.append(first.n_slices)
            flags['isolated'].append(first.isolated)
            flags['in_range'].append(first.in_range)
            flags['finite'].append(first.finite)
            for n in counts:
                bands[n].append(freqs[n].band.astype(np.int16))
                nus[n].append(freqs[n].nu.astype(np.float32))
            if progress is not None:
                progress(i + 1, total)
    if len(stamps) < 2:
        raise BagError(f'{", ".join(map(str, bags))}: {len(stamps)} scan(s) on {topic}; the '
                       'band search needs at least 2')
    sizes = np.array([p.shape[0] for p in points], dtype=np.int64)
    return SequenceCache(
        name=name or Path(bags[0]).name,
        key=cache_key(bags, gt_path, config, counts, topic, max_scans),
        stamps_ns=np.array(stamps, dtype=np.int64),
        offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        points_xyz=np.concatenate(points), time_offset_s=(
            np.concatenate(offsets_t).astype(np.float32) if has_time else None),
        bands={n: np.concatenate(v) for n, v in bands.items()},
        nu={n: np.concatenate(v) for n, v in nus.items()},
        isolated=np.concatenate(flags['isolated']), in_range=np.concatenate(flags['in_range']),
        finite=np.concatenate(flags['finite']), n_slices=np.array(n_slices, dtype=np.int64),
        ground_truth=ground_truth, ground_truth_is_gps=is_gps_ground_truth(gt_path),
        points_in=np.array(points_in, dtype=np.int64))


def load_or_build(cache_path: str | Path | None, bags: Sequence[str | Path],
                  gt_path: str | Path, config: GftOdomConfig, band_counts: Sequence[int],
                  name: str = '', topic: str = '/velodyne_points',
                  max_scans: int | None = None,
                  progress: Callable[[int, int], None] | None = None) -> SequenceCache:
    """The cache at `cache_path` when its key matches these inputs, else built (and saved)."""
    key = cache_key(bags, gt_path, config, band_counts, topic, max_scans)
    if cache_path is not None and Path(cache_path).exists():
        if SequenceCache.read_key(cache_path) == key:
            log.info('frequency cache %s reused', cache_path)
            return SequenceCache.load(cache_path)
        log.info('frequency cache %s is stale (inputs or spectral parameters changed); '
                 'rebuilding', cache_path)
    cache = build_sequence_cache(bags, gt_path, config, band_counts, name, topic, max_scans,
                                 progress)
    if cache_path is not None:
        cache.save(cache_path)
    return cache
