"""Bag replay harness: recorded scans through the same pipeline the node runs, in-process.

Deterministic (no DDS, no clock): the scans go one by one through `OdometryPipeline`. Results go
to a folder like kiss-icp's: TUM poses, metrics, the effective config and figures. Every file is
written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from gft_odom.config import GftOdomConfig
from gft_odom.core.geometry import transform_points
from gft_odom.core.localisation import MapLocalisation, PriorMap, planar_pose
from gft_odom.core.metrics import TrajectoryEvaluator, stamp_audit
from gft_odom.core.spectral.bands import band_of_nu
from gft_odom.core.trajectory import Trajectory
from gft_odom.core.types import Scan
from gft_odom.errors import BagError, GftOdomError, GroundTruthError, MapError, RegistrationError
from gft_odom.io.atomic import make_temp_dir, replace, write_text_atomic
from gft_odom.io.bags import ScanBagReader
from gft_odom.io.ground_truth import read_ground_truth
from gft_odom.io.pcd import PcdError, frequency_cloud, read_pcd, read_pcd_frame_id, write_pcd
from gft_odom.io.tum import write_tum
from gft_odom.params_file import write_params_file
from gft_odom.pipeline import FrameResult, OdometryPipeline

log = logging.getLogger(__name__)

MAP_POINTS_PER_SCAN = 1500


@dataclass
class ReplayResult:
    """Trajectories, per-scan statistics and (with ground truth) the metrics of one replay."""

    sensor_trajectory: Trajectory
    base_trajectory: Trajectory
    latency_s: np.ndarray  # (n_scans,) decode + pipeline: the time to the pose
    stage_s: dict[str, np.ndarray]
    points_in: np.ndarray
    points_kept: np.ndarray
    statuses: list[str]
    metrics: dict = field(default_factory=dict)
    map_points_world: np.ndarray | None = None  # (M, 3) sample for figures
    map_nu: np.ndarray | None = None  # (M,) nan when the filter is off
    skipped_messages: int = 0
    # Scans refused by the pipeline's acceptance, by reason (empty, out_of_order, ...).
    rejected: dict[str, int] = field(default_factory=dict)
    ground_truth: Trajectory | None = None
    ground_truth_is_gps: bool = False
    # With a map to localise in: T_map_sensor of every scan localised or carried by the
    # odometry from the last fit, and how many of each (localised, not_fitted, ...).
    map_trajectory: Trajectory | None = None
    localisation_counts: dict[str, int] = field(default_factory=dict)
    # (n_scans,) the work after each pose (`OdometryPipeline.update_map`: the frequencies
    # when they come after it, a keyframe's map rebuild); None when the method does it
    # inside its time to the pose.
    map_update_s: np.ndarray | None = None
    # (n_scans,) each latency's scan stamp: the latency at the sensor's rate needs them.
    scan_stamps_ns: np.ndarray | None = None


def scan_count(reader: ScanBagReader, max_scans: int | None) -> int:
    """Scans a replay will take from `reader` (for progress bars)."""
    return len(reader) if max_scans is None else min(len(reader), max_scans)


def timed_scans(reader: ScanBagReader, count: int) -> Iterator[tuple[Scan, float]]:
    """The first `count` scans of `reader`, each with the seconds spent reading and decoding
    it: every replay front end times the same way."""
    scans = iter(reader)
    for _ in range(count):
        t0 = time.perf_counter()
        try:
            scan = next(scans)
        except StopIteration:
            return
        yield scan, time.perf_counter() - t0


def is_gps_ground_truth(path: str | Path) -> bool:
    """CitrusFarm gt.csv / gt.bag hold the GPS antenna; a TUM file holds the sensor pose."""
    return Path(path).suffix.lower() not in ('.txt', '.tum')


def run_replay(bag_paths: Sequence[str | Path], config: GftOdomConfig,
               gt_path: str | Path | None = None, topic: str = '/velodyne_points',
               max_scans: int | None = None,
               progress: Callable[[int, int], None] | None = None,
               save_map_dir: str | Path | None = None,
               pipeline: OdometryPipeline | None = None) -> ReplayResult:
    """Replay the scans of `bag_paths` through the pipeline; evaluate against `gt_path`.
    `save_map_dir`: write the final map and the trajectory there (`write_map`), as the
    node's `~/save_map` does. `pipeline`: a study's own (a subclass, built from `config`);
    None: `OdometryPipeline(config)`. With `localisation.map_file` every scan is also
    localised in that map, from `localisation.initial_pose_xy_yaw`."""
    ground_truth = read_ground_truth(gt_path) if gt_path is not None else None
    pipeline = pipeline if pipeline is not None else OdometryPipeline(config)
    localisation = map_localisation(config, pipeline.T_base_sensor)
    rng = np.random.default_rng(0)
    latency, map_update, stamps, points_in, points_kept, statuses = [], [], [], [], [], []
    stages: dict[str, list[float]] = {}
    map_xyz, map_nu = [], []
    map_stamps, map_poses, located = [], [], Counter()
    rejected: Counter[str] = Counter()
    with ScanBagReader(list(bag_paths), topic=topic) as reader:
        total = scan_count(reader, max_scans)
        for i, (scan, t_decode) in enumerate(timed_scans(reader, total)):
            result = pipeline.register_frame(scan)
            if progress is not None:
                progress(i + 1, total)
            if not result.accepted:
                log.warning('%s', result.rejection.text)
                rejected[result.rejection.reason] += 1
                continue
            latency.append(t_decode + result.timings_s['pipeline'])
            if localisation is not None:
                fit = localisation.localise(pipeline.registration.deskewed_like_last(
                    result.filtered.points_xyz), result.T_world_sensor, result.nu)
                if fit is not None:
                    located[fit.status] += 1
                    map_stamps.append(result.stamp_ns)
                    map_poses.append(fit.T_map_sensor)
            # The work after the pose, as the node does it (frequencies left for after the
            # pose, a keyframe's map rebuild): busy time; its stages go into timings_s.
            map_update.append(pipeline.update_map())
            stamps.append(result.stamp_ns)
            for name, value in {'decode': t_decode, **result.timings_s}.items():
                stages.setdefault(name, []).append(value)
            points_in.append(result.n_points_in)
            points_kept.append(result.n_points_kept)
            statuses.append(result.status)
            _sample_map(result, rng, map_xyz, map_nu)
        skipped = getattr(reader, 'skipped', 0)
    if not statuses:
        # Nothing to evaluate or write: an empty results folder would look like a success.
        raise BagError(f'no decodable scan on {topic} in {", ".join(map(str, bag_paths))} '
                       f'({skipped} message(s) skipped as malformed, '
                       f'{sum(rejected.values())} rejected)')
    if pipeline.finished_segments:
        log.warning('the clock went back %d time(s): results are for the last run of the '
                    'odometry (%d of %d registered scans)', len(pipeline.finished_segments),
                    len(pipeline.sensor_trajectory()), len(statuses))
    replay = ReplayResult(
        sensor_trajectory=pipeline.sensor_trajectory(),
        base_trajectory=pipeline.base_trajectory(),
        latency_s=np.asarray(latency), stage_s={k: np.asarray(v) for k, v in stages.items()},
        points_in=np.asarray(points_in), points_kept=np.asarray(points_kept), statuses=statuses,
        map_points_world=np.concatenate(map_xyz) if map_xyz else np.zeros((0, 3)),
        map_nu=np.concatenate(map_nu) if map_nu else np.zeros(0), skipped_messages=skipped,
        rejected=dict(rejected), ground_truth=ground_truth,
        ground_truth_is_gps=gt_path is not None and is_gps_ground_truth(gt_path),
        map_update_s=np.asarray(map_update), scan_stamps_ns=np.asarray(stamps, dtype=np.int64),
        map_trajectory=(Trajectory(np.asarray(map_stamps, dtype=np.int64), np.asarray(map_poses))
                        if map_stamps else None),
        localisation_counts=dict(located))
    replay.metrics = summarize(replay, config)
    # Said once in the log when it happened; kept with the results.
    replay.metrics['motion_bounds'] = pipeline.bounds_watch.message
    if save_map_dir is not None:
        points, nu = pipeline.map_snapshot()
        pcd, tum = write_map(save_map_dir, points, nu, config.spectral.n_bands,
                             pipeline.base_trajectory(), config.node.odom_frame)
        replay.metrics['saved_map'] = {'pcd': str(pcd), 'trajectory': str(tum),
                                       'points': int(points.shape[0])}
        log.info('map of %d points written to %s, trajectory to %s', points.shape[0], pcd, tum)
    return replay


def _sample_map(result: FrameResult, rng, map_xyz: list, map_nu: list) -> None:
    n = result.n_points_kept
    if n == 0:
        return
    pick = rng.choice(n, size=min(n, MAP_POINTS_PER_SCAN), replace=False)
    map_xyz.append(transform_points(result.T_world_sensor, result.filtered.points_xyz[pick]))
    map_nu.append(result.nu[pick] if result.nu is not None else np.full(pick.size, np.nan))


def estimate_for_ground_truth(replay: ReplayResult, config: GftOdomConfig) -> Trajectory:
    """The estimated trajectory of the frame the ground truth measures (antenna or sensor)."""
    if replay.ground_truth_is_gps:
        return replay.sensor_trajectory.with_body_offset(config.ground_truth.T_lidar_gps())
    return replay.sensor_trajectory


def latency_at_rate_s(stamps_ns: np.ndarray, latency_s: np.ndarray,
                      busy_s: np.ndarray) -> np.ndarray:
    """Each scan's latency had the scans arrived at their stamps (the sensor's rate) to one
    worker: the wait until the work of the scans before it (`busy_s`: each one's time to
    the pose and its map update) is done, plus its own time to the pose.

    A replay runs as fast as it can, so its latency is never delayed by a queue; on a robot
    a scan whose predecessor's work overran the sensor period waits."""
    arrival_s = (np.asarray(stamps_ns, dtype=np.int64) - int(stamps_ns[0])) * 1e-9
    out = np.empty(arrival_s.shape[0])
    free_s = arrival_s[0]
    for i, (arrive, latency, busy) in enumerate(zip(arrival_s, latency_s, busy_s)):
        start = max(arrive, free_s)  # a clock jump back cannot make the worker idle
        out[i] = start - arrive + latency
        free_s = start + busy
    return out


