"""What varies from one simulated orchard drive to the next, drawn per seed within real ranges.

A fixed simulator flatters whatever registration was tuned on it. Each seed therefore draws
its own orchard (row and tree spacing, row length, tree size, canopy density and porosity,
missing and young trees), terrain (slope, undulation, roughness, wheel ruts), driving (cruise
speed, its change from lane to lane, acceleration, stops, headland turn radius down to pivot
turns, yaw-rate limit), sensor mount (height, tilt) and wind. `VARIATION_RANGES` is the one
place the ranges live; docs/benchmarks.md prints them from here, and every simulated bag
records its draws in its metadata.

Ranges (sources in brackets): citrus rows 4.5-7.5 m apart and trees 2.5-5.5 m apart in a row
[Florida/Spain citrus planting densities]; CitrusFarm's Jackal drove 0.3-2 m/s [Jackal top
speed 2 m/s]; a skid-steer robot turns from a headland arc of half the row spacing down to a
pivot on the spot; VLP-16 mounts 0.25-0.6 m above base_link with a few degrees of tilt.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

from gft_odom.errors import SimulationError

# name -> (low, high): every per-seed draw is uniform in its range.
VARIATION_RANGES: dict[str, tuple[float, float]] = {
    'row_spacing_m': (4.5, 7.5),
    'tree_spacing_m': (2.5, 5.5),
    'row_length_m': (40.0, 120.0),
    'missing_fraction': (0.0, 0.2),
    'young_fraction': (0.0, 0.25),
    'canopy_scale': (0.6, 1.2),
    'canopy_mean_free_path_m': (0.15, 0.9),
    'trunk_radius_scale': (0.7, 1.3),
    'slope': (0.0, 0.08),
    'undulation_std_m': (0.05, 0.4),
    'bump_std_m': (0.01, 0.06),
    'roughness_std_m': (0.003, 0.025),
    'rut_depth_m': (0.0, 0.06),
    'wind_amplitude_m': (0.0, 0.15),
    'cruise_speed_mps': (0.6, 1.8),
    'lane_speed_jitter': (0.0, 0.3),
    'max_accel_mps2': (0.3, 1.0),
    'stops_per_100m': (0.0, 1.5),
    'stop_duration_s': (1.0, 6.0),
    'max_yaw_rate_rps': (0.5, 1.2),
    'turn_radius_m': (0.05, 3.4),
    'mount_height_m': (0.25, 0.6),
    'mount_roll_rad': (-0.03, 0.03),
    'mount_pitch_rad': (-0.06, 0.06),
}
# The slowest a drive goes outside stops and pivots (the design's 0.3-2 m/s).
MIN_CRUISE_MPS = 0.3
MAX_SPEED_MPS = 2.0

# The stress family: drives no choice was made on, each quantity drawn OUTSIDE the range above
# (below or above it, either side at random where a range has two), and the canopy shaped by
# another model: closer and wider rows, hedgerows whose crowns close the gap between trees,
# denser and sparser foliage, the sensor mounted low or high, a faster robot, rougher ground,
# stronger wind, a wobblier drive. name -> the intervals a draw picks one of, then uniform.
STRESS_RANGES: dict[str, tuple[tuple[float, float], ...]] = {
    'row_spacing_m': ((3.5, 4.5), (7.5, 9.0)),
    'tree_spacing_m': ((1.5, 2.5), (5.5, 7.0)),
    'row_length_m': ((40.0, 120.0),),
    'missing_fraction': ((0.2, 0.35),),
    'young_fraction': ((0.25, 0.5),),
    'canopy_scale': ((0.45, 0.6), (1.2, 1.5)),
    'canopy_mean_free_path_m': ((0.05, 0.15), (0.9, 2.0)),
    'trunk_radius_scale': ((0.4, 0.7), (1.3, 1.8)),
    'slope': ((0.08, 0.15),),
    'undulation_std_m': ((0.4, 0.7),),
    'bump_std_m': ((0.06, 0.12),),
    'roughness_std_m': ((0.025, 0.05),),
    'rut_depth_m': ((0.06, 0.12),),
    'wind_amplitude_m': ((0.15, 0.35),),
    'cruise_speed_mps': ((1.8, 2.4),),
    'lane_speed_jitter': ((0.3, 0.5),),
    'max_accel_mps2': ((1.0, 2.0),),
    'stops_per_100m': ((1.5, 3.0),),
    'stop_duration_s': ((1.0, 6.0),),
    'max_yaw_rate_rps': ((1.2, 2.0),),
    'turn_radius_m': ((0.05, 3.4),),
    'mount_height_m': ((0.15, 0.25), (0.6, 1.0)),
    'mount_roll_rad': ((-0.06, -0.03), (0.03, 0.06)),
    'mount_pitch_rad': ((-0.12, -0.06), (0.06, 0.12)),
    # The skid-steer wobble (SimConfig: 0.05 m and 0.02 rad in the varied family).
    'lateral_wobble_m': ((0.1, 0.25),),
    'yaw_wobble_rad': ((0.04, 0.1),),
}
# How a crown is shaped: one porous ellipsoid (the varied family); a cluster of smaller lobes
# (lumpy, gaps between them); crowns stretched along the row until they meet (a hedgerow).
CANOPY_MODELS = ('ellipsoid', 'lumpy', 'hedgerow')
FAMILIES = ('varied', 'stress')


@dataclass(frozen=True)
class OrchardVariation:
    """One draw of every varied quantity; `nominal()` is the fixed simulator of before."""

    row_spacing_m: float
    tree_spacing_m: float
    row_length_m: float
    missing_fraction: float
    young_fraction: float
    canopy_scale: float
    canopy_mean_free_path_m: float
    trunk_radius_scale: float
    slope: float
    undulation_std_m: float
    bump_std_m: float
    roughness_std_m: float
    rut_depth_m: float
    wind_amplitude_m: float
    cruise_speed_mps: float
    lane_speed_jitter: float
    max_accel_mps2: float
    stops_per_100m: float
    stop_duration_s: float
    max_yaw_rate_rps: float
    turn_radius_m: float
    mount_height_m: float
    mount_roll_rad: float
    mount_pitch_rad: float
    seed: int = -1  # -1: not drawn (nominal)
    # The stress family's own quantities; the varied family leaves them at these values.
    family: str = 'varied'
    canopy_model: str = 'ellipsoid'
    lateral_wobble_m: float | None = None  # None: SimConfig's
    yaw_wobble_rad: float | None = None

    @classmethod
    def draw(cls, seed: int, family: str = 'varied') -> 'OrchardVariation':
        """Uniform draws within `VARIATION_RANGES` (family 'varied') or outside them
        (`STRESS_RANGES`, family 'stress'), deterministic per seed and family."""
        if family == 'stress':
            return cls._draw_stress(seed)
        if family != 'varied':
            raise SimulationError(f'unknown variation family {family!r}; choose from '
                                  f'{FAMILIES}')
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7A41A7]))
        values = {name: float(rng.uniform(lo, hi)) for name, (lo, hi) in
                  VARIATION_RANGES.items()}
        # Half the seeds turn on the spot or nearly (skid-steer pivots), half on arcs.
        if rng.random() < 0.5:
            values['turn_radius_m'] = float(rng.uniform(0.05, 0.5))
        return cls(**values, seed=int(seed))

    @classmethod
    def _draw_stress(cls, seed: int) -> 'OrchardVariation':
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x57E55]))
        values = {}
        for name, intervals in STRESS_RANGES.items():
            lo, hi = intervals[int(rng.integers(len(intervals)))]
            values[name] = float(rng.uniform(lo, hi))
        if rng.random() < 0.5:  # half the seeds pivot, as in the varied family
            values['turn_radius_m'] = float(rng.uniform(0.05, 0.5))
        model = CANOPY_MODELS[int(rng.integers(len(CANOPY_MODELS)))]
        return cls(**values, seed=int(seed), family='stress', canopy_model=model)

    @classmethod
    def nominal(cls) -> 'OrchardVariation':
        """The middle of the old fixed simulator's ranges (no per-seed variation)."""
        return cls(row_spacing_m=6.25, tree_spacing_m=4.0, row_length_m=60.0,
                   missing_fraction=0.1, young_fraction=0.0, canopy_scale=1.0,
                   canopy_mean_free_path_m=0.35, trunk_radius_scale=1.0, slope=0.015,
                   undulation_std_m=0.25, bump_std_m=0.04, roughness_std_m=0.01,
                   rut_depth_m=0.0, wind_amplitude_m=0.04, cruise_speed_mps=1.0,
                   lane_speed_jitter=0.0, max_accel_mps2=0.5, stops_per_100m=0.0,
                   stop_duration_s=2.0, max_yaw_rate_rps=0.8, turn_radius_m=3.0,
                   mount_height_m=0.38, mount_roll_rad=0.0, mount_pitch_rad=0.0)

    def as_dict(self) -> dict:
        """JSON-ready values, for the bag's metadata."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> 'OrchardVariation':
        """Inverse of `as_dict` (unknown keys are ignored, for older metadata)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})
