"""Run the five methods (and evalio's peers) on the same simulated sequences, one clock, one
metrics code.

Every method sees the scans of the same bag, decoded by the same reader; the latency of a scan
is `time.perf_counter()` from before the bag read + decode to after the method's per-scan call
returns. Metrics come from `gft_odom.replay.summarize` (ATE with the config's evaluation
section against the GPS antenna track, RPE drift, the paper's MSE, latency, points kept), so
the numbers mean exactly what `gft-odom replay` reports.
"""

from __future__ import annotations

import cProfile
import io
import logging
import pstats
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from gft_odom.bench.genz import GenzIcpConfig, GenzIcpOdometry, genz_icp_version
from gft_odom.bench.kiss import KissIcpConfig, KissIcpOdometry
from gft_odom.bench.peers import PEERS, EvalioOdometry, LidarLayout, peer_metadata
from gft_odom.config import GftOdomConfig, with_values
from gft_odom.core.geometry import sensor_to_base_poses
from gft_odom.core.trajectory import Trajectory
from gft_odom.errors import ConfigError
from gft_odom.io.bags import ScanBagReader
from gft_odom.io.ground_truth import read_ground_truth
from gft_odom.pipeline import OdometryPipeline, base_to_sensor
from gft_odom.replay import ReplayResult, scan_count, summarize, timed_scans
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag

log = logging.getLogger(__name__)

# name -> (label, registration mode or None for kiss-icp, spectral filter on)
METHODS: dict[str, tuple[str, str | None, bool]] = {
    'paper': ("paper ICP, no filter (the paper's baseline)", 'paper', False),
    'paper+gft': ('paper ICP + GFT filter', 'paper', True),
    'default': ('default registration, no filter', 'default', False),
    'default+gft': ('default registration + GFT filter', 'default', True),
    'kiss-icp': ('kiss-icp', None, False),
}
# evalio's LiDAR-only pipelines, run like kiss-icp (no spectral filter). Not in METHODS, so the
# default `gft-odom bench` stays the five methods; ask for them by name.
# GenZ-ICP through its own pip package: with its deskew (the per-point times normalised as
# it wants them), and as it ships (deskew off).
GENZ_CONFIGS: dict[str, GenzIcpConfig] = {'genz-icp': GenzIcpConfig(),
                                          'genz-icp-no-deskew': GenzIcpConfig(deskew=False)}
GENZ_LABELS = {'genz-icp': 'GenZ-ICP (deskew)',
               'genz-icp-no-deskew': 'GenZ-ICP (no deskew, as shipped)'}
PEER_METHODS: dict[str, tuple[str, str | None, bool]] = {
    **{name: (label, None, False) for name, label in GENZ_LABELS.items()},
    **{name: (label, None, False) for name, (_, label) in PEERS.items()}}
ALL_METHODS: dict[str, tuple[str, str | None, bool]] = {**METHODS, **PEER_METHODS}
# Peers on our simulator: its azimuth step varies (coarse for tests), so the column count of
# the organised cloud is read off the first scan; rows, ranges and rate are the VLP-16's.
PEER_LIDAR = LidarLayout(n_columns=None)


@dataclass(frozen=True)
class BenchSequence:
    """One simulated drive: where its bag and ground truth are."""

    scenario: str
    seed: int
    n_scans: int
    bag_path: Path
    gt_path: Path

    @property
    def name(self) -> str:
        """The method name used in tables and results folders."""
        return f'{self.scenario}-{self.seed}'


@dataclass
class MethodRun:
    """One method on one sequence: its replay (trajectories, latency) and metrics."""

    method: str
    sequence: BenchSequence
    replay: ReplayResult
    config: GftOdomConfig  # the effective config of the run (kiss-icp: lever arm, evaluation)

    @property
    def metrics(self) -> dict:
        """Flat metrics of this run (accuracy, latency, points, fallbacks)."""
        return self.replay.metrics


@dataclass
class BenchRun:
    """Everything one bench run measured."""

    sequences: list[BenchSequence]
    runs: list[MethodRun] = field(default_factory=list)
    profiles: dict[str, str] = field(default_factory=dict)