def timing_metrics(replay: ReplayResult) -> dict:
    """Latency (time to the pose), the busy time per scan (with the map update after it)
    and the latency at the sensor's rate, in ms: median, p95 (and the busy time's mean)."""
    lat_ms = 1e3 * replay.latency_s
    n = int(lat_ms.size)
    if not n:
        return {'latency_median_ms': None, 'latency_p95_ms': None}
    metrics = {'latency_median_ms': float(np.median(lat_ms)),
               'latency_p95_ms': float(np.percentile(lat_ms, 95))}
    busy_s = replay.latency_s
    if replay.map_update_s is not None and replay.map_update_s.shape[0] == n:
        busy_s = replay.latency_s + replay.map_update_s
        # The map's own work where the stages tell it apart from the frequencies after the
        # pose (a replay), else all the work after the pose (the benchmark runner).
        map_s = replay.stage_s.get('map_update', replay.map_update_s)
        metrics['map_update_p95_ms'] = float(np.percentile(1e3 * np.asarray(map_s), 95))
    metrics.update({'busy_median_ms': float(np.median(1e3 * busy_s)),
                    'busy_p95_ms': float(np.percentile(1e3 * busy_s, 95)),
                    'busy_mean_ms': float(np.mean(1e3 * busy_s))})
    if replay.scan_stamps_ns is not None and replay.scan_stamps_ns.shape[0] == n:
        at_rate_ms = 1e3 * latency_at_rate_s(replay.scan_stamps_ns, replay.latency_s, busy_s)
        metrics.update({'latency_at_rate_median_ms': float(np.median(at_rate_ms)),
                        'latency_at_rate_p95_ms': float(np.percentile(at_rate_ms, 95))})
    return metrics


