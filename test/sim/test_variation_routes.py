"""Per-seed variation of the simulator and the CitrusFarm-like routes over many lanes."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from gft_odom.sim.motion import (
    PIVOT_RADIUS_M,
    ROUTES,
    make_route_motion,
    route_lane_count,
    route_lanes,
)
from gft_odom.sim.orchard import RUT_OFFSET_M, generate_orchard
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
