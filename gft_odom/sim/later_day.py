"""Another day in the same orchard: the trunks, posts, pipes, ground and rows of the map day,
the canopy of a later one.

Between two visits of a block what changes is the canopy. A crown grows back after pruning
(regrowth "about 30 cm long" a few months after a cut [DPIRD Western Australia, Citrus
pruning]); side hedging cuts the row faces back so the inter-row stays open (hedging begins
"when the canopies of adjacent rows are about 7 to 8 feet apart across the middle" [Sauls,
Texas A&M Citrus pruning, L2308]), usually tilted 10-25 degrees from vertical [Zekri, UF/IFAS
HS1267]; leaf density changes with flushes and fruit, and the wind is that day's. A later day
here is one of two kinds, drawn per (block seed, day):

- `grown`: every crown's radii scaled by 1.10-1.30 (regrowth of 0.15-0.5 m on 1.2-2.2 m radii)
  and leaf density up (mean free path x 0.6-0.9);
- `hedged`: the row faces cut back (across-row radius x 0.6-0.8), the tops cut (height x
  0.85-1.0), sparser foliage where it was cut (mean free path x 1.1-1.6).

Each tree varies around the block's change by a few percent; the wind is drawn again from the
varied family's range. `same` is a later day whose canopy is that of the map day (only the
wind and the route differ): the control for what the changed canopy costs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from gft_odom.errors import SimulationError
from gft_odom.sim.motion import (
    ROUTES,
    make_route_motion,
    route_driving,
    route_lane_count,
    route_lanes,
)
from gft_odom.sim.orchard import Canopies, Orchard
from gft_odom.sim.simulator import ScanSimulator, SimConfig
from gft_odom.sim.variation import VARIATION_RANGES, OrchardVariation

CHANGES = ('same', 'grown', 'hedged', 'changed')  # changed: grown or hedged, drawn
# Per-tree spread around the block's change (relative std of each radius).
TREE_SPREAD = 0.05


@dataclass(frozen=True)
class CanopyChange:
    """How a later day's canopy differs from the map day's (scales of the crown radii along
    the row, across it and vertically; of the mean free path in a crown) and that day's wind."""

    kind: str
    along_scale: float
    across_scale: float
    vertical_scale: float
    mean_free_path_scale: float
    wind_amplitude_m: float
    seed: int
    day: int

    @classmethod
    def draw(cls, seed: int, day: int, kind: str = 'changed') -> 'CanopyChange':
        """The change of block `seed` on `day` (>= 1), deterministic per (seed, day, kind)."""
        if kind not in CHANGES:
            raise SimulationError(f'canopy change must be one of {CHANGES}, got {kind!r}')
        if int(day) < 1:
            raise SimulationError(f'a later day is day 1 or later, got {day}')
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(day), 0xDA7]))
        wind = float(rng.uniform(*VARIATION_RANGES['wind_amplitude_m']))
        drawn = 'grown' if rng.random() < 0.5 else 'hedged'
        kind = drawn if kind == 'changed' else kind
        if kind == 'same':
            scales = (1.0, 1.0, 1.0, 1.0)
        elif kind == 'grown':
            grow = float(rng.uniform(1.10, 1.30))
            scales = (grow, grow, grow, float(rng.uniform(0.6, 0.9)))
        else:
            scales = (1.0, float(rng.uniform(0.6, 0.8)), float(rng.uniform(0.85, 1.0)),
                      float(rng.uniform(1.1, 1.6)))
        return cls(kind, *scales, wind_amplitude_m=wind, seed=int(seed), day=int(day))


def orchard_on_day(orchard: Orchard, change: CanopyChange) -> Orchard:
    """`orchard` with its canopy as `change` has it; everything else is the same object."""
    if change.kind == 'same':
        return orchard
    rng = np.random.default_rng(np.random.SeedSequence([change.seed, change.day, 0xC40]))
    crowns = orchard.canopies
    n = len(crowns)
    scale = np.array([change.along_scale, change.across_scale, change.vertical_scale])
    radii = crowns.radii_m * scale * (1.0 + TREE_SPREAD * rng.standard_normal((n, 3)))
    radii = np.maximum(radii, 0.1)
    # A crown never closes the lane the robot drives (as generated: half the spacing - 1 m).
    radii[:, 1] = np.minimum(radii[:, 1], np.maximum(crowns.radii_m[:, 1],
                                                     0.5 * orchard.row_spacing_m - 1.0))
    # A crown keeps its skirt where it was: its centre moves with its vertical radius.
    centre = crowns.centre_m.copy()
    centre[:, 2] += radii[:, 2] - crowns.radii_m[:, 2]
    canopies = Canopies(centre, radii, crowns.sway_amplitude, crowns.sway_frequency_hz,
                        crowns.sway_phase_rad)
    return replace(orchard, canopies=canopies)


SECONDS_PER_DAY = 86400.0


def simulate_day(config: SimConfig, seed: int, map_route: str, day: int = 0,
                 route: str | None = None, change: str = 'changed',
                 map_distance_m: float = 280.0, distance_m: float | None = None
                 ) -> tuple[ScanSimulator, CanopyChange | None]:
    """The simulator of one day in block `seed`: day 0 is the map day (`map_route` over about
    `map_distance_m`, exactly `ScanSimulator.for_drive`'s varied drive); a later day drives
    `route` (default: the map day's) over about `distance_m` in the same block, with the
    canopy `change` of that day, its own driving and noise, stamped `day` days later. Every
    day's ground truth is in the same world frame."""
    map_sim, variation = ScanSimulator.for_drive(config, map_route, seed,
                                                 distance_m=map_distance_m, vary=True)
    if int(day) == 0:
        return map_sim, None
    route = route or map_route
    if route not in ROUTES:
        raise SimulationError(f'a later day drives a route, one of {ROUTES}; got {route!r}')
    if (route == 'edge_lawnmower') != (map_route == 'edge_lawnmower'):
        raise SimulationError('the edge route and the others have different headlands: '
                              'map and repeat a block with both or neither')
    canopy = CanopyChange.draw(seed, day, change)
    orchard = orchard_on_day(map_sim.orchard, canopy)
    day_seed = int(seed) * 1000 + int(day)
    driving = route_driving(route, OrchardVariation.draw(day_seed))
    # The block's own layout; the day's speeds, stops and turns.
    driving = replace(driving, row_length_m=variation.row_length_m)
    # Lanes the map day drove (the map covers them).
    most_lanes = max(route_lanes(map_route, route_lane_count(map_route, map_distance_m,
                                                             variation.row_length_m)))
    n_lanes = route_lane_count(route, distance_m or map_distance_m, variation.row_length_m)
    n_lanes = min(n_lanes, max(lane for lane in range(1, most_lanes + 2)
                               if max(route_lanes(route, lane)) <= most_lanes))
    day_config = replace(
        map_sim.config, speed_mps=driving.cruise_speed_mps,
        canopy_mean_free_path_m=map_sim.config.canopy_mean_free_path_m
        * canopy.mean_free_path_scale,
        wind_amplitude_m=canopy.wind_amplitude_m,
        start_time_s=map_sim.config.start_time_s + int(day) * SECONDS_PER_DAY)
    motion = make_route_motion(orchard, route, n_lanes, driving, day_seed,
                               day_config.lateral_wobble_m, day_config.yaw_wobble_rad)
    return ScanSimulator(orchard, motion, day_config, day_seed), canopy