def summarize(replay: ReplayResult, config: GftOdomConfig) -> dict:
    """Flat JSON-friendly metrics: accuracy (with ground truth), latency, points, failures."""
    lat_ms = 1e3 * replay.latency_s
    n = int(lat_ms.size)
    valid = replay.points_kept >= 0  # -1: not known (a lost best-effort cloud)
    kept = replay.points_kept[valid]
    metrics: dict = {
        'n_scans': n,
        'use_spectral_filter': config.pipeline.use_spectral_filter,
        'registration_mode': config.registration.mode,
        'band_mask': list(config.spectral.band_mask),
        'n_bands': config.spectral.n_bands,
        **timing_metrics(replay),
        'points_in_mean': float(replay.points_in.mean()) if n else 0.0,
        'points_kept_mean': float(kept.mean()) if kept.size else 0.0,
        'points_kept_fraction': (float(kept.sum() / max(replay.points_in[valid].sum(), 1))
                                 if kept.size else 0.0),
        'fallbacks': int(sum(s.startswith('fallback') for s in replay.statuses)),
        # Why: fallback_too_few_points / _low_fitness / _diverged / _degenerate (flat cloud).
        'status_counts': {s: replay.statuses.count(s) for s in sorted(set(replay.statuses))},
        'skipped_messages': int(replay.skipped_messages),
        'rejected_scans': {k: int(v) for k, v in sorted(replay.rejected.items())},
    }
    for stage, values in replay.stage_s.items():
        metrics[f'{stage}_median_ms'] = float(np.median(values) * 1e3)
    duration_s = (replay.sensor_trajectory.stamps_s[-1] - replay.sensor_trajectory.stamps_s[0]
                  if n > 1 else float('nan'))
    busy_s = float(replay.latency_s.sum() + (0.0 if replay.map_update_s is None
                                             else replay.map_update_s.sum()))
    metrics['real_time_factor'] = (float(duration_s / busy_s)
                                   if n > 1 and busy_s > 0 else None)
    if replay.ground_truth is not None:
        estimate = estimate_for_ground_truth(replay, config)
        try:
            metrics.update(TrajectoryEvaluator.from_config(config.evaluation)
                           .evaluate(estimate, replay.ground_truth))
        except GroundTruthError as exc:
            raise GroundTruthError(f'cannot evaluate against the ground truth: {exc}') from exc
        metrics['ground_truth_frame'] = 'gps_antenna' if replay.ground_truth_is_gps else 'sensor'
        metrics.update(stamp_audit_metrics(estimate, replay.ground_truth, config))
    if replay.map_trajectory is not None:
        metrics['localisation'] = _localisation_metrics(replay, config)
    return metrics