def simulate_sequences(out_dir: str | Path, scenarios: Sequence[str], seeds: Sequence[int],
                       n_scans: int, sim_config: SimConfig | None = None,
                       progress: Callable[[str], None] | None = None) -> list[BenchSequence]:
    """One bag + ground truth per (scenario, seed), each in its own folder under `out_dir`."""
    sequences = []
    for seed in seeds:
        for scenario in scenarios:
            folder = Path(out_dir) / f'{scenario}_{seed}'
            result = simulate_to_bag(folder, scenario=scenario, n_scans=n_scans, seed=int(seed),
                                     config=sim_config, topdown_png=False)
            sequences.append(BenchSequence(scenario, int(seed), n_scans, result.bag_path,
                                      result.gt_csv_path))
            if progress is not None:
                progress(f'{scenario}-{seed}')
    return sequences


def method_config(base: GftOdomConfig, method: str) -> GftOdomConfig:
    """The base config with the method's registration mode and filter switch."""
    if method not in ALL_METHODS:
        raise ConfigError(f'unknown bench method {method!r}; choose from {list(ALL_METHODS)}')
    _, mode, use_filter = ALL_METHODS[method]
    if mode is None:
        return with_values(base, {'pipeline.use_spectral_filter': False})
    return with_values(base, {'registration.mode': mode,
                              'pipeline.use_spectral_filter': use_filter})


def _no_map_update() -> None:
    """A peer updates its map inside its per-scan call: nothing is left after the pose."""
    return None


def _make_odometry(method: str, config: GftOdomConfig, kiss_config: KissIcpConfig):
    """(step, update_map): a callable scan -> (stamp_ns, T_world_sensor, n_points_in,
    n_points_kept, status), or None for a scan the pipeline's acceptance rejected (as the
    node would); and the callable that does the map work left after the pose."""
    if method in PEERS:
        peer = EvalioOdometry(PEERS[method][0], lidar=PEER_LIDAR)

        def step(scan):
            frame = peer.register_frame(scan)
            return frame.stamp_ns, frame.T_world_sensor, len(scan), frame.n_points_kept, 'ok'
        return step, _no_map_update
    if method in GENZ_CONFIGS or METHODS[method][1] is None:
        kiss = (GenzIcpOdometry(GENZ_CONFIGS[method]) if method in GENZ_CONFIGS
                else KissIcpOdometry(kiss_config))

        def step(scan):
            frame = kiss.register_frame(scan)
            return frame.stamp_ns, frame.T_world_sensor, len(scan), frame.n_points_kept, 'ok'
        return step, _no_map_update
    pipeline = OdometryPipeline(config, record_trajectory=False)

    def step(scan):
        r = pipeline.register_frame(scan)
        if not r.accepted:
            return None
        return r.stamp_ns, r.T_world_sensor, r.n_points_in, r.n_points_kept, r.status
    return step, pipeline.update_map


