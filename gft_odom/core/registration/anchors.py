"""The map's anchors: points kept after their keyframe left the window, one per voxel.

A long run accumulates hundreds of thousands of anchors (up to `ANCHOR_MAX_POINTS`, 2M by
default), and the map rebuild at every keyframe must neither sort them again nor touch those
far away. They are kept sorted by voxel key, whose major axis is x, in two runs: a large one
and a small recent one that new anchors join (merged into the large one when it grows past
`RECENT_ROWS`). Serving the anchors near a keyframe is two binary searches for the slab of
voxels within the map radius along x (`voxels.voxel_x_slab`), and a merge of the two slabs
by key: the same anchors, in the same order, as one sorted array would give, at a cost that
does not grow with the run.

Measured (benchmarks/bench_anchors.py): with 1M anchors a keyframe's map update took 0.36 s
of rebuild and 0.20 s of anchoring when every rebuild scanned and every anchoring re-sorted
all of them.
"""

from __future__ import annotations

import numpy as np

# New anchors wait in the recent run until it holds this many, then join the large run.
RECENT_ROWS = 65536


def _rows(a: np.ndarray) -> np.ndarray:
    """An (n, k) array as n opaque rows (boolean-mask copies of rows are far faster so)."""
    a = np.ascontiguousarray(a)
    return a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()


def _insert(old: np.ndarray, at: np.ndarray, new: np.ndarray) -> np.ndarray:
    """`np.insert(old, at, new, axis=0)` for sorted `at`, in O(n) with one mask (np.insert
    is ~10x slower on a million rows)."""
    if old.ndim == 2:
        return _insert(_rows(old), at, _rows(new)).view(old.dtype).reshape(-1, old.shape[1])
    out = np.empty(old.shape[0] + new.shape[0], dtype=old.dtype)
    where = at + np.arange(at.shape[0])
    keep = np.ones(out.shape[0], dtype=bool)
    keep[where] = False
    out[where] = new
    out[keep] = old
    return out


class _Run:
    """Anchors sorted by voxel key: keys, points, smoothness, viewpoints."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, dtype=np.int64)
        self.points = np.zeros((0, 3))
        self.smoothness = np.zeros(0)
        self.viewpoints = np.zeros((0, 3))

    def __len__(self) -> int:
        return self.keys.shape[0]

    def find(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(where each key is or would go, whether it is there)."""
        at = np.searchsorted(self.keys, keys)
        known = at < self.keys.shape[0]
        known[known] = self.keys[at[known]] == keys[known]
        return at, known

    def insert(self, keys, points, smoothness, viewpoints) -> None:
        """Add anchors of new, unique, sorted keys."""
        at = np.searchsorted(self.keys, keys)
        self.keys = _insert(self.keys, at, keys)
        self.points = _insert(self.points, at, points)
        self.smoothness = _insert(self.smoothness, at, smoothness)
        self.viewpoints = _insert(self.viewpoints, at, viewpoints)

    def take(self, index) -> None:
        """Keep only these anchors (sorted indices or a mask)."""
        self.keys, self.points = self.keys[index], self.points[index]
        self.smoothness, self.viewpoints = self.smoothness[index], self.viewpoints[index]

    def slab(self, lo_key: int, hi_key: int) -> slice:
        """The anchors with lo_key <= key < hi_key."""
        return slice(*np.searchsorted(self.keys, [lo_key, hi_key]))


class AnchorStore:
    """The anchors of a local map, one per voxel, sorted by voxel key (see the module)."""

    def __init__(self, recent_rows: int = RECENT_ROWS) -> None:
        self.recent_rows = recent_rows
        self.clear()

    def clear(self) -> None:
        """No anchor."""
        self._main, self._recent = _Run(), _Run()

    def __len__(self) -> int:
        return len(self._main) + len(self._recent)

    def find(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(whether each key is anchored, its smoothness there: NaN where not)."""
        smoothness = np.full(keys.shape[0], np.nan)
        known = np.zeros(keys.shape[0], dtype=bool)
        for run in (self._main, self._recent):
            at, here = run.find(keys)
            smoothness[here] = run.smoothness[at[here]]
            known |= here
        return known, smoothness

    def replace(self, keys, points, smoothness, viewpoints) -> None:
        """Give anchored voxels (`keys`, all known) a new point, smoothness and viewpoint."""
        for run in (self._main, self._recent):
            at, here = run.find(keys)
            where = at[here]
            run.points[where] = points[here]
            run.smoothness[where] = smoothness[here]
            run.viewpoints[where] = viewpoints[here]

    def add(self, keys, points, smoothness, viewpoints) -> None:
        """Anchor new voxels (unique keys, none anchored yet; any order)."""
        if keys.shape[0] == 0:
            return
        order = np.argsort(keys)
        self._recent.insert(keys[order], points[order], smoothness[order],
                            viewpoints[order])
        if len(self._recent) > self.recent_rows:
            self._flush()

    def _flush(self) -> None:
        """The recent run joins the large one."""
        recent, self._recent = self._recent, _Run()
        self._main.insert(recent.keys, recent.points, recent.smoothness, recent.viewpoints)

    def keep_nearest(self, centre_xyz: np.ndarray, max_points: int) -> None:
        """Over `max_points`, drop the anchors farthest from `centre_xyz`."""
        if len(self) <= max_points:
            return
        self._flush()
        offset = self._main.points - centre_xyz
        keep = np.sort(np.argpartition(np.einsum('ij,ij->i', offset, offset),
                                       max_points - 1)[:max_points])
        self._main.take(keep)

    def in_slab(self, lo_key: int, hi_key: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points, smoothness, viewpoints) of the anchors with lo_key <= key < hi_key (a
        slab along x: local_map.voxel_x_slab), sorted by voxel key."""
        main, recent = self._main.slab(lo_key, hi_key), self._recent.slab(lo_key, hi_key)
        if recent.start == recent.stop:  # nothing recent here
            return (self._main.points[main], self._main.smoothness[main],
                    self._main.viewpoints[main])
        keys = np.concatenate([self._main.keys[main], self._recent.keys[recent]])
        order = np.argsort(keys, kind='stable')
        return tuple(np.concatenate([a[main], b[recent]])[order] for a, b in (
            (self._main.points, self._recent.points),
            (self._main.smoothness, self._recent.smoothness),
            (self._main.viewpoints, self._recent.viewpoints)))