def _localisation_metrics(replay: ReplayResult, config: GftOdomConfig) -> dict:
    """How many scans were localised, and (with ground truth) the map-frame trajectory's ATE."""
    out: dict = {'status_counts': dict(sorted(replay.localisation_counts.items()))}
    if replay.ground_truth is not None:
        in_map = replay.map_trajectory
        if replay.ground_truth_is_gps:
            in_map = in_map.with_body_offset(config.ground_truth.T_lidar_gps())
        result = TrajectoryEvaluator.from_config(config.evaluation).evaluate(
            in_map, replay.ground_truth)
        out.update({k: v for k, v in result.items() if k.startswith(('ate_', 'end_error'))})
    return out


def stamp_audit_metrics(estimate: Trajectory, ground_truth: Trajectory,
                        config: GftOdomConfig) -> dict:
    """Where the poses hold: the stamp shift (ms) that scores best, and the ATE RMSE at each
    shift (`core.metrics.stamp_audit`); None when too few poses overlap at every shift."""
    try:
        audit = stamp_audit(estimate, ground_truth, max_gap_s=config.evaluation.max_gap_s)
    except GroundTruthError:
        return {'stamp_best_shift_ms': None, 'stamp_audit': None}
    return {'stamp_best_shift_ms': round(1e3 * audit.best_shift_s, 3),
            'stamp_audit': {'shifts_ms': [round(1e3 * v, 3) for v in audit.shifts_s],
                            'ate_rmse_m': [float(v) for v in audit.rmse_m]}}


MAP_FILE = 'map.pcd'
MAP_TRAJECTORY_FILE = 'trajectory_tum.txt'


def write_map(folder: str | Path, points_xyz: np.ndarray, nu: np.ndarray, n_bands: int,
              trajectory: Trajectory, frame_id: str = 'odom') -> tuple[Path, Path]:
    """The map as a binary PCD (x y z intensity frequency band; frequency NaN and band 0
    where unknown; its header names `frame_id`) and the trajectory as TUM, both in the odom
    frame, into `folder`: (pcd path, TUM path). `OdometryPipeline.map_snapshot` gives the
    points and frequencies; `read_prior_map` reads the map back to localise in it."""
    folder = Path(folder).expanduser()
    folder.mkdir(parents=True, exist_ok=True)
    nu = np.asarray(nu, dtype=np.float32)
    write_pcd(folder / MAP_FILE, frequency_cloud(points_xyz, None, nu, band_of_nu(nu, n_bands)),
              frame_id=frame_id)
    write_tum(folder / MAP_TRAJECTORY_FILE, trajectory)
    return folder / MAP_FILE, folder / MAP_TRAJECTORY_FILE


def map_localisation(config: GftOdomConfig, T_base_sensor: np.ndarray
                     ) -> MapLocalisation | None:
    """Localisation in `localisation.map_file` from `localisation.initial_pose_xy_yaw` (None
    without a map file); MapError when the map cannot serve."""
    cfg = config.localisation
    if not cfg.map_file:
        return None
    localisation = MapLocalisation(read_prior_map(cfg.map_file, config.node.odom_frame),
                                   T_base_sensor)
    localisation.start_at(planar_pose(*cfg.initial_pose_xy_yaw))
    return localisation


