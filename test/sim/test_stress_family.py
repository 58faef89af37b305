"""The stress family: drives drawn outside every range of the varied family, with other canopy
models, so that no choice made on the varied drives is flattered by them."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from gft_odom.errors import SimulationError
from gft_odom.sim.orchard import LUMP_LOBES, generate_orchard
from gft_odom.sim.simulator import ScanSimulator, SimConfig
from gft_odom.sim.variation import (
    CANOPY_MODELS,
    STRESS_RANGES,
    VARIATION_RANGES,
    OrchardVariation,
)

# Quantities the stress family leaves in the varied range: the route's length, how long a stop
# lasts and the turn radius (pivots to arcs already span what a robot does).
SHARED = {'row_length_m', 'stop_duration_s', 'turn_radius_m'}


def test_stress_draws_lie_outside_every_varied_range():
    draws = [OrchardVariation.draw(seed, 'stress') for seed in range(300, 340)]
    for name, (lo, hi) in VARIATION_RANGES.items():
        values = np.array([getattr(v, name) for v in draws])
        if name in SHARED:
            assert ((values >= lo) & (values <= hi)).all(), name
        else:
            assert ((values <= lo) | (values >= hi)).all(), name
    # Both sides of a two-sided range are drawn, and every canopy model.
    spacing = np.array([v.row_spacing_m for v in draws])
    assert (spacing < 4.5).any() and (spacing > 7.5).any()
    assert {v.canopy_model for v in draws} == set(CANOPY_MODELS)
    assert all(v.family == 'stress' and v.lateral_wobble_m >= 0.1 for v in draws)


def test_the_varied_family_draws_what_it_always_drew():
    a, b = OrchardVariation.draw(201), OrchardVariation.draw(201, 'varied')
    assert a == b and a.family == 'varied' and a.canopy_model == 'ellipsoid'
    assert a.lateral_wobble_m is None  # the SimConfig's wobble, as before
    assert OrchardVariation.draw(301, 'stress') == OrchardVariation.draw(301, 'stress')
    assert OrchardVariation.from_dict(OrchardVariation.draw(301, 'stress').as_dict()) == \
        OrchardVariation.draw(301, 'stress')
    with pytest.raises(SimulationError, match='family'):
        OrchardVariation.draw(1, 'gentle')


def _with_model(model: str) -> OrchardVariation:
    from dataclasses import replace
    return replace(OrchardVariation.draw(7), canopy_model=model)


def test_canopy_models_shape_the_crowns():
    base = generate_orchard(7, n_rows=3, variation=_with_model('ellipsoid'))
    lumpy = generate_orchard(7, n_rows=3, variation=_with_model('lumpy'))
    hedge = generate_orchard(7, n_rows=3, variation=_with_model('hedgerow'))
    n_trees = len(base.canopies)
    # The rest of the orchard is that of the same seed.
    np.testing.assert_array_equal(lumpy.cylinders.base_m, base.cylinders.base_m)
    np.testing.assert_array_equal(hedge.boxes.centre_m, base.boxes.centre_m)
    # Lumpy: lobes within their crown, smaller than it.
    assert len(lumpy.canopies) == LUMP_LOBES * n_trees
    parent = np.repeat(np.arange(n_trees), LUMP_LOBES)
    assert (lumpy.canopies.radii_m < base.canopies.radii_m[parent]).all()
    inside = np.abs(lumpy.canopies.centre_m - base.canopies.centre_m[parent]) / \
        base.canopies.radii_m[parent]
    assert (inside <= 0.45 + 1e-9).all()
    np.testing.assert_array_equal(lumpy.canopy_index_of_tree, np.arange(n_trees) * LUMP_LOBES)
    # Hedgerow: each crown reaches past half the tree spacing, so neighbours overlap.
    assert (hedge.canopies.radii_m[:, 0] > 0.5 * base.tree_spacing_m).all()
    np.testing.assert_array_equal(hedge.canopies.radii_m[:, 1:], base.canopies.radii_m[:, 1:])


def test_a_stress_drive_is_faster_and_wobblier_than_the_jackal():
    sim, variation = ScanSimulator.for_drive(SimConfig(azimuth_step_deg=2.0), 'lawnmower', 305,
                                             distance_m=120.0, vary=True, family='stress')
    assert variation.family == 'stress' and variation.cruise_speed_mps > 2.0
    assert sim.config.lateral_wobble_m == variation.lateral_wobble_m
    assert sim.config.base_to_sensor_xyz_m[2] == variation.mount_height_m
    t = np.arange(0.0, sim.motion.duration_s, 0.1)
    speed = np.linalg.norm(np.diff(sim.motion.poses(t)[:, :2, 3], axis=0), axis=1) / 0.1
    assert speed.max() > 2.0  # not capped at the Jackal's 2 m/s


def test_docs_list_the_stress_ranges():
    page = (Path(__file__).resolve().parents[2] / 'docs' / 'benchmarks.md').read_text()
    # | `name` | the stress family's intervals | the varied family's range |
    interval = r'-?[\d.]+ to -?[\d.]+'
    rows = re.findall(rf'^\| `(\w+)` \| ({interval}(?: or {interval})*) \| [^|]+ \|$',
                      page, re.M)
    documented = {name: tuple(tuple(float(v) for v in part.split(' to '))
                              for part in text.split(' or ')) for name, text in rows}
    assert documented == STRESS_RANGES
