"""`gft-odom frequencies`: every scan's per-point graph frequency and band as PCD files.

One binary PCD per scan, `<header stamp ns>.pcd`, in the sensor frame, with the points the
pipeline sees after its range crop: x y z intensity frequency (nu in [0, 1], NaN: no spectrum)
band (1..B for `spectral.n_bands`, 0: no spectrum), whatever the band mask. For inspection in
CloudCompare / Open3D / PCL and for the paper's Figure 3 (`gft-odom spectrum --pcd DIR`).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from gft_odom.tools.args import add_bags, add_config, add_switches
from gft_odom.tools.progress import progress_bar

log = logging.getLogger(__name__)

MAX_BANDS = 255  # the band field is uint8 (U1)


HELP = 'per-point graph frequency and band of every scan, as PCD files'
DESCRIPTION = ('Write one binary PCD per scan (<header stamp ns>.pcd, sensor frame) with '
               'fields x y z intensity frequency band for every point after the range '
               'crop, whatever the band mask (band 0 / frequency NaN: no spectrum).')


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `gft-odom frequencies`."""
    add_bags(p)
    p.add_argument('--out', required=True, help='output folder for the PCD files')
    add_config(p)
    add_switches(p, figures=False)


def _scan_frequencies(spectral_filter, scan, n_bands: int):
    """nu and band of every point of a cropped scan: the one call into the spectral engine."""
    return spectral_filter.scan_frequencies(scan, n_bands)


def write_frequency_pcds(scans, pipeline, out_dir: Path, progress=None) -> list[Path]:
    """Crop every scan as the pipeline does, compute its frequencies, write its PCD."""
    from gft_odom.io.pcd import frequency_cloud, write_pcd

    n_bands = pipeline.config.spectral.n_bands
    paths = []
    for scan in scans:
        cropped = pipeline._crop(scan)
        if len(cropped):
            freqs = _scan_frequencies(pipeline.spectral_filter, cropped, n_bands)
            nu, band = freqs.nu, freqs.band
        else:
            nu, band = np.zeros(0, np.float32), np.zeros(0, np.uint8)
        cloud = frequency_cloud(cropped.points_xyz, cropped.intensity, nu, band)
        path = out_dir / f'{int(scan.stamp_ns)}.pcd'
        write_pcd(path, cloud)
        paths.append(path)
        if progress is not None:
            progress(len(paths))
    return paths


def load_config_any_mask(path, overrides):
    """The config with an all-pass mask: the mask plays no part here, so `--set
    spectral.n_bands=4` alone must not be refused for a mask written for 10 bands."""
    from gft_odom.params_file import load_config, parse_override, read_params_file

    flat = read_params_file(path) if path is not None else {}
    flat.update(parse_override(text) for text in overrides)
    n_bands = flat.get('spectral.n_bands', load_config().spectral.n_bands)
    if isinstance(n_bands, int) and n_bands >= 1:
        overrides = [*overrides, f'spectral.band_mask={list(range(1, n_bands + 1))}']
    return load_config(path, overrides)


def run(args: argparse.Namespace) -> int:
    """Write the PCD files of every scan of the bags."""
    from gft_odom.errors import BagError
    from gft_odom.io.bags import ScanBagReader
    from gft_odom.pipeline import OdometryPipeline

    config = load_config_any_mask(args.config, args.overrides)
    if config.spectral.n_bands > MAX_BANDS:
        from gft_odom.errors import ConfigError
        raise ConfigError(f'spectral.n_bands = {config.spectral.n_bands}: the PCD band field is '
                          f'uint8, at most {MAX_BANDS} bands')
    pipeline = OdometryPipeline(config, record_trajectory=False)
    out_dir = Path(args.out)
    with ScanBagReader(args.bags, args.topic) as reader:
        with progress_bar(len(reader), 'frequencies', enabled=not args.quiet) as update:
            paths = write_frequency_pcds(reader, pipeline, out_dir, update)
    if not paths:
        raise BagError(f'no scans on {args.topic} in {", ".join(map(str, args.bags))}')
    s = config.spectral
    print(f'wrote {len(paths)} PCD files (B = {s.n_bands}, {s.method}) to {out_dir}')
    return 0