def read_prior_map(path: str | Path, frame_id: str = 'odom') -> PriorMap:
    """A map `write_map` wrote (`~/save_map`, `replay --save-map`), ready to localise in.
    MapError names what is wrong: no such file, not a PCD, no points, or points in another
    frame than `frame_id` (a map is saved in its run's odom frame)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise MapError(f'map file {path} does not exist')
    try:
        cloud = read_pcd(path)
        frame = read_pcd_frame_id(path)
    except PcdError as exc:
        raise MapError(f'map file {path} cannot be read: {exc}') from None
    if frame != frame_id:
        raise MapError(f'map file {path} is in frame {frame!r}, not {frame_id!r}: a map saved '
                       "by ~/save_map or replay --save-map is in its run's odom frame")
    if not {'x', 'y', 'z'} <= set(cloud.dtype.names or ()):
        raise MapError(f'map file {path} has no x, y, z fields')
    points = np.column_stack([cloud['x'], cloud['y'], cloud['z']]).astype(np.float64)
    nu = (cloud['frequency'].astype(np.float32) if 'frequency' in cloud.dtype.names
          else np.full(points.shape[0], np.nan, dtype=np.float32))
    finite = np.isfinite(points).all(axis=1)
    try:
        return PriorMap(points[finite], nu[finite])
    except RegistrationError as exc:
        raise MapError(f'map file {path}: {exc}') from None


def write_json(path: Path, data: dict) -> None:
    """Write `data` as indented JSON, atomically."""
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True) + '\n')


def write_results(replay: ReplayResult, config: GftOdomConfig, out_dir: str | Path,
                  figures: bool = True) -> dict[str, Path]:
    """The results folder: TUM poses, metrics.json, config.yaml and (optionally) PNGs.

    All-or-nothing: every file is first written into a sibling `<out>.partial-XXXX` folder.
    A new `out` is that folder renamed (one atomic step); into an existing `out` (which may
    hold other files) each file is moved with an atomic rename, `metrics.json` last, so a
    complete metrics.json means a complete run. On any failure the partial folder is removed
    and `out` is left as it was; a hard kill can leave only the `.partial-XXXX` folder.
    """
    out = Path(out_dir)
    names = {
        'trajectory': 'trajectory_tum.txt',
        'sensor_trajectory': 'trajectory_sensor_tum.txt',
        'map_trajectory': 'trajectory_map_tum.txt',
        'config': 'config.yaml',
        'trajectory_png': 'trajectory.png',
        'map_png': 'map.png',
        'metrics': 'metrics.json',  # last: its presence marks a complete folder
    }
    if replay.map_trajectory is None:
        del names['map_trajectory']
    if not figures:
        del names['trajectory_png'], names['map_png']
    elif replay.map_points_world is None:  # through the node: no per-scan clouds kept
        del names['map_png']
    try:
        if out.exists() and not out.is_dir():
            raise GftOdomError(f'results folder {out} exists and is not a folder')
        out.parent.mkdir(parents=True, exist_ok=True)
        partial = make_temp_dir(out.parent, prefix=f'{out.name}.partial-')
    except OSError as exc:
        raise GftOdomError(f'cannot create results folder {out}: {exc}') from exc
    try:
        tmp = {key: partial / name for key, name in names.items()}
        write_tum(tmp['trajectory'], replay.base_trajectory)
        write_tum(tmp['sensor_trajectory'], replay.sensor_trajectory)
        if 'map_trajectory' in tmp:
            write_tum(tmp['map_trajectory'], replay.map_trajectory)
        write_params_file(tmp['config'], config,
                          header='Effective configuration of this run (ROS params-file format).')
        if figures:
            from gft_odom.figures import plot_map, plot_trajectory
            estimate = estimate_for_ground_truth(replay, config)
            plot_trajectory(tmp['trajectory_png'], estimate, replay.ground_truth, replay.metrics)
            if 'map_png' in tmp:
                plot_map(tmp['map_png'], replay.map_points_world, replay.map_nu,
                         replay.sensor_trajectory)
        write_json(tmp['metrics'], replay.metrics)
        if out.exists():
            for key in names:  # dict order: metrics.json last
                replace(tmp[key], out / names[key])
            partial.rmdir()
        else:
            replace(partial, out)
    except OSError as exc:
        shutil.rmtree(partial, ignore_errors=True)
        raise GftOdomError(f'cannot write results to {out}: {exc}') from exc
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return {key: out / name for key, name in names.items()}
