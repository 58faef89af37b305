"""LiDAR-only odometry peers from evalio (pip package `evalio`) behind our per-scan interface.

evalio wraps published pipelines in C++ behind one API: set params, LiDAR and IMU parameters,
`initialize()`, then `add_lidar(LidarMeasurement)` per sweep and `saved_estimates()` for the
(stamp, SE3) poses it produced. `EvalioOdometry(pipeline).register_frame(scan)` returns a
`KissFrame` like `KissIcpOdometry`, so the bench runs these peers exactly like kiss-icp.

Six of evalio's pipelines are LiDAR-only (kiss, genz, mad, ct, loam, form); dlio and liosam
need an IMU, which our recordings lack, and are refused. All six ignore the IMU parameters
and read the LiDAR parameters (rows, columns, ranges, rate); each reports the pose of the IMU
frame, which is the LiDAR frame here (imu_T_lidar = identity), once per sweep, stamped with the
measurement's stamp: the sweep start. Where the pose holds within the sweep (`pose_time_s`):

- kiss (deskew on) and mad (deskew on) deskew to the sweep END: stamped at the latest point.
- ct deskews continuously and reports the pose at the sweep's first point (its begin pose).
- loam, form, and kiss / mad / genz with deskew off fit the sweep as one rigid cloud, which
  holds at about the sweep's middle; evalio stamps it at the sweep start, we at the middle of
  the sweep's per-point times. The stamp audit (`gft_odom.core.metrics.stamp_audit`) checks
  each of these on the drives.
- genz's deskew expects per-point stamps normalised to [0, 1] (its DeSkewScan interpolates
  around 0.5) while evalio hands it seconds, so genz with deskew on is refused here: GenZ-ICP
  with its deskew runs through its own pip package (`gft_odom.bench.genz`).

loam and form index the cloud as a dense row-major image (num_rows x num_columns, a missing
return = a zero point); the others take the valid points only. The conversion is numpy plus
evalio's own `pc2_to_evalio` / `fill_col_row_major`, with no Python loop over points: row =
ring (or derived from the elevation angle), column = azimuth step from the sweep's first point
(the head spins clockwise, as the VLP-16 and our simulator do), per-point time = the scan's
`time_offset_s` or, without it, column / num_columns * period.

Known behaviours of the wrapped code (read in the upstream sources, not worked around here):
mad runs with `realtime=True` by default, which stops its ICP iterations when the sweep period
(minus 5 ms) is used up, so its latency sits near 95 ms by design and its accuracy depends on
the machine's load; GenZ-ICP keeps its adaptive voxel size in a function-level static, shared
by every GenZICP instance of a process (a second run starts from the first run's voxel); ct
asks Ceres for 8 threads and Ceres logs once that it bounds them to the machine's cores.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from gft_odom.bench.kiss import KissFrame
from gft_odom.config import PipelineConfig
from gft_odom.core.constants import NS_PER_S
from gft_odom.core.deskew import sweep_middle_offset_s
from gft_odom.core.types import Scan
from gft_odom.errors import ConfigError

# evalio's names of its LiDAR-only pipelines; the IMU ones are refused with a reason.
LIDAR_ONLY_PIPELINES = ('kiss', 'genz', 'mad', 'ct', 'loam', 'form')
IMU_PIPELINES = ('dlio', 'liosam')
# Pipelines that index the cloud as a dense rows x columns image.
ORGANISED_PIPELINES = frozenset({'loam', 'form'})
# Pipelines whose deskew (when on) moves every point to the sweep's latest point.
DESKEW_TO_END_PIPELINES = frozenset({'kiss', 'mad'})

# THE one place for parameter changes a pipeline needs on a VLP-16 (evalio defaults otherwise).
# Measured on simulated VLP-16 drives (uturn/row, 80 scans): every pipeline runs with evalio's
# defaults; the one change is for reproducibility. Add {'pipeline': {'param': value}} here,
# with the reason.
VLP16_PARAMS: dict[str, dict[str, bool | int | float | str]] = {
    # MAD-ICP's default `realtime` mode spends what is left of each 0.1 s period iterating, so
    # its accuracy would depend on the machine's load; the benchmarks need it reproducible.
    'mad': {'realtime': False},
}

# bench method name -> (evalio pipeline, label)
PEERS: dict[str, tuple[str, str]] = {
    'kiss-icp-evalio': ('kiss', 'kiss-icp (evalio, C++)'),
    'genz-icp-evalio': ('genz', 'GenZ-ICP (evalio, no deskew)'),
    'mad-icp': ('mad', 'MAD-ICP (evalio)'),
    'ct-icp': ('ct', 'CT-ICP (evalio)'),
    'loam': ('loam', 'LOAM (evalio)'),
    'form': ('form', 'FORM (evalio)'),
}


@dataclass(frozen=True)
class LidarLayout:
    """Geometry of the spinning LiDAR as evalio's LidarParams needs it; VLP-16 defaults.

    `n_columns` None: estimated from the first scan (median azimuth step within a ring), which
    suits recordings at an unknown azimuth resolution (our simulator's test scans are coarser
    than the sensor's 0.2 deg = 1800 columns at 10 Hz).
    """

    n_rows: int = 16
    n_columns: int | None = 1800
    rate_hz: float = 10.0
    # Same crop as our pipeline (the Jackal's body); VLP-16 rated range.
    min_range_m: float = PipelineConfig.min_range_m
    max_range_m: float = 100.0
    # Ring r looks at lowest_elevation_deg + r * elevation_step_deg (VLP-16: -15..15 by 2).
    lowest_elevation_deg: float = -15.0
    elevation_step_deg: float = 2.0
    brand: str = 'Velodyne'
    model: str = 'VLP-16'

    @property
    def period_s(self) -> float:
        """Duration of one sweep."""
        return 1.0 / self.rate_hz

    def validate(self) -> None:
        """Raise ConfigError naming the first value evalio cannot use."""
        if not 1 <= self.n_rows <= 255:
            raise ConfigError(f'lidar n_rows must be in [1, 255] (evalio stores rows as '
                              f'uint8), got {self.n_rows}')
        if self.n_columns is not None and not 8 <= self.n_columns <= 65535:
            raise ConfigError(f'lidar n_columns must be in [8, 65535] or None (estimate), '
                              f'got {self.n_columns}')
        for name in ('rate_hz', 'max_range_m', 'elevation_step_deg'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f'lidar {name} must be a finite number > 0, got {value}')
        if not (math.isfinite(self.min_range_m) and 0.0 <= self.min_range_m < self.max_range_m):
            raise ConfigError(f'lidar min_range_m must be in [0, max_range_m '
                              f'({self.max_range_m})), got {self.min_range_m}')

    def with_columns(self, n_columns: int) -> 'LidarLayout':
        """This layout with a known number of columns."""
        return dataclasses.replace(self, n_columns=int(n_columns))


@dataclass
class ScanGrid:
    """One scan's valid points with their row, column and per-point time."""

    points_xyz: np.ndarray  # (M, 3) float64
    intensity: np.ndarray  # (M,) float32
    row: np.ndarray  # (M,) int64
    column: np.ndarray  # (M,) int64
    time_s: np.ndarray  # (M,) float64, from the sweep start


def evalio_version() -> str:
    """Installed evalio version, or raise ConfigError with the install line."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version('evalio')
    except PackageNotFoundError:
        raise ConfigError('evalio is not installed: pip install evalio==0.6.1 '
                          "(or pip install -e '.[peers]')") from None


def rings_from_elevation(points_xyz: np.ndarray, layout: LidarLayout,
                         tolerance_deg: float = 0.5, max_outliers: float = 0.05) -> np.ndarray:
    """Ring of each point from its elevation angle, for clouds without a ring field.

    Raises ConfigError when more than `max_outliers` of the points lie farther than
    `tolerance_deg` from every beam of `layout` (the cloud is not from that sensor).
    """
    xyz = np.asarray(points_xyz, dtype=float)
    elevation_deg = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    beam = (elevation_deg - layout.lowest_elevation_deg) / layout.elevation_step_deg
    ring = np.rint(beam)
    off_deg = np.abs(beam - ring) * layout.elevation_step_deg
    outside = (ring < 0) | (ring >= layout.n_rows) | (off_deg > tolerance_deg)
    if xyz.shape[0] and float(np.mean(outside)) > max_outliers:
        raise ConfigError(
            f'scan has no ring field and {100.0 * float(np.mean(outside)):.0f} % of its points '
            f'are more than {tolerance_deg} deg from every beam of a {layout.model} '
            f'({layout.n_rows} rings from {layout.lowest_elevation_deg} deg by '
            f'{layout.elevation_step_deg} deg): give the ring field or the right LidarLayout')
    return np.clip(ring, 0, layout.n_rows - 1).astype(np.int64)


def estimate_n_columns(points_xyz: np.ndarray, row: np.ndarray) -> int:
    """Columns per sweep from the median azimuth step between neighbours of one ring."""
    az = np.arctan2(points_xyz[:, 1], points_xyz[:, 0])
    order = np.lexsort((az, row))
    step = np.diff(az[order])
    same_ring = row[order][1:] == row[order][:-1]
    step = step[same_ring & (step > 1e-6)]
    if step.size < 8:
        raise ConfigError(f'cannot estimate the azimuth resolution from a scan with '
                          f'{points_xyz.shape[0]} points: give LidarLayout(n_columns=...)')
    return int(round(2.0 * math.pi / float(np.median(step))))


def _valid_rows(scan: Scan, layout: LidarLayout):
    """(points, rows, intensity, times or None) of the scan's finite points."""
    xyz = np.asarray(scan.points_xyz, dtype=np.float64).reshape(-1, 3)
    valid = np.isfinite(xyz).all(axis=1)
    xyz = xyz[valid]
    if scan.ring is not None:
        row = np.asarray(scan.ring)[valid].astype(np.int64)
        if row.size and int(row.max()) >= layout.n_rows:
            raise ConfigError(f'scan ring {int(row.max())} >= n_rows {layout.n_rows} of the '
                              f'{layout.model} layout: give the right LidarLayout')
    else:
        row = rings_from_elevation(xyz, layout)
    intensity = (np.zeros(xyz.shape[0], np.float32) if scan.intensity is None
                 else np.asarray(scan.intensity, np.float32)[valid])
    times = None if scan.time_offset_s is None else \
        np.asarray(scan.time_offset_s, np.float64)[valid]
    return xyz, row, intensity, times


def scan_grid(scan: Scan, layout: LidarLayout) -> ScanGrid:
    """Row, column and time of every valid point of `scan` (numpy only).

    Column c covers the azimuth step c counted clockwise from the azimuth of the sweep's first
    point (the earliest by `time_offset_s`, else the first in the cloud), rounded to the
    nearest step. Without `time_offset_s`, a point's time is c / n_columns * period.
    """
    if layout.n_columns is None:
        raise ConfigError('scan_grid needs LidarLayout.n_columns (or estimate_n_columns)')
    xyz, row, intensity, times = _valid_rows(scan, layout)
    n = layout.n_columns
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    first = int(np.argmin(times)) if times is not None and times.size else 0
    az0 = az[first] if az.size else 0.0
    # Clockwise spin: azimuth decreases with time.
    column = np.rint(np.mod(az0 - az, 2.0 * math.pi) * (n / (2.0 * math.pi))).astype(np.int64)
    column %= n
    if times is None:
        times = column * (layout.period_s / n)
    return ScanGrid(xyz, intensity, row, column, times)


# The PointCloud2-like record handed to evalio's pc2_to_evalio (field names it reads).
_RECORD = np.dtype([('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('intensity', '<f4'),
                    ('t', '<f8'), ('ring', '<u2')])
# evalio's DataType codes (sensor_msgs/PointField): FLOAT64 = 8, FLOAT32 = 7, UINT16 = 4.
_FIELD_TYPES = {'x': 'FLOAT64', 'y': 'FLOAT64', 'z': 'FLOAT64', 'intensity': 'FLOAT32',
                't': 'FLOAT64', 'ring': 'UINT16'}


def _records(grid: ScanGrid, layout: LidarLayout, organised: bool) -> np.ndarray:
    """The grid as records: valid points in cloud order, or the dense row-major image."""
    if not organised:
        out = np.empty(grid.row.size, _RECORD)
        out['ring'] = grid.row
        target = slice(None)
        keep = slice(None)
    else:
        n = layout.n_columns
        out = np.zeros(layout.n_rows * n, _RECORD)  # a missing return: a zero point
        out['ring'] = np.repeat(np.arange(layout.n_rows, dtype=np.uint16), n)
        out['t'] = np.tile(np.arange(n) * (layout.period_s / n), layout.n_rows)
        cell = grid.row * n + grid.column
        # Later points overwrite earlier ones in a cell: keep each cell's last occurrence.
        _, last_reversed = np.unique(cell[::-1], return_index=True)
        keep = cell.size - 1 - last_reversed
        target = cell[keep]
    out['x'][target] = grid.points_xyz[keep, 0]
    out['y'][target] = grid.points_xyz[keep, 1]
    out['z'][target] = grid.points_xyz[keep, 2]
    out['intensity'][target] = grid.intensity[keep]
    out['t'][target] = grid.time_s[keep]
    return out


def grid_to_measurement(stamp_ns: int, grid: ScanGrid, layout: LidarLayout, organised: bool):
    """An evalio LidarMeasurement stamped `stamp_ns` (the sweep start) from a ScanGrid.

    organised: the dense row-major rows x columns image that loam and form index (a missing
    return is a zero point; row and col are set for every cell); else the valid points only,
    in cloud order, with row set and col left 0.
    """
    from evalio._cpp.helpers import (
        DataType,
        Field,
        PointCloudMetadata,
        fill_col_row_major,
        pc2_to_evalio,
    )
    from evalio.types import Stamp
    records = _records(grid, layout, organised)
    fields = [Field(name=name, datatype=getattr(DataType, _FIELD_TYPES[name]),
                    offset=_RECORD.fields[name][1]) for name in _RECORD.names]
    width = layout.n_columns if organised else records.size
    height = layout.n_rows if organised else 1
    meta = PointCloudMetadata(stamp=Stamp.from_nsec(int(stamp_ns)), width=width,
                              height=height, point_step=_RECORD.itemsize,
                              row_step=_RECORD.itemsize * width, is_bigendian=0,
                              is_dense=int(not organised))
    measurement = pc2_to_evalio(meta, fields, records.tobytes())
    if organised and records.size > 1:
        fill_col_row_major(measurement)
    return measurement


def to_lidar_measurement(scan: Scan, layout: LidarLayout, organised: bool):
    """`scan` as an evalio LidarMeasurement stamped at the sweep start (`scan.stamp_ns`)."""
    return grid_to_measurement(scan.stamp_ns, scan_grid(scan, layout), layout, organised)


def _pipeline_class(pipeline: str):
    """evalio's pipeline class for a LiDAR-only name, or ConfigError listing the valid ones."""
    if pipeline in IMU_PIPELINES:
        raise ConfigError(f'evalio pipeline {pipeline!r} needs an IMU, which these recordings '
                          f'do not have; LiDAR-only ones: {list(LIDAR_ONLY_PIPELINES)}')
    if pipeline not in LIDAR_ONLY_PIPELINES:
        raise ConfigError(f'unknown evalio pipeline {pipeline!r}; choose from '
                          f'{list(LIDAR_ONLY_PIPELINES)}')
    evalio_version()
    from evalio.pipelines import get_pipeline
    cls = get_pipeline(pipeline)
    if isinstance(cls, Exception):
        raise ConfigError(f'evalio {evalio_version()} has no pipeline {pipeline!r}: {cls}')
    return cls


def pipeline_params(pipeline: str, params: Mapping | None = None) -> dict:
    """evalio's defaults for `pipeline`, then VLP16_PARAMS, then `params`; validated."""
    cls = _pipeline_class(pipeline)
    defaults = cls.default_params()
    merged = {**defaults, **VLP16_PARAMS.get(pipeline, {}), **dict(params or {})}
    for key, value in merged.items():
        if key not in defaults:
            raise ConfigError(f'evalio {pipeline} has no parameter {key!r}; its parameters: '
                              f'{sorted(defaults)}')
        if type(value) is not type(defaults[key]):
            raise ConfigError(f'evalio {pipeline} parameter {key!r} must be '
                              f'{type(defaults[key]).__name__}, got {value!r}')
    if pipeline == 'genz' and merged['deskew']:
        raise ConfigError("evalio genz with deskew=True is refused: GenZ-ICP's deskew expects "
                          'per-point stamps normalised to [0, 1] while evalio passes seconds')
    return merged


def peer_metadata(pipeline: str, params: Mapping | None = None) -> dict:
    """What the bench records about a peer run: mode, pipeline version, effective params."""
    return {'registration_mode': f'evalio:{pipeline}',
            'pipeline_version': str(_pipeline_class(pipeline).version()),
            'evalio_version': evalio_version(),
            'pipeline_params': pipeline_params(pipeline, params)}


class EvalioOdometry:
    """One evalio LiDAR-only pipeline; `register_frame(scan)` like our pipeline's.

    A sweep for which the pipeline reports no pose (none of the six does that, but a pipeline
    may still be initialising) returns the previous pose (identity before the first one),
    stamped at the scan's header stamp.
    """

    def __init__(self, pipeline: str, params: Mapping | None = None,
                 lidar: LidarLayout = LidarLayout()):
        lidar.validate()
        self.name = pipeline
        self.params = pipeline_params(pipeline, params)
        self._cls = _pipeline_class(pipeline)
        self.version = str(self._cls.version())
        self.organised = pipeline in ORGANISED_PIPELINES
        self.deskews_to_end = pipeline in DESKEW_TO_END_PIPELINES and bool(
            self.params.get('deskew', False))
        self.lidar = lidar
        self._pipe = None
        self._T_world_sensor = np.eye(4)
        if lidar.n_columns is not None:
            self._start(lidar)

    def _start(self, lidar: LidarLayout) -> None:
        """Build and initialise the evalio pipeline (evalio's own order of calls)."""
        from evalio.types import SE3, ImuParams, LidarParams
        pipe = self._cls()
        unused = pipe.set_params(self.params)
        if unused:
            raise ConfigError(f'evalio {self.name} ignored parameters {dict(unused)}')
        # No IMU data: the six LiDAR-only pipelines ignore these two, evalio requires them.
        pipe.set_imu_params(ImuParams.up())
        pipe.set_lidar_params(LidarParams(
            num_rows=lidar.n_rows, num_columns=lidar.n_columns, min_range=lidar.min_range_m,
            max_range=lidar.max_range_m, rate=lidar.rate_hz, brand=lidar.brand,
            model=lidar.model))
        pipe.set_imu_T_lidar(SE3.identity())
        pipe.initialize()
        self.lidar = lidar
        self._pipe = pipe

    def pose_time_s(self, grid_times_s: np.ndarray) -> float:
        """Where in the sweep the reported pose holds, in seconds after the header stamp."""
        if not grid_times_s.size:
            return 0.0
        if self.deskews_to_end:
            return float(np.max(grid_times_s))
        if self.name == 'ct':
            return float(np.min(grid_times_s))
        return sweep_middle_offset_s(grid_times_s, self.lidar.period_s)

    def register_frame(self, scan: Scan) -> KissFrame:
        """Register one scan; its pose is stamped where the pipeline says it holds.

        `n_points_kept` counts the valid points handed to evalio: the pipelines' own crops and
        downsampling are not visible through evalio's interface.
        """
        if self._pipe is None:
            xyz, row, _, _ = _valid_rows(scan, self.lidar)
            self._start(self.lidar.with_columns(estimate_n_columns(xyz, row)))
        grid = scan_grid(scan, self.lidar)
        measurement = grid_to_measurement(scan.stamp_ns, grid, self.lidar, self.organised)
        self._pipe.add_lidar(measurement)
        estimates = self._pipe.saved_estimates()
        stamp_ns = int(scan.stamp_ns)
        if estimates:
            stamp, pose = estimates[-1]
            self._T_world_sensor = np.array(pose.to_mat(), dtype=float)
            stamp_ns = int(stamp.to_nsec()) + int(round(self.pose_time_s(grid.time_s)
                                                        * NS_PER_S))
        return KissFrame(stamp_ns=stamp_ns, T_world_sensor=self._T_world_sensor.copy(),
                         n_points_kept=int(grid.row.size))