def run_method(method: str, sequence: BenchSequence, base_config: GftOdomConfig,
               kiss_config: KissIcpConfig = KissIcpConfig(), max_scans: int | None = None,
               ground_truth: Trajectory | None = None, paced: bool = False) -> MethodRun:
    """Replay `sequence` through `method`, timing read + decode + the per-scan call up to
    the pose, and apart the map work a method leaves after it.

    `paced`: each scan is handed over no earlier than its stamp says it arrives (the
    sensor's rate, as on the robot), and its latency runs from that arrival: a scan waits
    while the work before it (a map update too, and a thread's share of the cores) is not
    done. The latency metrics are then measured at the sensor's rate, not modelled."""
    config = method_config(base_config, method)
    step, update_map = _make_odometry(method, config, kiss_config)
    if ground_truth is None:
        ground_truth = read_ground_truth(sequence.gt_path)
    stamps, poses, latency, points_in, points_kept, statuses = [], [], [], [], [], []
    map_update = []
    origin_s: float | None = None  # paced: the wall time scan stamp 0 arrives at
    first_stamp_ns = 0
    with ScanBagReader([sequence.bag_path]) as reader:
        for scan, t_decode in timed_scans(reader, scan_count(reader, max_scans)):
            arrival_s = None
            if paced:
                if origin_s is None:
                    origin_s, first_stamp_ns = time.perf_counter(), scan.stamp_ns
                # A stamp going back (a corrupted bag) arrives at once.
                arrival_s = origin_s + max(scan.stamp_ns - first_stamp_ns, 0) * 1e-9
                early_s = arrival_s - time.perf_counter()
                if early_s > 0.0:
                    time.sleep(early_s)
            t0 = time.perf_counter()
            out = step(scan)
            if out is None:
                continue
            stamp_ns, T_world_sensor, n_in, n_kept, status = out
            t_pose = time.perf_counter()
            latency.append(t_decode + t_pose - (t0 if arrival_s is None else arrival_s))
            update_map()
            map_update.append(time.perf_counter() - t_pose)
            stamps.append(stamp_ns)
            poses.append(T_world_sensor)
            points_in.append(n_in)
            points_kept.append(n_kept)
            statuses.append(status)
        skipped = reader.skipped
    sensor = Trajectory(np.array(stamps, dtype=np.int64), np.array(poses).reshape(-1, 4, 4))
    T_base_sensor = base_to_sensor(config)
    base = Trajectory(sensor.stamps_ns, sensor_to_base_poses(sensor.poses, T_base_sensor))
    replay = ReplayResult(
        sensor_trajectory=sensor, base_trajectory=base, latency_s=np.asarray(latency),
        stage_s={}, points_in=np.asarray(points_in), points_kept=np.asarray(points_kept),
        statuses=statuses, skipped_messages=skipped, ground_truth=ground_truth,
        ground_truth_is_gps=True, map_update_s=np.asarray(map_update),
        # Paced, the latency is already at the sensor's rate: no model of it on top.
        scan_stamps_ns=None if paced else np.array(stamps, dtype=np.int64))
    metrics = summarize(replay, config)
    metrics['paced'] = paced
    metrics['method'] = method
    metrics['sequence'] = sequence.name
    metrics['scenario'] = sequence.scenario
    metrics['seed'] = sequence.seed
    if method in PEERS:
        metrics.update(peer_metadata(PEERS[method][0]), use_spectral_filter=False,
                       band_mask=None, n_bands=None)
    elif method in GENZ_CONFIGS:
        genz = GENZ_CONFIGS[method]
        metrics.update(registration_mode='genz-icp', pipeline_version=genz_icp_version(),
                       pipeline_params={'deskew': genz.deskew}, use_spectral_filter=False,
                       band_mask=None, n_bands=None)
    elif METHODS[method][1] is None:
        metrics.update(registration_mode='kiss-icp', use_spectral_filter=False,
                       band_mask=None, n_bands=None)
    replay.metrics = metrics
    return MethodRun(method, sequence, replay, config)


def run_bench(sequences: Sequence[BenchSequence], base_config: GftOdomConfig,
              methods: Sequence[str] = tuple(METHODS),
              kiss_config: KissIcpConfig = KissIcpConfig(),
              progress: Callable[[str, str, int, int], None] | None = None) -> BenchRun:
    """Every method on every sequence, interleaved per sequence so load drifts hit all alike."""
    for method in methods:
        method_config(base_config, method)  # fail before any work on a bad name/config
    kiss_config.validate()
    bench = BenchRun(list(sequences))
    total = len(sequences) * len(methods)
    for sequence in sequences:
        ground_truth = read_ground_truth(sequence.gt_path)
        for method in methods:
            run = run_method(method, sequence, base_config, kiss_config,
                             ground_truth=ground_truth)
            bench.runs.append(run)
            log.info('%s on %s: ATE RMSE %s m, latency median %.1f ms', method, sequence.name,
                     _fmt(run.metrics.get('ate_rmse_m')), run.metrics['latency_median_ms'])
            if progress is not None:
                progress(method, sequence.name, len(bench.runs), total)
    return bench


def _fmt(value) -> str:
    return 'n/a' if value is None else f'{value:.3f}'


def profile_method(method: str, sequence: BenchSequence, base_config: GftOdomConfig,
                   kiss_config: KissIcpConfig = KissIcpConfig(), max_scans: int = 30,
                   top: int = 18) -> str:
    """cProfile of one method over the first `max_scans` scans: the top functions by own time.

    Separate from the timed runs (the profiler's overhead would distort their latency).
    """
    profiler = cProfile.Profile()
    profiler.enable()
    run_method(method, sequence, base_config, kiss_config, max_scans=max_scans)
    profiler.disable()
    text = io.StringIO()
    stats = pstats.Stats(profiler, stream=text)
    stats.sort_stats('tottime').print_stats(top)
    lines = [line for line in text.getvalue().splitlines() if line.strip()]
    # Drop pstats' preamble up to the column header; shorten the site-packages paths.
    start = next((i for i, line in enumerate(lines) if 'ncalls' in line), 0)
    out = [lines[0].strip()] + lines[start:]
    prefixes = (str(Path(np.__file__).parents[1]) + '/', str(Path(__file__).parents[2]) + '/')
    for prefix in prefixes:
        out = [line.replace(prefix, '') for line in out]
    return '\n'.join(out)
