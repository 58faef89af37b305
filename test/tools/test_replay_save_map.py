"""`gft-odom replay --save-map`: the final map (binary PCD with frequencies) and the trajectory
(TUM) in the odom frame, where the simulated scene really is."""

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
    assert known.mean() > 0.2  # a share of the map: what the last of 10 scans along a row saw
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
    # The points with a frequency are those within a map voxel of what the last scan saw,
    # the others are farther.
    last = scans[-1]
    last_seen = cKDTree(transform_points(
        truth.poses[np.argmin(np.abs(truth.stamps_ns - last.stamp_ns))], last.points_xyz))
    to_last_m, _ = last_seen.query(transform_points(T_world_odom, map_odom))
    voxel_m = GftOdomConfig().registration.map_voxel_size_m
    assert np.median(to_last_m[known]) < voxel_m < np.median(to_last_m[~known])
    # Read as the first sensor frame (0.38 m above odom) the same points are off the scene.
    assert np.median(scene.query(transform_points(truth.poses[0], map_odom))[0]) > 0.25
