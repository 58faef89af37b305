"""Helpers the tests share: random velodyne-like columns, scripts imported as modules."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

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


def load_script(path: Path) -> ModuleType:
    """A Python file that is not in a package (a benchmark, a helper process) as a module."""
    spec = importlib.util.spec_from_file_location(Path(path).stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
