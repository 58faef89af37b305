"""One source of truth for every parameter default.

Each component owns a frozen dataclass of its parameters (`SpectralConfig`,
`RegistrationConfig`, ...); `GftOdomConfig` groups them into the sections that the ROS params
files (`config/*.yaml`, `/**: ros__parameters: <section>: <key>`) and the node's parameter names
(`<section>.<key>`) use. Nothing here reads YAML: `gft_odom.io.params_file` does.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from dataclasses import dataclass, field
from typing import Any

from gft_odom.core.metrics import MetricsConfig
from gft_odom.core.registration import RegistrationConfig
from gft_odom.core.spectral.filter import SpectralConfig
from gft_odom.errors import ConfigError
from gft_odom.io.ground_truth import GroundTruthConfig


@dataclass(frozen=True)
class PipelineConfig:
    """The per-scan loop: range crop, then the spectral filter (or not), then registration."""

    # Off gives the unfiltered baseline with the same registration, for fair comparisons.
    use_spectral_filter: bool = True

    # The Jackal's own body and the operator walking next to it return points inside ~0.5 m.
    min_range_m: float = 0.5
    # VLP-16 returns beyond ~60 m in an orchard are sparse canopy hits that only add noise.
    max_range_m: float = 60.0
    # A VLP-16 sweep has ~29 k points; a bigger cloud (another sensor, a driver glitch) is
    # thinned by a regular stride to this many so one scan cannot stall the node for seconds.
    max_points_per_scan: int = 120000
    # A control for ablations only: each scan's frequencies are permuted among its points
    # before registration (their distribution kept, what they tell about each point lost).
    shuffle_frequencies: bool = False
    # Which permutation the control draws; a few seeds give the control's spread, against
    # which the frequency's choice is judged.
    shuffle_seed: int = 0

    def validate(self) -> None:
        """Raise ConfigError naming the first value that cannot work."""
        if not (self.min_range_m >= 0.0 and math.isfinite(self.min_range_m)):
            raise ConfigError(f'min_range_m must be >= 0, got {self.min_range_m}')
        if not self.max_range_m > self.min_range_m:
            raise ConfigError(
                f'max_range_m ({self.max_range_m}) must be > min_range_m ({self.min_range_m})')
        if self.shuffle_seed < 0:
            raise ConfigError(f'shuffle_seed must be >= 0, got {self.shuffle_seed}')
        if self.max_points_per_scan < 100:
            raise ConfigError(
                f'max_points_per_scan must be >= 100, got {self.max_points_per_scan}')


# node.input_reliability: adaptive like rosbag2, or forced.
INPUT_RELIABILITIES = ('auto', 'reliable', 'best_effort')


@dataclass(frozen=True)
class NodeConfig:
    """ROS-facing settings of `filter_odom_node` (frames, extrinsic, publishing, lag policy)."""

    odom_frame: str = 'odom'
    base_frame: str = 'base_link'
    # Pose of the LiDAR in base_link (Jackal with the VLP-16 on its top plate, REP 103 axes).
    base_to_sensor_xyz_m: tuple[float, ...] = (0.04, 0.0, 0.38)
    base_to_sensor_rpy_rad: tuple[float, ...] = (0.0, 0.0, 0.0)
    publish_tf: bool = True
    publish_filtered_points: bool = True
    # Bounded so a long run does not grow memory without limit.
    path_max_length: int = 5000
    # A scan older than this when its turn comes (processing lagged) is dropped and counted.
    max_scan_age_s: float = 0.5
    # Depth of the sensor-data subscription. 1 = always the newest sweep: a lagging node skips
    # sweeps instead of working through a queue of old ones (latency stays one processing
    # time); the skipped sweeps are counted from the gaps between stamps (`missed`).
    input_queue_depth: int = 1
    # Reliability of the input subscription: auto (like rosbag2: reliable when every publisher
    # on the topic is reliable, so the stock velodyne driver is lossless without a Fast DDS
    # profile; best effort when any is best effort; re-checked as publishers come and go),
    # reliable or best_effort. A qos_overrides reliability for the topic forces it too.
    input_reliability: str = 'auto'
    # Folder where `~/save_map` writes the map (binary PCD) and the trajectory (TUM); `~` is
    # expanded, a relative path is relative to the node's working directory.
    save_map_dir: str = '~/.ros/gft_odom_maps'
    # `/diagnostics` WARNs when the weakest translation direction of the match has less than
    # this fraction of the strongest one's information (0 = never): motion along it leans on
    # the motion prior. Measured in the simulator: along an orchard row ~0.3 (x), continuous
    # hedges ~0.1, open ground ~0.002.
    weak_direction_warn_ratio: float = 0.02

    def validate(self) -> None:
        """Raise ConfigError naming the first value that cannot work."""
        for name in ('odom_frame', 'base_frame'):
            value = getattr(self, name)
            if not value or value.startswith('/'):
                raise ConfigError(f'{name} must be a non-empty frame id without a leading "/", '
                                  f'got {value!r}')
        if self.odom_frame == self.base_frame:
            raise ConfigError('odom_frame and base_frame must differ')
        for name in ('base_to_sensor_xyz_m', 'base_to_sensor_rpy_rad'):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ConfigError(f'{name} must be 3 finite numbers, got {list(value)}')
        if self.path_max_length < 1:
            raise ConfigError(f'path_max_length must be >= 1, got {self.path_max_length}')
        if not self.max_scan_age_s > 0.0:
            raise ConfigError(f'max_scan_age_s must be > 0, got {self.max_scan_age_s}')
        if not 1 <= self.input_queue_depth <= 100:
            raise ConfigError(f'input_queue_depth must be in 1..100, got {self.input_queue_depth}')
        if self.input_reliability not in INPUT_RELIABILITIES:
            raise ConfigError(f'input_reliability must be one of {", ".join(INPUT_RELIABILITIES)}'
                              f', got {self.input_reliability!r}')
        if not self.save_map_dir.strip():
            raise ConfigError('save_map_dir must be a folder path, got an empty string')
        if not 0.0 <= self.weak_direction_warn_ratio < 1.0:
            raise ConfigError(f'weak_direction_warn_ratio must be in [0, 1), got '
                              f'{self.weak_direction_warn_ratio}')


@dataclass(frozen=True)
class LocalisationConfig:
    """Localisation in a map an earlier drive saved (`~/save_map`, `replay --save-map`)."""

    # The map (PCD in its run's odom frame); empty: odometry only. `~` is expanded. Changing
    # it at run time loads the new map (`~/load_map` loads it again).
    map_file: str = ''
    # Where base_link is in the map at the first scan after the map is loaded: x (m), y (m),
    # yaw (rad). `/initialpose` (RViz's "2D Pose Estimate") sets it again at any time.
    initial_pose_xy_yaw: tuple[float, ...] = (0.0, 0.0, 0.0)
    # The frame of the map (REP 105: localisation publishes map -> odom).
    map_frame: str = 'map'

    def validate(self) -> None:
        """Raise ConfigError naming the first value that cannot work."""
        if len(self.initial_pose_xy_yaw) != 3 or not all(
                math.isfinite(v) for v in self.initial_pose_xy_yaw):
            raise ConfigError(f'initial_pose_xy_yaw must be 3 finite numbers (x m, y m, yaw '
                              f'rad), got {list(self.initial_pose_xy_yaw)}')
        if not self.map_frame or self.map_frame.startswith('/'):
            raise ConfigError(f'map_frame must be a non-empty frame id without a leading "/", '
                              f'got {self.map_frame!r}')


@dataclass(frozen=True)
class GftOdomConfig:
    """All parameters, grouped by section as in `config/*.yaml`."""

    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    spectral: SpectralConfig = field(default_factory=SpectralConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    node: NodeConfig = field(default_factory=NodeConfig)
    localisation: LocalisationConfig = field(default_factory=LocalisationConfig)
    ground_truth: GroundTruthConfig = field(default_factory=GroundTruthConfig)
    evaluation: MetricsConfig = field(default_factory=MetricsConfig)

    def validate(self) -> None:
        """Validate every section; the error names the section."""
        if self.localisation.map_frame in (self.node.odom_frame, self.node.base_frame):
            raise ConfigError('localisation.map_frame must differ from node.odom_frame and '
                              'node.base_frame')
        for section in dataclasses.fields(self):
            try:
                getattr(self, section.name).validate()
            except ConfigError as exc:
                text = str(exc)
                if not text.startswith(f'{section.name}.'):
                    text = f'{section.name}: {text}'
                raise ConfigError(text) from None


def _field_types(cls) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def flatten(config: GftOdomConfig) -> dict[str, Any]:
    """`{'spectral.tau_m': 0.5, ...}`: the node's parameter names and their values."""
    flat: dict[str, Any] = {}
    for section in dataclasses.fields(config):
        values = getattr(config, section.name)
        for f in dataclasses.fields(values):
            flat[f'{section.name}.{f.name}'] = getattr(values, f.name)
    return flat


