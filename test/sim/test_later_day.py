"""A later day in the same block: what stays, what changes, and where it drives."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.errors import SimulationError
from gft_odom.sim.later_day import SECONDS_PER_DAY, CanopyChange, orchard_on_day, simulate_day
from gft_odom.sim.simulator import SimConfig

CONFIG = SimConfig(azimuth_step_deg=1.0)


@pytest.fixture(scope='module')
def days():
    map_day, _ = simulate_day(CONFIG, 7, 'lawnmower', map_distance_m=120.0)
    grown = [simulate_day(CONFIG, 7, 'lawnmower', day=1, route='spiral', change=kind,
                          map_distance_m=120.0, distance_m=120.0)
             for kind in ('same', 'grown', 'hedged')]
    return map_day, grown


def test_trunks_posts_ground_and_rows_stay_the_canopy_changes(days):
    map_day, later = days
    for sim, change in later:
        o0, o1 = map_day.orchard, sim.orchard
        np.testing.assert_array_equal(o0.cylinders.base_m, o1.cylinders.base_m)
        np.testing.assert_array_equal(o0.row_v_m, o1.row_v_m)
        np.testing.assert_array_equal(o0.ground.z_m, o1.ground.z_m)
        ratio = o1.canopies.radii_m / o0.canopies.radii_m
        if change.kind == 'same':
            np.testing.assert_array_equal(ratio, 1.0)
        elif change.kind == 'grown':
            assert 1.05 < np.median(ratio) < 1.35
        else:  # hedged: the row faces cut back, the length along the row kept
            assert 0.55 < np.median(ratio[:, 1]) < 0.85
            assert 0.9 < np.median(ratio[:, 0]) < 1.1


def test_a_later_day_drives_its_own_route_a_day_later_in_the_mapped_lanes(days):
    map_day, later = days
    sim, change = later[0]
    assert sim.start_ns - map_day.start_ns == int(SECONDS_PER_DAY * 1e9)
    assert sim.motion.duration_s != map_day.motion.duration_s
    # Every pose of the later day lies within the map day's area, headlands included.
    t0 = np.linspace(0.0, map_day.motion.duration_s, 400)
    t1 = np.linspace(0.0, sim.motion.duration_s, 400)
    xy0 = map_day.motion.poses(t0)[:, :2, 3]
    xy1 = sim.motion.poses(t1)[:, :2, 3]
    nearest = np.min(np.linalg.norm(xy1[:, None] - xy0[None], axis=2), axis=1)
    assert nearest.max() < 8.0


def test_the_same_day_drawn_twice_is_the_same_and_bad_days_are_refused():
    assert CanopyChange.draw(3, 2) == CanopyChange.draw(3, 2)
    assert CanopyChange.draw(3, 2, 'changed').kind in ('grown', 'hedged')
    with pytest.raises(SimulationError):
        CanopyChange.draw(3, 0)
    with pytest.raises(SimulationError):
        CanopyChange.draw(3, 1, 'flooded')


def test_a_changed_canopy_changes_what_the_lidar_sees(days):
    map_day, later = days
    same, _ = later[0]
    hedged, _ = later[2]
    surface_same = same.scan(20).surface
    surface_hedged = hedged.scan(20).surface
    assert not np.array_equal(surface_same, surface_hedged)
    assert orchard_on_day(map_day.orchard, CanopyChange.draw(7, 1, 'same')) is map_day.orchard
