"""Horizontal slices of a cloud: which layer of thickness h each point falls in.

The slices are sorted into contiguous blocks so that every later step (graph, Laplacian,
Chebyshev recursion, Lanczos) works on ONE block-diagonal matrix instead of a loop over slices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gft_odom.errors import SpectralError


@dataclass(frozen=True)
class Slices:
    """Points in the z range, sorted by slice.

    `order[i]` is the input index of sorted point i; `starts` (n_slices + 1,) are the block
    boundaries in sorted order (empty slices are left out); `slice_of_point` (n,) gives each
    sorted point its block number 0..n_slices-1; `in_range` (N_input,) marks the points kept.
    """

    order: np.ndarray
    starts: np.ndarray
    slice_of_point: np.ndarray
    in_range: np.ndarray
    z_bottom_m: np.ndarray  # (n_slices,) lower z of every non-empty slice

    @property
    def n_slices(self) -> int:
        """Number of non-empty slices."""
        return int(self.starts.shape[0] - 1)

    @property
    def sizes(self) -> np.ndarray:
        """Points per slice."""
        return np.diff(self.starts)


def slice_points(z_m: np.ndarray, thickness_m: float, z_min_m: float, z_max_m: float) -> Slices:
    """Assign each point to the layer [z_min + k h, z_min + (k + 1) h) inside [z_min, z_max).

    Points outside [z_min_m, z_max_m) or with a non-finite z get no slice (`in_range` False).
    """
    if not thickness_m > 0.0:
        raise SpectralError(f'slice thickness must be > 0 m, got {thickness_m}')
    if not z_max_m > z_min_m:
        raise SpectralError(f'z range is empty: z_min_m {z_min_m} >= z_max_m {z_max_m}')
    z_m = np.asarray(z_m, dtype=np.float64)
    in_range = np.isfinite(z_m) & (z_m >= z_min_m) & (z_m < z_max_m)
    idx = np.flatnonzero(in_range)
    layer = np.floor((z_m[idx] - z_min_m) / thickness_m).astype(np.int64)
    sort = np.argsort(layer, kind='stable')
    order = idx[sort]
    layer = layer[sort]
    if layer.size:
        first = np.flatnonzero(np.r_[True, layer[1:] != layer[:-1]])
        starts = np.r_[first, layer.size].astype(np.int64)
        used_layers = layer[first]
        slice_of_point = np.repeat(np.arange(first.size), np.diff(starts))
    else:
        starts = np.zeros(1, dtype=np.int64)
        used_layers = np.zeros(0, dtype=np.int64)
        slice_of_point = np.zeros(0, dtype=np.int64)
    return Slices(order=order, starts=starts, slice_of_point=slice_of_point, in_range=in_range,
                  z_bottom_m=z_min_m + used_layers * thickness_m)


def voxelise(xy_m: np.ndarray, slice_of_point: np.ndarray, n_slices: int, voxel_size_m: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Merge points of one slice that share a 2-D voxel into one graph node (their centroid).

    Near the sensor a VLP-16 ring has points ~1 cm apart, so the graph's edge count (and the
    cost of everything after it) is dominated by a few metres of ground; merging at a voxel
    size well below tau removes that redundancy. Returns (node_xy (n, 2), node_slice (n,),
    starts (n_slices + 1,) block boundaries over the nodes, node_of_point (N_sorted,)); with
    voxel_size_m <= 0 every point is its own node. Nodes stay sorted by slice.
    """
    xy_m = np.asarray(xy_m, dtype=np.float64)
    slice_of_point = np.asarray(slice_of_point, dtype=np.int64)
    if voxel_size_m <= 0.0 or xy_m.shape[0] == 0:
        starts = np.searchsorted(slice_of_point, np.arange(n_slices + 1))
        return xy_m, slice_of_point, starts.astype(np.int64), np.arange(xy_m.shape[0])
    cell = np.floor(xy_m / voxel_size_m).astype(np.int64)
    cell -= cell.min(axis=0)
    ny = int(cell[:, 1].max()) + 1
    nx = int(cell[:, 0].max()) + 1
    if float(nx) * float(ny) * float(max(n_slices, 1)) < 2.0**62:
        key = (slice_of_point * nx + cell[:, 0]) * ny + cell[:, 1]
        uniq, node_of_point = np.unique(key, return_inverse=True)
        node_slice = uniq // (nx * ny)
    else:  # absurd extents: an int64 key would overflow, sort rows instead (slower)
        rows = np.column_stack([slice_of_point, cell])
        uniq, node_of_point = np.unique(rows, axis=0, return_inverse=True)
        node_of_point = node_of_point.ravel()
        node_slice = uniq[:, 0]
    count = np.bincount(node_of_point).astype(np.float64)
    node_xy = np.column_stack([np.bincount(node_of_point, weights=xy_m[:, c]) / count
                               for c in range(2)])
    starts = np.searchsorted(node_slice, np.arange(n_slices + 1)).astype(np.int64)
    return node_xy, node_slice, starts, node_of_point
