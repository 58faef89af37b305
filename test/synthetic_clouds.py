"""Random velodyne-like columns for codec, bag and DDS tests (one definition for all)."""

from __future__ import annotations

import numpy as np


def velodyne_columns(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """x, y, z, intensity (float32), ring (uint16), time (float32 in [0, 0.1)) of n points."""
    rng = np.random.default_rng(seed)
    return {
        'x': rng.normal(0, 10, n).astype(np.float32),
        'y': rng.normal(0, 10, n).astype(np.float32),
        'z': rng.normal(0, 1, n).astype(np.float32),
        'intensity': rng.uniform(0, 255, n).astype(np.float32),
        'ring': rng.integers(0, 16, n).astype(np.uint16),
        'time': rng.uniform(0, 0.1, n).astype(np.float32),
    }
