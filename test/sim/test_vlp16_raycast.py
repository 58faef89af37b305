"""VLP-16 geometry and the ray caster against scenes with known answers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gft_odom.sim.lidar import Vlp16Model, _hit_ground, cast_rays
from gft_odom.sim.motion import make_motion, required_row_length_m
from gft_odom.sim.orchard import (
    BUILDING,
    CANOPY,
    GROUND,
    TRUNK,
    Boxes,
    Canopies,
    Cylinders,
    Heightfield,
    Orchard,
    generate_orchard,
)
from gft_odom.sim.simulator import ScanSimulator, SimConfig


def _scene(cylinders=(), canopies=(), boxes=(), ground_z=0.0):
    """A flat-ground scene. cylinders: (base, axis, length, radius); canopies: (centre, radii);
    boxes: (centre, half, yaw)."""
    def arr(rows, i, width):
        return np.array([r[i] for r in rows], float).reshape(-1, width)
    cyl = Cylinders(arr(cylinders, 0, 3), arr(cylinders, 1, 3), arr(cylinders, 2, 1)[:, 0],
                    arr(cylinders, 3, 1)[:, 0], np.full(len(cylinders), TRUNK, np.int8))
    k = len(canopies)
    can = Canopies(arr(canopies, 0, 3), arr(canopies, 1, 3), np.ones(k), np.full((k, 2), 0.5),
                   np.zeros((k, 2)))
    box = Boxes(arr(boxes, 0, 3), arr(boxes, 1, 3), arr(boxes, 2, 1)[:, 0],
                np.full(len(boxes), BUILDING, np.int8))
    ground = Heightfield(np.array([-200.0, -200.0]), 1.0, np.full((401, 401), ground_z))
    return Orchard(seed=0, heading_rad=0.0, origin_xy_m=np.zeros(2), row_v_m=np.array([0.0, 6.0]),
                   row_start_u_m=0.0, row_end_u_m=10.0, row_spacing_m=6.0, tree_spacing_m=4.0,
                   ground=ground, cylinders=cyl, canopies=can, boxes=box,
                   trunk_index_of_tree=np.arange(len(cylinders)),
                   canopy_index_of_tree=np.arange(k))


def test_ray_table_is_the_vlp16():
    model = Vlp16Model()
    rays = model.ray_table()
    assert model.n_columns == 1800
    assert rays['direction'].shape == (1800 * 16, 3)
    np.testing.assert_allclose(np.linalg.norm(rays['direction'], axis=1), 1.0)
    elevation = np.degrees(np.arcsin(rays['direction'][:, 2]))
    ring = rays['ring'].astype(int)
    np.testing.assert_allclose(elevation, -15.0 + 2.0 * ring, atol=1e-9)
    assert set(ring.tolist()) == set(range(16)) and rays['ring'].dtype == np.uint16
    # 0.2 deg between consecutive firings of one laser; sweep clockwise (azimuth decreasing).
    ring0 = rays['direction'][ring == 0]
    az = np.unwrap(np.arctan2(ring0[:, 1], ring0[:, 0]))
    np.testing.assert_allclose(np.degrees(np.diff(az)), -0.2, atol=1e-9)
    t = rays['time_offset_s']
    assert t.min() == 0.0 and t.max() < 0.1
    assert np.all(np.diff(t[ring == 0]) > 0.0)


def test_cylinder_box_and_ground_hits_are_exact():
    scene = _scene(cylinders=[((5.0, 0.0, -0.1), (0.0, 0.0, 1.0), 2.0, 0.1)],
                   boxes=[((0.0, 8.0, 1.0), (1.0, 2.0, 1.0), 0.0)])
    origin = np.array([0.0, 0.0, 0.5])
    dirs = np.array([[1.0, 0.0, 0.0],  # trunk at 5 m, radius 0.1
                     [0.0, 1.0, 0.0],  # box face at y = 6
                     [0.0, np.sqrt(0.5), -np.sqrt(0.5)],  # ground at 0.5 * sqrt(2)
                     [0.0, 0.0, 1.0],  # sky
                     [1.0, 0.0, 1.0] / np.sqrt(2.0)])  # above the trunk: sky
    hits = cast_rays(scene, np.tile(origin, (5, 1)), dirs, np.zeros(5),
                     np.random.default_rng(0))
    np.testing.assert_allclose(hits.range_m[:3], [4.9, 6.0, 0.5 * np.sqrt(2.0)], atol=1e-4)
    assert np.isinf(hits.range_m[3]) and np.isinf(hits.range_m[4])
    assert hits.surface[0] == TRUNK and hits.surface[1] == BUILDING and hits.surface[2] == GROUND
    np.testing.assert_allclose(hits.cos_incidence[:3], [1.0, 1.0, np.sqrt(0.5)], atol=1e-4)


def test_nearest_surface_wins_and_occludes():
    # Two trunks in line: the farther one is hidden.
    scene = _scene(cylinders=[((4.0, 0.0, 0.0), (0.0, 0.0, 1.0), 2.0, 0.1),
                              ((2.0, 0.0, 0.0), (0.0, 0.0, 1.0), 2.0, 0.1)])
    hits = cast_rays(scene, np.array([[0.0, 0.0, 0.5]]), np.array([[1.0, 0.0, 0.0]]),
                     np.zeros(1), np.random.default_rng(0))
    assert hits.primitive[0] == 1
    np.testing.assert_allclose(hits.range_m[0], 1.9, atol=1e-6)


@pytest.mark.parametrize('mean_free_path_m', [0.5, 1.0])
def test_canopy_porosity_follows_the_mean_free_path(mean_free_path_m):
    # Rays through the middle of a sphere of radius 1 (2 m of crown): P(pass) = exp(-2 / mfp);
    # the depth of the stopped ones is a truncated exponential.
    n = 20000
    scene = _scene(canopies=[((10.0, 0.0, 3.0), (1.0, 1.0, 1.0))])
    origins = np.tile([0.0, 0.0, 3.0], (n, 1))
    dirs = np.tile([1.0, 0.0, 0.0], (n, 1))
    hits = cast_rays(scene, origins, dirs, np.zeros(n), np.random.default_rng(1),
                     canopy_mean_free_path_m=mean_free_path_m)
    stopped = np.isfinite(hits.range_m)
    assert np.all(hits.surface[stopped] == CANOPY)
    p_pass = np.exp(-2.0 / mean_free_path_m)
    assert abs((~stopped).mean() - p_pass) < 4.0 * np.sqrt(p_pass * (1 - p_pass) / n) + 1e-3
    depth = hits.range_m[stopped] - 9.0
    assert depth.min() >= 0.0 and depth.max() <= 2.0
    lam = mean_free_path_m
    expected = lam - 2.0 * p_pass / (1.0 - p_pass)  # mean of Exp(lam) truncated at 2
    assert abs(depth.mean() - expected) < 0.02


def test_wind_moves_canopies_by_about_the_amplitude():
    scene = _scene(canopies=[((5.0, 0.0, 2.0), (1.0, 1.0, 1.0))])
    # A ray grazing the crown's side at y = 1.0 - 0.02: inside at rest, outside when the crown
    # sways 5 cm away; rays are cast at many instants.
    n = 2000
    t = np.linspace(0.0, 10.0, n)
    origins = np.tile([0.0, 0.99, 2.0], (n, 1))
    dirs = np.tile([1.0, 0.0, 0.0], (n, 1))
    calm = cast_rays(scene, origins, dirs, t, np.random.default_rng(2), wind_amplitude_m=0.0,
                     canopy_mean_free_path_m=1e-3)
    windy = cast_rays(scene, origins, dirs, t, np.random.default_rng(2), wind_amplitude_m=0.05,
                      canopy_mean_free_path_m=1e-3)
    assert np.isfinite(calm.range_m).all()
    frac = np.isfinite(windy.range_m).mean()
    assert 0.2 < frac < 0.9


def test_ground_march_agrees_with_a_dense_march():
    orchard = generate_orchard(5, n_rows=4, row_length_m=40.0, margin_m=20.0)
    rng = np.random.default_rng(3)
    centre = orchard.to_world_xy(np.array([20.0, 3.0]))
    z0 = orchard.ground.height(centre[:1], centre[1:])[0] + 0.45
    n = 300
    elev = rng.uniform(np.radians(-15.0), np.radians(3.0), n)
    az = rng.uniform(-np.pi, np.pi, n)
    dirs = np.column_stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
    origins = np.tile([centre[0], centre[1], z0], (n, 1))
    t_hit = _hit_ground(origins, dirs, orchard.ground, 0.4, 60.0)
    ts = np.linspace(0.4, 60.0, 12000)
    agree = 0
    for i in range(n):
        p = origins[i] + ts[:, None] * dirs[i]
        below = p[:, 2] <= orchard.ground.height(p[:, 0], p[:, 1])
        ref = ts[np.argmax(below)] if below.any() else np.inf
        agree += (np.isinf(ref) and np.isinf(t_hit[i])) or abs(ref - t_hit[i]) < 0.02
    # Grazing rays may skip a bump thinner than a march step; nearly all must agree.
    assert agree / n > 0.99
    hit = np.isfinite(t_hit)
    assert hit.sum() > 0.5 * n
    p = origins[hit] + t_hit[hit, None] * dirs[hit]
    np.testing.assert_allclose(p[:, 2], orchard.ground.height(p[:, 0], p[:, 1]), atol=1e-3)


def test_real_resolution_scan_geometry():
    """One full-resolution VLP-16 sweep: ring elevations, 0.2 deg columns, plausible counts."""
    distance = 5.0
    orchard = generate_orchard(11, n_rows=6, row_length_m=required_row_length_m('row', distance))
    motion = make_motion(orchard, 'row', distance, 1.0, 11)
    config = dataclasses.replace(SimConfig(), motion_distortion=False)
    sim = ScanSimulator(orchard, motion, config, 11)
    out = sim.scan(0)
    scan = out.scan
    assert 15000 < len(scan) < 28800
    xyz = scan.points_xyz
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    np.testing.assert_allclose(elevation, -15.0 + 2.0 * scan.ring.astype(float), atol=1e-6)
    azimuth = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    steps = (180.0 - azimuth) / 0.2
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-4)
    rng_m = np.linalg.norm(xyz, axis=1)
    assert rng_m.min() >= config.min_range_m and rng_m.max() <= config.max_range_m
    assert np.all(scan.time_offset_s == 0.0)  # no distortion: an instantaneous sweep
    # Every kind of near surface shows up; intensities on the 0..255 scale.
    counts = np.bincount(out.surface, minlength=7)
    assert counts[GROUND] > 3000 and counts[CANOPY] > 3000 and counts[TRUNK] > 20
    assert scan.intensity.dtype == np.float32
    assert 0.0 <= scan.intensity.min() and scan.intensity.max() <= 255.0
    assert np.median(scan.intensity[out.surface == CANOPY]) > \
        np.median(scan.intensity[out.surface == GROUND])


def test_culling_loses_no_hits():
    """The azimuth/elevation culling gives the same first hits as testing every primitive."""
    from gft_odom.sim.lidar import _hit_boxes, _hit_cylinders

    orchard = generate_orchard(8, n_rows=5, row_length_m=40.0, margin_m=10.0)
    empty = Canopies(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2)),
                     np.zeros((0, 2)))
    solid = dataclasses.replace(orchard, canopies=empty)
    rng = np.random.default_rng(4)
    n = 3000
    centre = orchard.to_world_xy(np.array([15.0, orchard.lane_v_m(1)]))
    ground_z = orchard.ground.height(centre[:1], centre[1:])[0]
    # Origins spread over 0.1 m as within a sweep; directions over the VLP-16's field of view.
    origins = np.column_stack([centre[0] + rng.uniform(-0.05, 0.05, n),
                               centre[1] + rng.uniform(-0.05, 0.05, n),
                               np.full(n, ground_z + 0.45)])
    elev = rng.uniform(np.radians(-15.0), np.radians(15.0), n)
    az = rng.uniform(-np.pi, np.pi, n)
    dirs = np.column_stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
    hits = cast_rays(solid, origins, dirs, np.zeros(n), rng)

    cyl, box = orchard.cylinders, orchard.boxes
    ray = np.repeat(np.arange(n), len(cyl))
    prim = np.tile(np.arange(len(cyl)), n)
    t_cyl, _ = _hit_cylinders(origins[ray], dirs[ray], cyl.base_m[prim], cyl.axis[prim],
                              cyl.length_m[prim], cyl.radius_m[prim])
    ray_b = np.repeat(np.arange(n), len(box))
    prim_b = np.tile(np.arange(len(box)), n)
    t_box, _ = _hit_boxes(origins[ray_b], dirs[ray_b], box.centre_m[prim_b],
                          box.half_extent_m[prim_b], box.yaw_rad[prim_b])
    t_ground = _hit_ground(origins, dirs, orchard.ground, 0.4, 100.0)
    brute = np.minimum(np.minimum(t_cyl.reshape(n, -1).min(axis=1),
                                  t_box.reshape(n, -1).min(axis=1)), t_ground)
    brute[brute > 100.0] = np.inf
    np.testing.assert_array_equal(np.isfinite(hits.range_m), np.isfinite(brute))
    finite = np.isfinite(brute)
    np.testing.assert_allclose(hits.range_m[finite], brute[finite], atol=1e-9)
    assert (hits.surface != GROUND).sum() > 20  # the check covered object hits too