def parameter_types() -> dict[str, Any]:
    """Type of every flattened parameter, from the dataclass annotations."""
    types: dict[str, Any] = {}
    for section, section_type in _field_types(GftOdomConfig).items():
        for name, t in _field_types(section_type).items():
            types[f'{section}.{name}'] = t
    return types


def coerce_value(key: str, value: Any, expected: Any) -> Any:
    """Check `value` against the annotated type; ints are accepted for floats offline."""
    origin = typing.get_origin(expected)
    if origin is tuple:
        item_type = typing.get_args(expected)[0]
        if isinstance(value, (str, bytes)) or not hasattr(value, '__iter__'):
            raise ConfigError(f'{key}: expected a list of {item_type.__name__}, got {value!r}')
        return tuple(coerce_value(key, v, item_type) for v in value)
    if expected is bool:
        if isinstance(value, bool):
            return value
    elif expected is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif expected is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif expected is str:
        if isinstance(value, str):
            return value
    raise ConfigError(f'{key}: expected {getattr(expected, "__name__", expected)}, '
                      f'got {value!r} ({type(value).__name__})')


def with_values(config: GftOdomConfig, flat: dict[str, Any]) -> GftOdomConfig:
    """A copy of `config` with the flattened `flat` values set, type-checked and validated."""
    types = parameter_types()
    per_section: dict[str, dict[str, Any]] = {}
    for key, value in flat.items():
        if key not in types:
            close = difflib.get_close_matches(key, list(types), n=3)
            hint = f' (did you mean {", ".join(close)}?)' if close else ''
            raise ConfigError(f'unknown parameter {key!r}{hint}')
        section, name = key.split('.', 1)
        per_section.setdefault(section, {})[name] = coerce_value(key, value, types[key])
    sections = {
        name: dataclasses.replace(getattr(config, name), **values)
        for name, values in per_section.items()
    }
    new = dataclasses.replace(config, **sections)
    new.validate()
    return new
