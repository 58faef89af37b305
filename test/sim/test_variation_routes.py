"""Per-seed variation of the simulator and the CitrusFarm-like routes over many lanes."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from gft_odom.sim.motion import (
    EDGE_DRIVING,
    EDGE_LANE,
    EDGE_ROUTE,
    EDGE_TURN_CLEARANCE_M,
    OPEN_HEADLAND_M,
    PIVOT_RADIUS_M,
    ROUTES,
    TURN_CLEARANCE_M,
    make_route_motion,
    route_headland_m,
    route_lane_count,
    route_lanes,
    route_turn_clearance_m,
)
from gft_odom.sim.orchard import HEADLAND_M, RUT_OFFSET_M, TRUNK, generate_orchard
from gft_odom.sim.simulator import ScanSimulator, SimConfig
from gft_odom.sim.variation import MAX_SPEED_MPS, VARIATION_RANGES, OrchardVariation
from gft_odom.sim.writer import METADATA_FILE, METADATA_KEY, read_drive_metadata, simulate_to_bag


def test_draws_stay_in_their_ranges_and_depend_on_the_seed():
    draws = [OrchardVariation.draw(seed) for seed in range(60)]
    for name, (lo, hi) in VARIATION_RANGES.items():
        values = np.array([getattr(d, name) for d in draws])
        assert values.min() >= lo and values.max() <= hi, name
        # Spread over the range, not stuck at one value.
        assert values.max() - values.min() > 0.5 * (hi - lo), name
    assert OrchardVariation.draw(3) == OrchardVariation.draw(3)
    assert OrchardVariation.draw(3) != OrchardVariation.draw(4)
    # About half the seeds pivot (turn radius below 0.5 m).
    pivots = np.mean([d.turn_radius_m < 0.5 for d in draws])
    assert 0.3 < pivots < 0.8
    assert OrchardVariation.from_dict(draws[0].as_dict() | {'future': 1}) == draws[0]


def test_varied_orchard_follows_its_draw():
    variation = replace(OrchardVariation.draw(11), young_fraction=0.25, rut_depth_m=0.05,
                        slope=0.0, undulation_std_m=0.0, bump_std_m=0.0, roughness_std_m=0.0)
    orchard = generate_orchard(11, n_rows=5, row_length_m=40.0, variation=variation)
    assert orchard.row_spacing_m == variation.row_spacing_m
    assert orchard.tree_spacing_m == variation.tree_spacing_m
    # Young trees: some crowns far smaller than the smallest grown one could be.
    grown_min = 1.2 * variation.canopy_scale
    small = orchard.canopies.radii_m[:, 0] < 0.6 * 2.2 * variation.canopy_scale
    assert small.any() and (orchard.canopies.radii_m[:, 0] < grown_min).any()
    # Ruts: on otherwise flat ground, a trough along the lane and none beside it.
    lane_v = orchard.lane_v_m(1)
    u = 0.5 * (orchard.row_start_u_m + orchard.row_end_u_m)
    v = lane_v + np.linspace(-1.0, 1.0, 201)
    xy = orchard.to_world_xy(np.column_stack([np.full_like(v, u), v]))
    z = orchard.ground.height(xy[:, 0], xy[:, 1])
    in_ruts = np.abs(np.abs(v - lane_v) - RUT_OFFSET_M) < 0.25
    assert z[~in_ruts].max() - z[in_ruts].min() > 0.01
    assert np.ptp(z[np.abs(v - lane_v) > 0.8]) < 0.005


def test_route_lane_orders():
    assert route_lanes('lawnmower', 4) == [0, 1, 2, 3]
    assert route_lanes('every_other_row', 5) == [0, 2, 4, 3, 1]
    assert route_lanes('spiral', 5) == [0, 4, 1, 3, 2]
    assert route_lanes('out_and_back', 2) == [0, 0, 1, 1]
    with pytest.raises(Exception, match='unknown route'):
        route_lanes('zigzag', 3)
    assert route_lane_count('lawnmower', 500.0, 80.0) >= 500.0 / (80.0 + 11.0)


def _motion(route: str, **changes):
    variation = replace(OrchardVariation.draw(5), row_length_m=30.0, **changes)
    n_lanes = 3 if route != 'out_and_back' else 2
    orchard = generate_orchard(5, n_rows=n_lanes + 2, row_length_m=30.0, variation=variation)
    return make_route_motion(orchard, route, n_lanes, variation, seed=5), variation


@pytest.mark.parametrize('route', ROUTES)
def test_route_is_smooth_physical_and_starts_and_ends_at_rest(route):
    motion, variation = _motion(route, stops_per_100m=0.0)
    t = np.arange(0.0, motion.duration_s, 0.05)
    poses = motion.poses(t)
    xy = poses[:, :2, 3]
    speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.05
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    yaw_rate = np.abs(np.diff(yaw)) / 0.05
    assert speed.max() <= MAX_SPEED_MPS * 1.05
    # The yaw-rate limit plus the skid-steer wobble (0.02 rad at <= 0.5 Hz).
    assert yaw_rate.max() <= variation.max_yaw_rate_rps * 1.1 + 2 * np.pi * 0.5 * 0.02
    assert speed[:3].max() < 0.2 and speed[-3:].max() < 0.2
    # Every lane is driven: the path crosses the whole row length several times.
    u = (xy - motion.orchard.origin_xy_m) @ motion.orchard.rotation_2d
    assert u[:, 0].max() - u[:, 0].min() > 30.0


def test_out_and_back_pivots_on_the_spot():
    motion, _ = _motion('out_and_back', stops_per_100m=0.0)
    s = motion.s_m
    # Where the heading turns by half a turn within a few centimetres of path.
    heading = motion.heading_rad
    window = np.searchsorted(s, s + 4 * PIVOT_RADIUS_M)
    turned = np.abs(heading[np.minimum(window, s.size - 1)] - heading)
    assert turned.max() > 0.9 * np.pi


def test_stops_hold_the_robot_still():
    motion, variation = _motion('lawnmower', stops_per_100m=1.5, stop_duration_s=6.0)
    t = np.arange(0.0, motion.duration_s, 0.1)
    xy = motion.poses(t)[:, :2, 3]
    still = np.linalg.norm(np.diff(xy, axis=0), axis=1) < 1e-3
    # At least one run of >= 1 s standing still in the middle of the drive.
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], still[5:-5], [0]]))))[::2]
    assert runs.size and runs.max() >= 10


@pytest.mark.parametrize('fmt', ['ros2', 'ros1'])
def test_varied_route_bag_records_its_draws(tmp_path, fmt):
    from gft_odom.io.bags import ScanBagReader
    config = SimConfig(azimuth_step_deg=2.0)
    result = simulate_to_bag(tmp_path, 'spiral', 6, seed=9, config=config, fmt=fmt,
                             topdown_png=False, distance_m=150.0, vary=True)
    meta = read_drive_metadata(result.bag_path)
    draw = OrchardVariation.draw(9)
    assert meta['variation'] == draw.as_dict() and meta['n_scans'] == 6
    assert meta['sim_config']['base_to_sensor_xyz_m'][2] == draw.mount_height_m
    assert meta['sim_config']['speed_mps'] == draw.cruise_speed_mps
    assert (tmp_path / METADATA_FILE).is_file()
    if fmt == 'ros2':
        text = (result.bag_path / 'metadata.yaml').read_text()
        assert METADATA_KEY in text and 'mount_height_m' in text
    else:
        from rosbags.highlevel import AnyReader
        with AnyReader([result.bag_path]) as reader:
            conns = [c for c in reader.connections if c.topic == '/gft_odom/sim_metadata']
            (_, _, raw), = list(reader.messages(connections=conns))
            assert json.loads(reader.deserialize(raw, conns[0].msgtype).data)['seed'] == 9
    with ScanBagReader([result.bag_path]) as reader:
        assert len(list(reader)) == 6  # the metadata message is not taken for a scan


def test_whole_route_and_fixed_simulator_unchanged():
    sim, variation = ScanSimulator.for_drive(SimConfig(azimuth_step_deg=2.0), 'lawnmower', 4,
                                             distance_m=120.0)
    assert variation is None  # not varied: the nominal orchard
    assert sim.n_scans_in_drive == int(np.floor(sim.motion.duration_s * 10.0)) - 1
    # The short scenarios without --vary are exactly what from_config always built.
    a, _ = ScanSimulator.for_drive(SimConfig(azimuth_step_deg=2.0), 'uturn', 3, n_scans=20)
    b = ScanSimulator.from_config(SimConfig(azimuth_step_deg=2.0), 'uturn', 20, 3)
    np.testing.assert_array_equal(a.scan(4).scan.points_xyz, b.scan(4).scan.points_xyz)


def test_docs_list_the_ranges_the_simulator_draws_from():
    import re
    from pathlib import Path
    page = (Path(__file__).resolve().parents[2] / 'docs' / 'benchmarks.md').read_text()
    documented = {name: (float(lo), float(hi)) for name, lo, hi in
                  re.findall(r'^\| `(\w+)` \| (-?[\d.]+) \| (-?[\d.]+) \|$', page, re.M)}
    assert documented == VARIATION_RANGES


# --- edge_lawnmower: leaves the block at its edge into open ground --------------------------

@pytest.fixture(scope='module')
def edge_drive():
    """Held-out edge drive 221 as the record simulates it (motion only: no ray is cast)."""
    sim, variation = ScanSimulator.for_drive(SimConfig(azimuth_step_deg=2.0), EDGE_ROUTE, 221,
                                             distance_m=280.0, vary=True)
    t = np.arange(0.0, sim.motion.duration_s, 0.05)
    poses = sim.motion.poses(t)
    uv = (poses[:, :2, 3] - sim.orchard.origin_xy_m) @ sim.orchard.rotation_2d
    return sim.orchard, sim.motion, variation, poses, uv


def _row_frame(orchard, xy):
    return (xy[..., :2] - orchard.origin_xy_m) @ orchard.rotation_2d


def test_edge_route_starts_on_the_edge_track_with_open_ground_beyond(edge_drive):
    orchard, _, _, _, uv = edge_drive
    assert route_lanes(EDGE_ROUTE, 4) == [EDGE_LANE, 0, 1, 2]
    v_start = uv[0, 1]
    assert abs(v_start - orchard.edge_lane_v_m) < 0.1
    # Trees on one side only: row 0 half a row spacing away, nothing at all on the other.
    trunks = _row_frame(orchard, orchard.cylinders.base_m[orchard.cylinders.surface == TRUNK])
    assert np.abs(trunks[:, 1] - v_start).min() > 0.4 * orchard.row_spacing_m
    cyl_v = _row_frame(orchard, orchard.cylinders.base_m)[:, 1]
    crown_v = _row_frame(orchard, orchard.canopies.centre_m)[:, 1] - \
        orchard.canopies.radii_m[:, 1]
    box_v = _row_frame(orchard, orchard.boxes.centre_m)[:, 1] - \
        np.linalg.norm(orchard.boxes.half_extent_m[:, :2], axis=1)
    assert min(cyl_v.min(), crown_v.min(), box_v.min()) > v_start + 0.5
    # The first lane is driven along the edge, the whole row length.
    first = np.abs(uv[:, 1] - v_start) < 0.2
    assert np.ptp(uv[first, 0]) > orchard.row_end_u_m - orchard.row_start_u_m


def test_edge_route_turns_far_past_the_row_ends_in_open_ground(edge_drive):
    orchard, _, _, _, uv = edge_drive
    u0, u1 = orchard.row_start_u_m, orchard.row_end_u_m
    past = np.maximum(uv[:, 0] - u1, u0 - uv[:, 0])
    # Out at both ends, well beyond the crowns of the last trees (< 3.5 m past the trunks).
    assert (uv[:, 0] - u1).max() > EDGE_TURN_CLEARANCE_M - 0.3
    assert (u0 - uv[:, 0]).max() > EDGE_TURN_CLEARANCE_M - 0.3
    cyl_u = _row_frame(orchard, orchard.cylinders.base_m)[:, 0]
    crown_u = _row_frame(orchard, orchard.canopies.centre_m)[:, 0]
    reach = orchard.canopies.radii_m[:, 0]
    assert cyl_u.min() > u0 - 2.5 and cyl_u.max() < u1 + 2.5  # trunks, row-end posts, pipes
    assert (crown_u - reach).min() > u0 - 3.5 and (crown_u + reach).max() < u1 + 3.5
    # No shed or vehicle within 20 m of where the robot turns.
    headland = uv[past > 3.5]
    boxes = _row_frame(orchard, orchard.boxes.centre_m)
    gap = np.linalg.norm(headland[:, None] - boxes[None], axis=2) - \
        np.linalg.norm(orchard.boxes.half_extent_m[:, :2], axis=1)
    assert gap.min() > 20.0


def test_edge_route_is_fast_with_tight_turns(edge_drive):
    _, motion, variation, poses, _ = edge_drive
    assert variation.cruise_speed_mps == EDGE_DRIVING['cruise_speed_mps']
    assert variation.seed == 221 and variation.slope == OrchardVariation.draw(221).slope
    speed = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1) / 0.05
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    yaw_rate = np.abs(np.diff(yaw)) / 0.05
    assert 1.7 < speed.max() <= MAX_SPEED_MPS * 1.05
    assert np.median(speed[speed > 0.1]) > 1.6
    assert 1.5 < yaw_rate.max() <= EDGE_DRIVING['max_yaw_rate_rps'] * 1.1 + 2 * np.pi * 0.5 * 0.02
    # Squared turns: quarter arcs of the 0.8 m corner radius (curvature 1 / 0.8 m).
    moving = np.diff(motion.s_m, prepend=-1.0) > 0.0  # a stop repeats its sample
    curvature = np.abs(np.gradient(motion.heading_rad[moving], motion.s_m[moving]))
    assert 1.0 / EDGE_DRIVING['turn_radius_m'] == pytest.approx(np.percentile(
        curvature[curvature > 0.5], 50), rel=0.05)


def test_edge_route_is_deterministic_and_other_routes_keep_their_orchard(edge_drive):
    orchard, motion, variation, _, _ = edge_drive
    again, variation_again = ScanSimulator.for_drive(SimConfig(azimuth_step_deg=2.0),
                                                     EDGE_ROUTE, 221, distance_m=280.0,
                                                     vary=True)
    assert variation_again == variation
    for name in ('s_m', 'uv_m', 'heading_rad', 't_s'):
        np.testing.assert_array_equal(getattr(again.motion, name), getattr(motion, name))
    np.testing.assert_array_equal(again.orchard.boxes.centre_m, orchard.boxes.centre_m)
    # The other routes: the seed's own driving, turns TURN_CLEARANCE_M out, row-end objects
    # HEADLAND_M past the trees; the edge orchard differs from theirs only in those objects.
    sim, other = ScanSimulator.for_drive(SimConfig(azimuth_step_deg=2.0), 'lawnmower', 221,
                                         distance_m=280.0, vary=True)
    assert other == OrchardVariation.draw(221)
    assert route_turn_clearance_m('lawnmower') == TURN_CLEARANCE_M
    assert route_headland_m('lawnmower') == HEADLAND_M
    u1 = sim.orchard.row_end_u_m
    assert sim.motion.uv_m[:, 0].max() - u1 == pytest.approx(TURN_CLEARANCE_M, abs=0.01)
    n_rows = len(orchard.row_v_m)
    plain = generate_orchard(221, n_rows=n_rows, row_length_m=variation.row_length_m,
                             variation=variation)
    np.testing.assert_array_equal(plain.cylinders.base_m, orchard.cylinders.base_m)
    np.testing.assert_array_equal(plain.canopies.centre_m, orchard.canopies.centre_m)
    np.testing.assert_array_equal(plain.ground.z_m, orchard.ground.z_m)
    shift = np.abs(_row_frame(orchard, orchard.boxes.centre_m)[:, 0] -
                   _row_frame(plain, plain.boxes.centre_m)[:, 0])
    np.testing.assert_allclose(shift, OPEN_HEADLAND_M - HEADLAND_M, atol=1e-9)
