"""gft_odom as an evalio pipeline, so `evalio run` can put it beside the pipelines it wraps.

evalio's `Pipeline` is a nanobind class with a trampoline: a Python subclass overrides
`set_params`, `set_imu_params`, `set_lidar_params`, `set_imu_T_lidar`, `initialize`,
`add_imu`, `add_lidar` and `map`, plus the static `name`, `version`, `url` and
`default_params`; poses go back through `self.save(stamp, SE3)`. `register()` adds the class
to evalio's registry (`evalio.pipelines.get_pipeline('gft_odom')`); for the evalio CLI, point
`EVALIO_CUSTOM=gft_odom.bench.evalio_pipeline` at this module (evalio finds the class in the
module's namespace, so this module imports evalio at import time: nothing else imports it).

Parameters are our config's flattened keys (`'spectral.tau_m'`, `'registration.mode'`, ...)
of the sections that shape the odometry (pipeline, spectral, registration), with the defaults
of `GftOdomConfig()`; evalio parameters are scalars, so the band mask is the string "2,3".

Reading a LidarMeasurement back costs one list per field: evalio exposes the positions and
point stamps as Python lists (`to_vec_positions`, `to_vec_stamps`), which numpy turns into
arrays in C; no Python loop over points runs here, but nanobind builds one small object per
point (measured 15 ms for a 16 x 900 image, 14 400 points). Rows are not exposed as a list, so
the ring comes from the elevation angle (VLP-16 beams) when evalio's LiDAR parameters say 16
rows, else the scan has no ring (the spectral filter then warns once and uses the slice graph).
"""

from __future__ import annotations

import numpy as np

import gft_odom
from gft_odom.bench.peers import LidarLayout, rings_from_elevation
from gft_odom.config import GftOdomConfig, flatten, with_values
from gft_odom.core.types import Scan
from gft_odom.errors import ConfigError
from gft_odom.pipeline import OdometryPipeline

try:
    from evalio.pipelines import Pipeline, register_pipeline
    from evalio.types import SE3
except ImportError as exc:  # pragma: no cover - depends on the environment
    raise ImportError('gft_odom.bench.evalio_pipeline needs evalio: pip install evalio==0.6.1 '
                      "(or pip install -e '.[peers]')") from exc

PARAM_SECTIONS = ('pipeline', 'spectral', 'registration')


def default_params() -> dict[str, bool | int | float | str]:
    """evalio-style parameters: our config's odometry sections, tuples as 'a,b,c' strings."""
    params: dict[str, bool | int | float | str] = {}
    for key, value in flatten(GftOdomConfig()).items():
        if key.split('.', 1)[0] not in PARAM_SECTIONS:
            continue
        params[key] = ','.join(str(v) for v in value) if isinstance(value, tuple) else value
    return params


def config_from_params(params: dict) -> GftOdomConfig:
    """GftOdomConfig with evalio-style `params` set (tuple strings parsed back)."""
    defaults = flatten(GftOdomConfig())
    flat = {}
    for key, value in params.items():
        if isinstance(defaults.get(key), tuple) and isinstance(value, str):
            item = type(defaults[key][0]) if defaults[key] else int
            try:
                value = tuple(item(v) for v in value.split(',') if v.strip())
            except ValueError:
                raise ConfigError(f'{key}: expected comma-separated {item.__name__}s, '
                                  f'got {value!r}') from None
        flat[key] = value
    return with_values(GftOdomConfig(), flat)


def measurement_to_scan(mm, layout: LidarLayout | None) -> Scan:
    """An evalio LidarMeasurement as our Scan (zero points, evalio's missing returns, dropped).

    The ring is derived from the elevation for a 16-row sensor, else left None.
    """
    xyz = np.asarray(mm.to_vec_positions(), dtype=np.float64).reshape(-1, 3)
    t_s = np.asarray(mm.to_vec_stamps(), dtype=np.float64).reshape(-1)
    valid = np.isfinite(xyz).all(axis=1) & (np.abs(xyz).sum(axis=1) > 0.0)
    xyz, t_s = xyz[valid], t_s[valid]
    ring = None
    if layout is not None and layout.n_rows == LidarLayout().n_rows:
        try:
            ring = rings_from_elevation(xyz, layout).astype(np.uint16)
        except ConfigError:
            ring = None
    return Scan(stamp_ns=int(mm.stamp.to_nsec()), points_xyz=xyz, ring=ring,
                time_offset_s=t_s.astype(np.float32))


class GftOdomEvalio(Pipeline):
    """gft_odom's OdometryPipeline behind evalio's Pipeline interface (LiDAR only)."""

    def __init__(self):
        super().__init__()
        self._params = default_params()
        self._layout: LidarLayout | None = None
        self._lidar_T_imu = np.eye(4)
        self._odometry: OdometryPipeline | None = None
        self.n_rejected = 0

    @staticmethod
    def name() -> str:
        """Name in evalio's registry."""
        return 'gft_odom'

    @staticmethod
    def version() -> str:
        """gft_odom's version."""
        return gft_odom.__version__

    @staticmethod
    def url() -> str:
        """No public address yet: evalio's own placeholder."""
        return 'url-not-set'

    @staticmethod
    def default_params() -> dict[str, bool | int | float | str]:
        """Our config's odometry sections, flattened."""
        return default_params()

    def set_params(self, params):
        """Take the known parameters; return the unknown ones, as evalio expects."""
        known = default_params()
        self._params.update({k: v for k, v in params.items() if k in known})
        return {k: v for k, v in params.items() if k not in known}

    def set_imu_params(self, params) -> None:
        """LiDAR-only: IMU parameters are ignored."""

    def set_lidar_params(self, params) -> None:
        """Remember the sensor's rows (for the ring from elevation) and rate."""
        self._layout = LidarLayout(n_rows=int(params.num_rows),
                                   n_columns=int(params.num_columns),
                                   rate_hz=float(params.rate))

    def set_imu_T_lidar(self, T) -> None:
        """The extrinsic that turns our LiDAR pose into the IMU pose evalio records."""
        self._lidar_T_imu = np.linalg.inv(np.asarray(T.to_mat(), dtype=float))

    def initialize(self) -> None:
        """Build the odometry from the parameters (raises ConfigError on a bad one)."""
        self._odometry = OdometryPipeline(config_from_params(self._params),
                                          record_trajectory=False)

    def add_imu(self, mm) -> None:
        """LiDAR-only: IMU measurements are ignored."""

    def add_lidar(self, mm) -> None:
        """Register one sweep; save the IMU pose at the sweep stamp (none if rejected)."""
        if self._odometry is None:
            raise ConfigError('gft_odom evalio pipeline: call initialize() before add_lidar()')
        result = self._odometry.register_frame(measurement_to_scan(mm, self._layout))
        if not result.accepted:
            self.n_rejected += 1
            return
        T_world_imu = np.asarray(result.T_world_sensor, dtype=float) @ self._lidar_T_imu
        self.save(mm.stamp, SE3.from_mat(np.asfortranarray(T_world_imu)))

    def map(self):
        """No map is exported (evalio uses it for visualisation only)."""
        return {}


def register() -> type:
    """Add gft_odom to evalio's pipeline registry; returns the class."""
    register_pipeline(GftOdomEvalio)
    return GftOdomEvalio
