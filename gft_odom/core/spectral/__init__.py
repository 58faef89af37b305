"""Graph-frequency analysis of LiDAR scans: slices, slice graphs, GFT, band masks, filter."""

from gft_odom.core.spectral.bands import BandMask, band_centres, band_edges, band_of_nu
from gft_odom.core.spectral.filter import (
    FilterResult,
    PointFrequencies,
    SpectralConfig,
    SpectralFilter,
    keep_mask,
)

__all__ = [
    'BandMask',
    'FilterResult',
    'PointFrequencies',
    'SpectralConfig',
    'SpectralFilter',
    'band_centres',
    'band_edges',
    'band_of_nu',
    'keep_mask',
]
