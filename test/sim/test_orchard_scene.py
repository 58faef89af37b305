"""The orchard generator: determinism, the design's ranges, and a sane layout."""

from __future__ import annotations

import numpy as np
import pytest

from gft_odom.errors import SimulationError
from gft_odom.sim.orchard import (
    BUILDING,
    PIPE,
    POST,
    TRUNK,
    VEHICLE,
    Heightfield,
    generate_orchard,
)


@pytest.fixture(scope='module')
def orchard():
    return generate_orchard(7, n_rows=6, row_length_m=50.0)


def _arrays(o):
    return [o.ground.z_m, o.cylinders.base_m, o.cylinders.axis, o.cylinders.radius_m,
            o.canopies.centre_m, o.canopies.radii_m, o.boxes.centre_m, o.row_v_m]


def test_same_seed_same_orchard(orchard):
    again = generate_orchard(7, n_rows=6, row_length_m=50.0)
    for a, b in zip(_arrays(orchard), _arrays(again)):
        np.testing.assert_array_equal(a, b)


def test_different_seeds_differ_in_layout_not_only_noise(orchard):
    others = [generate_orchard(s, n_rows=6, row_length_m=50.0, margin_m=5.0) for s in (8, 9)]
    for other in others:
        assert other.row_spacing_m != orchard.row_spacing_m
        assert other.tree_spacing_m != orchard.tree_spacing_m
        assert other.heading_rad != orchard.heading_rad
    counts = {len(o.canopies) for o in [orchard] + others}
    spacings = [o.tree_spacing_m for o in [orchard] + others]
    assert len(counts) > 1 or np.ptp(spacings) > 0.1


def test_ranges_from_the_design(orchard):
    cyl = orchard.cylinders
    trunk = cyl.surface == TRUNK
    assert 5.5 <= orchard.row_spacing_m <= 7.0
    assert 3.0 <= orchard.tree_spacing_m <= 5.0
    assert np.all((cyl.radius_m[trunk] >= 0.06) & (cyl.radius_m[trunk] <= 0.15))
    assert np.all((cyl.length_m[trunk] >= 0.4) & (cyl.length_m[trunk] <= 0.9))
    lean = np.degrees(np.arccos(cyl.axis[trunk, 2]))
    assert 0.5 < lean.mean() < 8.0 and lean.max() < 20.0
    radii = orchard.canopies.radii_m
    assert np.all((radii[:, 0] >= 1.2) & (radii[:, 0] <= 2.2))
    assert np.all(radii[:, 1] <= 2.2) and np.all(radii[:, 1] <= 0.5 * orchard.row_spacing_m - 1.0)
    assert np.all((radii[:, 2] >= 1.0) & (radii[:, 2] <= 2.0))
    # Posts, pipes and at least a building and a vehicle exist.
    assert (cyl.surface == POST).sum() == 2 * len(orchard.row_v_m)
    assert (cyl.surface == PIPE).sum() > 0
    assert (orchard.boxes.surface == BUILDING).sum() == 1
    assert (orchard.boxes.surface == VEHICLE).sum() >= 1


def test_some_trees_are_missing():
    fractions = []
    for seed in range(4):
        o = generate_orchard(seed, n_rows=8, row_length_m=80.0, margin_m=5.0)
        n_grid = len(o.row_v_m) * (int(round((o.row_end_u_m - o.row_start_u_m)
                                             / o.tree_spacing_m)) + 1)
        fractions.append(1.0 - len(o.canopies) / n_grid)
    assert 0.04 < np.mean(fractions) < 0.17


def test_canopies_skirt_low_over_the_trunks(orchard):
    cyl, can = orchard.cylinders, orchard.canopies
    trunk = np.nonzero(cyl.surface == TRUNK)[0]
    top = cyl.base_m[trunk] + cyl.axis[trunk] * cyl.length_m[trunk, None]
    bottom = can.centre_m[:, 2] - can.radii_m[:, 2]
    ground = orchard.ground.height(can.centre_m[:, 0], can.centre_m[:, 1])
    assert np.all(bottom - ground >= 0.15)
    # The crown's lowest point is below the trunk top for most trees: trunks partly hidden.
    assert np.mean(bottom < top[:, 2]) > 0.7
    centre_height = can.centre_m[:, 2] - ground
    assert 1.3 < np.median(centre_height) < 2.7


def test_ground_is_gentle_with_bumps(orchard):
    g = orchard.ground
    gx, gy = np.gradient(g.z_m, g.resolution_m)
    slope = np.hypot(gx, gy)
    assert np.median(slope) < 0.1
    # Bumps of a few cm: height differences over one metre are centimetres, not zero.
    step = int(round(1.0 / g.resolution_m))
    d1 = g.z_m[step:, :] - g.z_m[:-step, :]
    detrended = d1 - np.median(d1)
    assert 0.005 < np.std(detrended) < 0.15


def test_heightfield_bilinear_and_gradient():
    rng = np.random.default_rng(0)
    z = rng.normal(size=(6, 5))
    hf = Heightfield(np.array([10.0, -3.0]), 0.5, z)
    # Exact at the nodes.
    ii, jj = np.meshgrid(np.arange(5), np.arange(4), indexing='ij')
    x = 10.0 + 0.5 * ii.ravel()
    y = -3.0 + 0.5 * jj.ravel()
    np.testing.assert_allclose(hf.height(x, y), z[ii.ravel(), jj.ravel()], atol=1e-12)
    # Gradient agrees with finite differences inside a cell.
    px, py = np.array([10.37, 11.1]), np.array([-2.81, -1.66])
    gx, gy = hf.gradient(px, py)
    e = 1e-6
    np.testing.assert_allclose(gx, (hf.height(px + e, py) - hf.height(px - e, py)) / (2 * e),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(gy, (hf.height(px, py + e) - hf.height(px, py - e)) / (2 * e),
                               rtol=1e-5, atol=1e-6)


def test_invalid_requests_name_the_value():
    with pytest.raises(SimulationError, match='n_rows'):
        generate_orchard(0, n_rows=1)
    with pytest.raises(SimulationError, match='row_length_m'):
        generate_orchard(0, row_length_m=1.0)
