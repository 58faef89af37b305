"""evalio peers behind the bench's per-scan interface: the Scan -> LidarMeasurement conversion,
the pipelines on a tiny simulated drive through `run_method`, and gft_odom as an evalio
pipeline fed LidarMeasurements."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip('evalio')

from gft_odom.bench import runner  # noqa: E402
from gft_odom.bench.peers import (  # noqa: E402
    LIDAR_ONLY_PIPELINES,
    EvalioOdometry,
    LidarLayout,
    estimate_n_columns,
    grid_to_measurement,
    pipeline_params,
    rings_from_elevation,
    scan_grid,
    to_lidar_measurement,
)
from gft_odom.config import GftOdomConfig  # noqa: E402
from gft_odom.core.types import Scan  # noqa: E402
from gft_odom.errors import ConfigError  # noqa: E402
from gft_odom.io.bags import ScanBagReader  # noqa: E402
from gft_odom.io.ground_truth import read_ground_truth  # noqa: E402

N_COLUMNS = 36  # 10 deg columns keep the synthetic image small (16 x 36 cells)
PERIOD_S = 0.1
LAYOUT = LidarLayout(n_columns=N_COLUMNS)


def _synthetic_scan(with_time=True, with_ring=True, drop=()):
    """A VLP-16-like sweep in firing order: column by column, ring by ring.

    Ring r at elevation -15 + 2 r deg, column c at azimuth pi - 2 pi c / 36 (clockwise from
    behind, as the VLP-16 and our simulator), range 5 + 0.1 r + 0.01 c, time c * period / 36
    plus 1 us per ring. `drop`: (ring, column) cells without a return.
    """
    column, ring = np.meshgrid(np.arange(N_COLUMNS), np.arange(16), indexing='ij')
    column, ring = column.ravel(), ring.ravel()
    keep = np.ones(column.size, bool)
    for r, c in drop:
        keep &= ~((ring == r) & (column == c))
    column, ring = column[keep], ring[keep]
    az = math.pi - 2.0 * math.pi * column / N_COLUMNS
    elev = np.radians(-15.0 + 2.0 * ring)
    rng = 5.0 + 0.1 * ring + 0.01 * column
    xyz = rng[:, None] * np.column_stack([np.cos(elev) * np.cos(az),
                                          np.cos(elev) * np.sin(az), np.sin(elev)])
    time_s = (column * PERIOD_S / N_COLUMNS + ring * 1e-6).astype(np.float32)
    scan = Scan(stamp_ns=1_700_000_000_123_456_789, points_xyz=xyz,
                intensity=np.full(column.size, 7.0, np.float32),
                ring=ring.astype(np.uint16) if with_ring else None,
                time_offset_s=time_s if with_time else None)
    return scan, ring, column, time_s


def _by_cell(measurement):
    """{(row, col): Point} of an evalio LidarMeasurement (test-side only)."""
    return {(p.row, p.col): p for p in measurement.points}


def test_organised_image_puts_known_points_in_their_cells():
    scan, ring, column, time_s = _synthetic_scan(drop=[(3, 5), (0, 0)])
    m = to_lidar_measurement(scan, LAYOUT, organised=True)
    assert m.stamp.to_nsec() == scan.stamp_ns
    points = m.points
    assert len(points) == 16 * N_COLUMNS
    # Row-major: cell (r, c) is point r * n_columns + c, with its row and col set.
    assert [(p.row, p.col) for p in points[:3]] == [(0, 0), (0, 1), (0, 2)]
    assert (points[N_COLUMNS + 1].row, points[N_COLUMNS + 1].col) == (1, 1)
    assert (points[-1].row, points[-1].col) == (15, N_COLUMNS - 1)
    cells = _by_cell(m)
    for i in (0, 17, 250, len(ring) - 1):
        p = cells[(int(ring[i]), int(column[i]))]
        np.testing.assert_allclose([p.x, p.y, p.z], scan.points_xyz[i], atol=1e-9)
        assert p.t.to_sec() == pytest.approx(float(time_s[i]), abs=1e-7)
        assert p.intensity == 7.0
    # A missing return is a zero point in its cell, still with its row and col.
    for r, c in ((3, 5), (0, 0)):
        gap = cells[(r, c)]
        assert (gap.x, gap.y, gap.z) == (0.0, 0.0, 0.0)
        assert points[r * N_COLUMNS + c] == gap


def test_later_point_overwrites_earlier_in_a_cell():
    scan, ring, column, time_s = _synthetic_scan()
    i = int(np.flatnonzero((ring == 2) & (column == 7))[0])
    later = scan.points_xyz[i] * 1.5  # same direction, farther: same cell
    scan = Scan(scan.stamp_ns, np.vstack([scan.points_xyz, later]),
                np.append(scan.intensity, 9.0).astype(np.float32),
                np.append(scan.ring, 2).astype(np.uint16),
                np.append(scan.time_offset_s, PERIOD_S * 0.999).astype(np.float32))
    p = _by_cell(to_lidar_measurement(scan, LAYOUT, organised=True))[(2, 7)]
    np.testing.assert_allclose([p.x, p.y, p.z], later, atol=1e-9)
    assert p.intensity == 9.0


def test_unorganised_measurement_has_valid_points_with_rows():
    scan, ring, _, time_s = _synthetic_scan(drop=[(4, 4)])
    xyz = scan.points_xyz.copy()
    xyz[10] = np.nan  # a non-finite point is dropped
    scan = Scan(scan.stamp_ns, xyz, scan.intensity, scan.ring, scan.time_offset_s)
    m = to_lidar_measurement(scan, LAYOUT, organised=False)
    points = m.points
    assert len(points) == len(ring) - 1
    assert [p.row for p in points] == [int(r) for r in np.delete(ring, 10)]
    np.testing.assert_allclose(m.to_vec_stamps(), np.delete(time_s, 10), atol=1e-7)


def test_scan_without_time_gets_azimuth_times():
    scan, _, column, _ = _synthetic_scan(with_time=False)
    grid = scan_grid(scan, LAYOUT)
    np.testing.assert_array_equal(grid.column, column)
    np.testing.assert_allclose(grid.time_s, column * PERIOD_S / N_COLUMNS)
    cells = _by_cell(to_lidar_measurement(scan, LAYOUT, organised=True))
    assert cells[(5, 9)].t.to_sec() == pytest.approx(9 * PERIOD_S / N_COLUMNS, abs=1e-9)
    assert cells[(0, 0)].t.to_sec() == 0.0


def test_columns_start_at_the_earliest_point():
    # The same sweep rotated by 90 deg: columns still count from the earliest point.
    scan, _, column, _ = _synthetic_scan()
    yaw = math.pi / 2
    R = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                  [0, 0, 1]])
    rotated = Scan(scan.stamp_ns, scan.points_xyz @ R.T, scan.intensity, scan.ring,
                   scan.time_offset_s)
    np.testing.assert_array_equal(scan_grid(rotated, LAYOUT).column, column)


def test_ring_from_elevation_or_a_clear_refusal():
    scan, ring, column, _ = _synthetic_scan(with_ring=False)
    np.testing.assert_array_equal(scan_grid(scan, LAYOUT).row, ring)
    np.testing.assert_array_equal(rings_from_elevation(scan.points_xyz, LAYOUT), ring)
    cells = _by_cell(to_lidar_measurement(scan, LAYOUT, organised=True))
    i = 123
    p = cells[(int(ring[i]), int(column[i]))]
    np.testing.assert_allclose([p.x, p.y, p.z], scan.points_xyz[i], atol=1e-9)
    # A cloud that is not a VLP-16 sweep (uniform random elevations) is refused.
    rng = np.random.default_rng(0)
    blob = rng.normal(size=(2000, 3)) * [10.0, 10.0, 10.0]
    with pytest.raises(ConfigError, match='no ring field'):
        scan_grid(Scan(0, blob), LAYOUT)
    # A ring the layout does not have is refused too.
    with pytest.raises(ConfigError, match='n_rows'):
        scan_grid(Scan(0, scan.points_xyz, ring=np.full(len(ring), 20, np.uint16)), LAYOUT)


def test_n_columns_is_estimated_from_a_scan():
    scan, ring, _, _ = _synthetic_scan(drop=[(1, 1), (2, 3), (7, 30)])
    assert estimate_n_columns(scan.points_xyz, ring.astype(np.int64)) == N_COLUMNS


def test_bad_names_and_params_are_config_errors():
    with pytest.raises(ConfigError) as err:
        EvalioOdometry('kiss_icp')
    for name in LIDAR_ONLY_PIPELINES:
        assert repr(name) in str(err.value)
    with pytest.raises(ConfigError, match='needs an IMU'):
        EvalioOdometry('dlio')
    with pytest.raises(ConfigError, match="no parameter 'voxel'"):
        pipeline_params('kiss', {'voxel': 1.0})
    with pytest.raises(ConfigError, match='must be float'):
        pipeline_params('kiss', {'voxel_size': 1})
    with pytest.raises(ConfigError, match='deskew'):
        pipeline_params('genz', {'deskew': True})
    with pytest.raises(ConfigError, match='n_columns'):
        EvalioOdometry('kiss', lidar=LidarLayout(n_columns=3))
    with pytest.raises(ConfigError, match='unknown bench method'):
        runner.method_config(GftOdomConfig(), 'not-a-method')


def test_pose_stamp_follows_the_pipelines_deskew():
    scan, _, _, time_s = _synthetic_scan()
    end_ns = scan.stamp_ns + int(round(float(np.max(time_s)) * 1e9))
    assert EvalioOdometry('kiss', {'deskew': True}, LAYOUT).register_frame(scan).stamp_ns \
        == end_ns
    # A rigid fit of the whole sweep holds at its middle; CT-ICP reports its begin pose.
    mid_ns = scan.stamp_ns + int(round(0.5 * float(np.min(time_s) + np.max(time_s)) * 1e9))
    for name in ('kiss', 'loam'):
        frame = EvalioOdometry(name, lidar=LAYOUT).register_frame(scan)
        assert frame.stamp_ns == mid_ns
        np.testing.assert_allclose(frame.T_world_sensor, np.eye(4), atol=1e-9)  # first scan
    begin_ns = scan.stamp_ns + int(round(float(np.min(time_s)) * 1e9))
    assert EvalioOdometry('ct', lidar=LAYOUT).register_frame(scan).stamp_ns == begin_ns


def test_no_estimate_returns_the_previous_pose():
    scan, _, _, _ = _synthetic_scan()
    odometry = EvalioOdometry('kiss', lidar=LAYOUT)

    class Silent:
        def add_lidar(self, mm):
            pass

        def saved_estimates(self):
            return []
    odometry._pipe = Silent()
    odometry._T_world_sensor = np.diag([1.0, 1.0, 1.0, 1.0])
    odometry._T_world_sensor[0, 3] = 2.5
    frame = odometry.register_frame(scan)
    assert frame.stamp_ns == scan.stamp_ns and frame.T_world_sensor[0, 3] == 2.5


# -- the peers on a tiny simulated drive ---------------------------------------------------------

@pytest.fixture(scope='module')
def tiny_drive(tmp_path_factory):
    """20 scans of the U-turn drive, 0.4 deg azimuth step (900 columns)."""
    from gft_odom.sim.simulator import SimConfig
    sequences = runner.simulate_sequences(tmp_path_factory.mktemp('peers'), ['uturn'], [5],
                                          20, SimConfig(azimuth_step_deg=0.4))
    return sequences[0]


def _displacement_ratio(stamps_ns, positions, gt):
    """Net displacement of the estimate over that of the ground truth (nearest stamps)."""
    i0, i1 = (int(np.argmin(np.abs(gt.stamps_ns - s))) for s in (stamps_ns[0], stamps_ns[-1]))
    gt_m = float(np.linalg.norm(gt.poses[i1, :3, 3] - gt.poses[i0, :3, 3]))
    assert gt_m > 1.0  # the drive moves: identity-only poses would give a ratio of 0
    return float(np.linalg.norm(positions[-1] - positions[0])) / gt_m


@pytest.mark.slow
@pytest.mark.parametrize('method', list(runner.PEERS))
def test_peer_tracks_the_tiny_drive(method, tiny_drive):
    run = runner.run_method(method, tiny_drive, GftOdomConfig())
    m = run.metrics
    pipeline = dict(runner.PEERS)[method][0]
    assert m['registration_mode'] == f'evalio:{pipeline}'
    assert m['pipeline_version'] == EvalioOdometry(pipeline, lidar=LAYOUT).version
    assert m['n_scans'] == 20
    # Measured 0.02-0.12 m on this drive; a scrambled image or wrong times drift far more.
    assert m['ate_rmse_m'] < 0.2, m['ate_rmse_m']
    # Identity-only poses (a pipeline fed garbage) would not move: the displacement must
    # match the ground truth's (measured 0.83 loam .. 1.02 form).
    sensor = run.replay.sensor_trajectory
    ratio = _displacement_ratio(sensor.stamps_ns, sensor.poses[:, :3, 3],
                                read_ground_truth(tiny_drive.gt_path))
    assert 0.7 < ratio < 1.3, ratio


@pytest.mark.slow
@pytest.mark.parametrize('method', list(runner.GENZ_CONFIGS))
def test_genz_icp_tracks_the_tiny_drive(method, tiny_drive):
    pytest.importorskip('genz_icp')
    run = runner.run_method(method, tiny_drive, GftOdomConfig())
    m = run.metrics
    assert m['registration_mode'] == 'genz-icp'
    assert m['pipeline_params'] == {'deskew': runner.GENZ_CONFIGS[method].deskew}
    assert m['n_scans'] == 20 and m['ate_rmse_m'] < 0.2, m['ate_rmse_m']
    sensor = run.replay.sensor_trajectory
    ratio = _displacement_ratio(sensor.stamps_ns, sensor.poses[:, :3, 3],
                                read_ground_truth(tiny_drive.gt_path))
    assert 0.7 < ratio < 1.3, ratio


# -- gft_odom as an evalio pipeline --------------------------------------------------------------

@pytest.mark.slow
def test_gft_odom_runs_as_an_evalio_pipeline(tiny_drive):
    from evalio.pipelines import get_pipeline
    from evalio.types import SE3, ImuParams, LidarParams

    from gft_odom.bench import evalio_pipeline
    cls = evalio_pipeline.register()
    assert get_pipeline('gft_odom') is cls
    params = cls.default_params()
    assert params['registration.mode'] == GftOdomConfig().registration.mode
    assert isinstance(params['spectral.band_mask'], str)
    assert evalio_pipeline.config_from_params(params) == GftOdomConfig()

    pipe = cls()
    assert pipe.set_params({'pipeline.use_spectral_filter': True, 'bogus': 1}) == {'bogus': 1}
    pipe.set_imu_params(ImuParams.up())
    pipe.set_lidar_params(LidarParams(num_rows=16, num_columns=900, min_range=0.5,
                                      max_range=100.0, rate=10.0))
    pipe.set_imu_T_lidar(SE3.identity())
    pipe.initialize()
    layout = LidarLayout(n_columns=900)
    with ScanBagReader([tiny_drive.bag_path]) as reader:
        scans = [scan for _, scan in zip(range(12), reader)]
    saved = []
    for scan in scans:
        measurement = to_lidar_measurement(scan, layout, organised=True)
        back = evalio_pipeline.measurement_to_scan(measurement, pipe._layout)
        # The round trip keeps every point (zeros of the image dropped) and its ring.
        assert len(back) == len(scan)
        np.testing.assert_array_equal(np.sort(back.ring), np.sort(scan.ring))
        pipe.add_lidar(measurement)
        saved += pipe.saved_estimates()
    assert [s.to_nsec() for s, _ in saved] == [scan.stamp_ns for scan in scans]
    positions = np.array([pose.trans for _, pose in saved])
    ratio = _displacement_ratio([s.to_nsec() for s, _ in saved], positions,
                                read_ground_truth(tiny_drive.gt_path))
    assert 0.7 < ratio < 1.3, ratio


def test_grid_to_measurement_matches_to_lidar_measurement():
    scan, _, _, _ = _synthetic_scan()
    a = to_lidar_measurement(scan, LAYOUT, organised=True)
    b = grid_to_measurement(scan.stamp_ns, scan_grid(scan, LAYOUT), LAYOUT, organised=True)
    assert a == b
