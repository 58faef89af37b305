"""`gft-odom replay --save-map`: the drive's map (binary PCD with frequencies) and the
trajectory (TUM) in the odom frame, where the simulated scene really is."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gft_odom.config import GftOdomConfig
from gft_odom.core.geometry import invert_transform, transform_points
from gft_odom.core.spectral.bands import band_of_nu
from gft_odom.io.bags import ScanBagReader
from gft_odom.io.pcd import read_pcd
from gft_odom.io.tum import read_tum
from gft_odom.pipeline import base_to_sensor
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag
from gft_odom.tools.cli import main

pytestmark = pytest.mark.slow


def test_replay_saves_the_map_in_the_odom_frame_with_frequencies(tmp_path):
    sim = simulate_to_bag(tmp_path / 'data', 'row', 10, seed=3,
                          config=SimConfig(azimuth_step_deg=0.8), topdown_png=False)
    out = tmp_path / 'out'
    assert main(['replay', str(sim.bag_path), '--out', str(out), '--quiet', '--no-figures',
                 '--save-map']) == 0
    metrics = json.loads((out / 'metrics.json').read_text())
    saved = metrics['saved_map']
    assert saved['pcd'] == str(out / 'map' / 'map.pcd') and saved['points'] > 1000
    cloud = read_pcd(saved['pcd'])
    assert cloud.shape[0] == saved['points']
    known = np.isfinite(cloud['frequency'])
    assert known.mean() > 0.5  # every point of the drive's map but isolated ones
    np.testing.assert_array_equal(cloud['band'], band_of_nu(cloud['frequency'], 10))
    trajectory = read_tum(saved['trajectory'])
    np.testing.assert_allclose(trajectory.poses, read_tum(out / 'trajectory_tum.txt').poses,
                               atol=1e-6)
    assert len(trajectory) == 10

    # Into the simulator's world: odom is base_link at the first scan.
    truth = read_tum(sim.gt_tum_path)  # T_world_sensor
    T_base_sensor = base_to_sensor(GftOdomConfig())
    T_world_odom = truth.poses[0] @ invert_transform(T_base_sensor)
    map_odom = np.stack([cloud['x'], cloud['y'], cloud['z']], axis=1).astype(float)
    with ScanBagReader([sim.bag_path]) as reader:
        scans = list(reader)
    seen_world = np.concatenate([
        transform_points(truth.poses[np.argmin(np.abs(truth.stamps_ns - scan.stamp_ns))],
                         scan.points_xyz) for scan in scans])
    scene = cKDTree(seen_world)
    distance_m, _ = scene.query(transform_points(T_world_odom, map_odom))
    # Within the sensor noise and the map voxel of what the scans saw.
    assert np.median(distance_m) < 0.1
    # Read as the first sensor frame (0.38 m above odom) the same points are off the scene.
    assert np.median(scene.query(transform_points(truth.poses[0], map_odom))[0]) > 0.25


@pytest.fixture(scope='module')
def two_days(tmp_path_factory):
    """A map day and a later day (the same canopy) of one block, coarse scans."""
    root = tmp_path_factory.mktemp('block')
    config = SimConfig(azimuth_step_deg=0.8)
    day0 = simulate_to_bag(root / 'd0', 'lawnmower', 120, seed=5, config=config,
                           topdown_png=False, distance_m=60.0, vary=True)
    day1 = simulate_to_bag(root / 'd1', 'lawnmower', 80, seed=5, config=config,
                           topdown_png=False, distance_m=60.0, vary=True, day=1,
                           canopy='same')
    return root, day0, day1


def _start_in_map(day0, day1) -> str:
    """Where base_link starts on day 1 in day 0's odom frame: x,y,yaw."""
    T_base_sensor = base_to_sensor(GftOdomConfig())
    T = (T_base_sensor @ invert_transform(read_tum(day0.gt_tum_path).poses[0])
         @ read_tum(day1.gt_tum_path).poses[0] @ invert_transform(T_base_sensor))
    return f'{T[0, 3]:.3f},{T[1, 3]:.3f},{np.arctan2(T[1, 0], T[0, 0]):.4f}'


def test_a_later_day_localises_in_the_map_of_the_first(two_days):
    root, day0, day1 = two_days
    assert main(['replay', str(day0.bag_path), '--out', str(root / 'r0'), '--quiet',
                 '--no-figures', '--save-map']) == 0
    out = root / 'r1'
    assert main(['replay', str(day1.bag_path), '--out', str(out), '--quiet', '--no-figures',
                 '--map', str(root / 'r0' / 'map' / 'map.pcd'),
                 f'--initial-pose={_start_in_map(day0, day1)}']) == 0
    located = json.loads((out / 'metrics.json').read_text())['localisation']
    assert located['status_counts'].get('localised', 0) >= 0.9 * 80
    # In the map frame, unaligned: where day 1's sensor really was, in day 0's odom frame.
    in_map = read_tum(out / 'trajectory_map_tum.txt')
    truth0, truth1 = read_tum(day0.gt_tum_path), read_tum(day1.gt_tum_path)
    T_base_sensor = base_to_sensor(GftOdomConfig())
    T_map_world = T_base_sensor @ invert_transform(truth0.poses[0])
    true_map = T_map_world @ truth1.poses[np.searchsorted(truth1.stamps_ns, in_map.stamps_ns)]
    error_m = np.linalg.norm(in_map.poses[:, :3, 3] - true_map[:, :3, 3], axis=1)
    assert error_m.max() < 0.15


@pytest.mark.parametrize('case', ['missing', 'not a pcd', 'sensor frame'])
def test_a_map_that_cannot_serve_is_refused_with_the_reason(two_days, case, tmp_path, caplog):
    root, _, day1 = two_days
    path = tmp_path / 'map.pcd'
    if case == 'not a pcd':
        path.write_text('hello')
    elif case == 'sensor frame':
        from gft_odom.io.pcd import frequency_cloud, write_pcd
        points = np.random.default_rng(0).uniform(-5, 5, (500, 3))
        nu = np.zeros(500, np.float32)
        write_pcd(path, frequency_cloud(points, None, nu, np.zeros(500, np.uint8)),
                  frame_id='velodyne')
    code = main(['replay', str(day1.bag_path), '--out', str(tmp_path / 'r'), '--quiet',
                 '--no-figures', '--map', str(path)])
    assert code != 0
    said = caplog.text
    assert str(path) in said
    assert {'missing': 'does not exist', 'not a pcd': 'cannot be read',
            'sensor frame': "'velodyne'"}[case] in said
