"""Every odometry the benchmarks run is stamped where its pose holds, checked by measurement.

A short synthetic drive rocks the robot forwards and back along a lane (1 m either way, a 4 s
period, up to 1.6 m/s), each sweep motion-distorted with its per-point times. Its velocity
changes sign, so a pose stamped `delta` away from the time it holds is `v delta` off, forwards
on one stroke and backwards on the next, which no alignment absorbs: the stamp audit
(`core.metrics.stamp_audit`) finds the shift that scores best. A rigid fit of the whole sweep
stamped at the sweep start instead of mid-sweep is 50 ms off; on this drive (60 sweeps) the
audit resolves a stamp to about 15 ms.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gft_odom.config import GftOdomConfig, with_values
from gft_odom.core.metrics import STAMP_AUDIT_TOLERANCE_S, StampAudit, stamp_audit
from gft_odom.core.trajectory import Trajectory
from gft_odom.pipeline import OdometryPipeline
from gft_odom.sim.motion import RobotMotion
from gft_odom.sim.orchard import generate_orchard
from gft_odom.sim.simulator import ScanSimulator, SimConfig

N_SCANS = 60
# What this drive resolves; the mis-stamping it must catch is 50 ms.
RESOLUTION_S = 0.020


def rocking_drive(n_scans: int = N_SCANS, seed: int = 3, amplitude_m: float = 1.0,
                  period_s: float = 4.0):
    """(scans, sensor ground truth at 100 Hz) of the robot rocking along lane 1."""
    orchard = generate_orchard(seed, n_rows=4, row_length_m=60.0)
    t = np.linspace(0.0, 0.1 * (n_scans + 3), 4000)
    u = amplitude_m * (1.0 - np.cos(2.0 * np.pi * t / period_s))
    s = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(u)))])  # arc length, reversing too
    uv = np.column_stack([orchard.row_start_u_m + 10.0 + u,
                          np.full_like(u, orchard.lane_v_m(1))])
    motion = RobotMotion(orchard=orchard, s_m=s, uv_m=uv, heading_rad=np.zeros_like(s), t_s=t,
                         closed=False, lateral_wobble_m=0.0, lateral_wobble_wavelength_m=10.0,
                         lateral_wobble_phase_rad=0.0, yaw_wobble_rad=0.0, yaw_wobble_hz=0.3,
                         yaw_wobble_phase_rad=0.0)
    config = replace(SimConfig(azimuth_step_deg=1.0), wind_amplitude_m=0.0)
    sim = ScanSimulator(orchard, motion, config, seed)
    scans = [sim.scan(k).scan for k in range(n_scans)]
    t_gt = np.arange(0.0, 0.1 * (n_scans + 1), 0.01)
    truth = Trajectory(sim.start_ns + np.round(t_gt * 1e9).astype(np.int64),
                       sim.sensor_poses(t_gt))
    return scans, truth


@pytest.fixture(scope='module')
def drive():
    return rocking_drive()


class _Ours:
    """Our pipeline as the bench runs it: pose, then the map work."""

    def __init__(self, config: GftOdomConfig):
        self.pipeline = OdometryPipeline(config)

    def register_frame(self, scan):
        result = self.pipeline.register_frame(scan)
        self.pipeline.update_map()
        return result


def _ours(**values):
    return lambda: _Ours(with_values(GftOdomConfig(), values))


def _kiss(**kwargs):
    def make():
        pytest.importorskip('kiss_icp')
        from gft_odom.bench.kiss import KissIcpConfig, KissIcpOdometry
        return KissIcpOdometry(KissIcpConfig(**kwargs))
    return make


def _genz(**kwargs):
    def make():
        pytest.importorskip('genz_icp')
        from gft_odom.bench.genz import GenzIcpConfig, GenzIcpOdometry
        return GenzIcpOdometry(GenzIcpConfig(**kwargs))
    return make


def _evalio(pipeline):
    def make():
        pytest.importorskip('evalio')
        from gft_odom.bench.peers import EvalioOdometry, LidarLayout
        return EvalioOdometry(pipeline, lidar=LidarLayout(n_columns=None))
    return make


# Every adapter, with where it says its pose holds.
ADAPTERS = {
    'gft_odom (deskewed to the stamp)': _ours(),
    'gft_odom, deskew off (mid-sweep)': _ours(**{'registration.deskew': False}),
    "the paper's ICP (mid-sweep)": _ours(**{'registration.mode': 'paper'}),
    'kiss-icp (deskewed to the sweep end)': _kiss(),
    'kiss-icp, deskew off (mid-sweep)': _kiss(deskew=False),
    'GenZ-ICP (deskewed to mid-sweep)': _genz(),
    'GenZ-ICP, deskew off (mid-sweep)': _genz(deskew=False),
    **{f'evalio {name}': _evalio(name) for name in ('kiss', 'genz', 'mad', 'ct', 'loam',
                                                     'form')},
}


def _run(make, scans) -> Trajectory:
    odometry = make()
    frames = [odometry.register_frame(scan) for scan in scans]
    return Trajectory(np.array([f.stamp_ns for f in frames]),
                      np.array([f.T_world_sensor for f in frames]))


@pytest.mark.slow
@pytest.mark.parametrize('name', list(ADAPTERS))
def test_adapter_stamps_its_poses_where_they_hold(name, drive):
    scans, truth = drive
    estimate = _run(ADAPTERS[name], scans)
    audit = stamp_audit(estimate, truth)
    assert audit.n >= N_SCANS - 6
    assert abs(audit.best_shift_s) <= RESOLUTION_S + 1e-9, (name, audit.best_shift_s)
    # The audit tells 50 ms: the same poses stamped 50 ms early score best 50 ms later.
    early = stamp_audit(Trajectory(estimate.stamps_ns - 50_000_000, estimate.poses), truth)
    assert early.best_shift_s > 0.05 - RESOLUTION_S - 1e-9


def test_our_pose_stamp_is_the_stamp_deskewed_to_or_mid_sweep(drive):
    scans, _ = drive
    scan = scans[0]
    mid_ns = scan.stamp_ns + int(round(0.5 * float(scan.time_offset_s.min()
                                                   + scan.time_offset_s.max()) * 1e9))
    assert 40_000_000 < mid_ns - scan.stamp_ns < 60_000_000
    for values, expected in (({}, scan.stamp_ns),
                             ({'registration.deskew': False}, mid_ns),
                             ({'registration.mode': 'paper'}, mid_ns)):
        pipeline = OdometryPipeline(with_values(GftOdomConfig(), values))
        assert pipeline.register_frame(scan).stamp_ns == expected, values
        assert pipeline.sensor_trajectory().stamps_ns[-1] == expected
    # Without per-point times a sweep spans one period from its stamp.
    no_time = replace(scan, time_offset_s=None)
    pipeline = OdometryPipeline(with_values(GftOdomConfig(), {'registration.deskew': False}))
    assert pipeline.register_frame(no_time).stamp_ns == scan.stamp_ns + 50_000_000


def test_stamp_audit_finds_a_known_shift():
    """A trajectory that lags its stamps by 30 ms scores best 30 ms later; exact poses at 0."""
    t = np.arange(0.0, 20.0, 0.1)
    x = np.sin(2.0 * np.pi * t / 5.0)  # forwards and back
    poses = np.tile(np.eye(4), (t.size, 1, 1))
    poses[:, 0, 3] = x
    poses[:, 1, 3] = 0.3 * np.cos(2.0 * np.pi * t / 7.0)
    truth = Trajectory(np.round(t * 1e9).astype(np.int64), poses)
    exact = stamp_audit(truth, truth)
    assert exact.best_shift_s == 0.0 and exact.best_rmse_m < 1e-9 and exact.stamped_right()
    lagging = Trajectory(truth.stamps_ns - 30_000_000, poses)
    audit = stamp_audit(lagging, truth)
    assert audit.best_shift_s == pytest.approx(0.030)
    assert not audit.stamped_right(STAMP_AUDIT_TOLERANCE_S)
    assert audit.rmse_at_zero_m > 5 * audit.best_rmse_m
    assert isinstance(audit, StampAudit) and audit.shifts_s.size == 41


def test_stamp_audit_needs_overlap():
    from gft_odom.errors import GroundTruthError
    t = np.arange(0.0, 1.0, 0.1)
    truth = Trajectory(np.round(t * 1e9).astype(np.int64), np.tile(np.eye(4), (t.size, 1, 1)))
    far = Trajectory(truth.stamps_ns + 10_000_000_000, truth.poses)
    with pytest.raises(GroundTruthError, match='overlap'):
        stamp_audit(far, truth)
