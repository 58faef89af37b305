"""The graph low-pass filter of the range signal (core/spectral/lowpass.py)."""

import numpy as np

from gft_odom.core.spectral.lowpass import range_lowpass


def _ring(ranges_m: np.ndarray, z_m: float = -0.7) -> np.ndarray:
    azimuth = np.linspace(-np.pi, np.pi, ranges_m.size, endpoint=False)
    return np.c_[ranges_m * np.cos(azimuth), ranges_m * np.sin(azimuth),
                 np.full(ranges_m.size, z_m)]


def test_a_smooth_ring_loses_range_noise_and_keeps_every_beam():
    rng = np.random.default_rng(3)
    points = _ring(6.0 + rng.normal(0.0, 0.025, 1800))
    ring = np.zeros(len(points), dtype=np.uint16)
    out = range_lowpass(points, ring, alpha=8.0, tau_m=0.2, sigma_m=0.1)
    range_error = np.linalg.norm(out[:, :2], axis=1) - 6.0
    assert np.std(range_error) < 0.5 * 0.025
    beams = points / np.linalg.norm(points, axis=1, keepdims=True)
    assert np.allclose(out / np.linalg.norm(out, axis=1, keepdims=True), beams, atol=1e-12)


def test_a_depth_jump_is_not_smoothed_across():
    ranges_m = np.where(np.arange(1800) % 600 < 300, 5.0, 8.0)  # two surfaces, no noise
    points = _ring(ranges_m)
    out = range_lowpass(points, np.zeros(1800, dtype=np.uint16), alpha=8.0, tau_m=0.2,
                        sigma_m=0.1)
    assert np.abs(np.linalg.norm(out, axis=1) - np.linalg.norm(points, axis=1)).max() < 1e-3


def test_rings_are_filtered_apart_and_bad_points_left_alone():
    rng = np.random.default_rng(4)
    # Two rings 0.1 m apart in range, their points interleaved in azimuth: smoothed together
    # they would meet half way.
    near, far = _ring(np.full(900, 4.0)), _ring(np.full(900, 4.1))
    points = np.vstack([near, far]) + rng.normal(0.0, 0.01, (1800, 3))
    points[7] = np.nan
    ring = np.repeat(np.array([0, 1], dtype=np.uint16), 900)
    out = range_lowpass(points, ring, alpha=4.0, tau_m=0.2, sigma_m=0.1)
    assert np.isnan(out[7]).all()
    ranges = np.linalg.norm(out[:, :2], axis=1)
    assert abs(np.nanmean(ranges[:900]) - 4.0) < 0.01
    assert abs(np.nanmean(ranges[900:]) - 4.1) < 0.01
    assert not np.allclose(out[8:], points[8:])
    assert np.array_equal(range_lowpass(points, ring, 0.0, 0.2, 0.1), points,
                          equal_nan=True)


def test_the_pipeline_registers_the_filtered_ranges_only_with_the_filter():
    from gft_odom.config import GftOdomConfig, with_values
    from gft_odom.pipeline import OdometryPipeline
    from gft_odom.sim.simulator import ScanSimulator, SimConfig

    sim = ScanSimulator.from_config(SimConfig(azimuth_step_deg=0.4), 'row', 40, 5)
    scans = [sim.scan(i).scan for i in range(3)]

    def run(overrides):
        pipeline = OdometryPipeline(with_values(GftOdomConfig(), overrides))
        return [pipeline.register_frame(scan) for scan in scans]

    lowpass = {'spectral.range_lowpass_alpha': 4.0}
    plain, filtered = run({}), run(lowpass)
    off = run({**lowpass, 'pipeline.use_spectral_filter': False})
    for a, b, c in zip(plain, filtered, off):
        assert not np.allclose(b.filtered.points_xyz, a.filtered.points_xyz)
        np.testing.assert_array_equal(b.nu, a.nu)  # the measured points' frequencies
        np.testing.assert_array_equal(c.filtered.points_xyz, a.filtered.points_xyz)
    assert not np.allclose(filtered[-1].T_world_sensor, plain[-1].T_world_sensor)
