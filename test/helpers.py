"""Helpers the tests share: random velodyne-like columns, scripts imported as modules, a
small registration scene."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import open3d as o3d

from gft_odom.core.registration.matching import MapTarget


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


def load_script(path: Path, register: bool = False) -> ModuleType:
    """A Python file that is not in a package (a benchmark, a helper process) as a module.
    `register`: also in sys.modules under its stem (dataclasses look their module up there
    while being defined); the caller removes it."""
    spec = importlib.util.spec_from_file_location(Path(path).stem, path)
    module = importlib.util.module_from_spec(spec)
    if register:
        sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def box_scene(seed: int = 0, corridor: bool = False) -> np.ndarray:
    """Points on a ground plane, two long walls along x and (unless `corridor`) posts."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(-15, 15, (4000, 2)), np.zeros(4000)]
    walls = []
    for y in (-4.0, 4.0):
        walls.append(np.c_[rng.uniform(-15, 15, 1500), np.full(1500, y),
                           rng.uniform(0.0, 3.0, 1500)])
    parts = [ground] + walls
    if not corridor:
        for px, py in ((-6.0, 2.0), (3.0, -2.5), (9.0, 1.0), (-1.0, -1.5)):
            angle = rng.uniform(0, 2 * np.pi, 400)
            parts.append(np.c_[px + 0.3 * np.cos(angle), py + 0.3 * np.sin(angle),
                               rng.uniform(0.0, 2.5, 400)])
    return np.concatenate(parts)


def target_of(points: np.ndarray) -> MapTarget:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(15))
    return MapTarget(points, np.asarray(cloud.normals))
