"""Where does the along-row bias come from? An oracle harness on the simulator.

The local map is built from TRUE poses (keyframes every 1 m / 0.2 rad, the registration's
0.4 m points, 0.3 m map voxels keeping the oldest point, 60 keyframes: what the default
pipeline builds, without its pose errors), every test scan is registered starting AT THE
TRUTH, and the signed error of the result is measured in the robot's along-track axis (the
path tangent), across it (lateral) and in yaw. Whatever comes out is the registration's own
bias against a perfect map: the drift the odometry adds one map renewal at a time.

Variants (registration from the truth unless an initial offset is named):
- surface classes: all source points, only ground / trunk / canopy / non-canopy ones;
- scans and map: motion-distorted as the sensor gives them (the pipeline's default, deskew
  off), perfectly deskewed with the simulator's true pose at every firing (scan and map), and
  the distorted map keeping the newest point per voxel instead of the oldest;
- solvers: open3d point-to-plane ICP as `IcpBackend.register` (core/icp_backend.py) runs it
  (Tukey 0.3 m, relative criteria 1e-4, 30 iterations), the same run to 1e-10 / 100
  iterations, the Gauss-Newton solver (`core/gauss_newton.py`) with the plane model
  (update < 1e-4, and < 1e-5) and with the 'frequency' model (smoothness from the scan
  point's nu);
- initial guess moved +-0.1 / 0.2 m along the track: does ICP come back, or stay near it?
- the pull of each class at the truth: the along-track step that the class's point-to-plane
  rows alone ask for (-sum w r n_a / sum w n_a^2 over all pairs), trunks split into those
  ahead of the sensor and those beside or behind it.
And the ground-truth timing: ATE of the perfect trajectory (the truth at the scan stamps)
against the simulator's GPS track (10 Hz at a 37 ms phase) with `match: nearest` and
`interpolate`.

Training seeds only (111 lawnmower, 113 every_other_row, 112 spiral, 114 out_and_back).
Writes benchmarks/results/bias_study.json and docs/bias_study.png.

Run: .venv/bin/python benchmarks/bias_study.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from gft_odom.config import PipelineConfig
from gft_odom.core.constants import NS_PER_S
from gft_odom.core.gauss_newton import GaussNewtonICP
from gft_odom.core.geometry import transform_points
from gft_odom.core.local_map import LocalMap, voxel_downsample_indices
from gft_odom.core.metrics import ate
from gft_odom.core.registration import RegistrationConfig, local_map_from_config
from gft_odom.core.residuals import PlaneResidual, SmoothnessResidual, smoothness_from_nu
from gft_odom.core.spectral import SpectralFilter
from gft_odom.core.trajectory import Trajectory
from gft_odom.sim.orchard import CANOPY, GROUND, TRUNK
from gft_odom.sim.simulator import ScanSimulator, SimConfig
from gft_odom.sim.writer import GPS_PHASE_S

o3d_reg = o3d.pipelines.registration
ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'benchmarks' / 'results' / 'bias_study.json'
FIGURE = ROOT / 'docs' / 'bias_study.png'
DRIVES = (('lawnmower', 111), ('every_other_row', 113), ('spiral', 112), ('out_and_back', 114))
CLASSES = ('ground', 'trunk', 'canopy', 'noncanopy')
# Map kind -> (which scans build it, which point a voxel keeps): the oldest point (the
# pipeline's), the newest, or the mean of every keyframe's point in the voxel (session 14:
# all the views, not the first).
MAPS = {'distorted': ('distorted', 'oldest'), 'deskewed': ('deskewed', 'oldest'),
        'newest': ('distorted', 'newest'), 'mean': ('distorted', 'mean'),
        'deskewed_mean': ('deskewed', 'mean')}
OFFSETS_M = (-0.2, -0.1, 0.1, 0.2)
# A scan is on a straight segment when the path heading turns less than this within +-1.5 s.
STRAIGHT_RAD = 0.02
STRAIGHT_WINDOW_S = 1.5
MIN_SPEED_MPS = 0.3


@dataclass(frozen=True)
class Variant:
    """One registration of a test scan: solver, scan/map kind, source class, guess offset."""

    name: str
    solver: str = 'o3d'  # o3d | o3d_tight | gn_plane | gn_plane_tight | gn_freq
    map_kind: str = 'distorted'
    points: str = 'all'  # all | ground | trunk | canopy | noncanopy
    offset_m: float = 0.0  # initial guess moved along the track
    every: int = 1  # run on every n-th test scan only (the offset runs)


def default_variants() -> list[Variant]:
    """The study's registrations (~15 per test scan)."""
    out = [Variant('o3d'), Variant('o3d_tight', 'o3d_tight'), Variant('gn_plane', 'gn_plane'),
           Variant('gn_plane_tight', 'gn_plane_tight'), Variant('gn_freq', 'gn_freq'),
           Variant('deskewed', map_kind='deskewed'), Variant('newest', map_kind='newest'),
           Variant('mean', map_kind='mean'), Variant('deskewed_mean', map_kind='deskewed_mean'),
           Variant('deskewed_mean_canopy', map_kind='deskewed_mean', points='canopy')]
    out += [Variant(f'o3d_{c}', points=c) for c in CLASSES]
    out += [Variant(f'deskewed_{c}', map_kind='deskewed', points=c)
            for c in ('canopy', 'noncanopy')]
    for solver in ('o3d', 'o3d_tight', 'gn_plane'):
        for off in OFFSETS_M:
            out.append(Variant(f'{solver}_from_{off:+.1f}', solver, offset_m=off, every=4))
    return out


def reversal_variants() -> list[Variant]:
    """What the time-reversed run (a map seen from ahead) repeats."""
    return [Variant('o3d'), Variant('deskewed', map_kind='deskewed'),
            Variant('o3d_canopy', points='canopy'),
            Variant('deskewed_canopy', map_kind='deskewed', points='canopy'),
            Variant('deskewed_noncanopy', map_kind='deskewed', points='noncanopy'),
            Variant('gn_freq', 'gn_freq'), Variant('mean', map_kind='mean'),
            Variant('deskewed_mean', map_kind='deskewed_mean'),
            Variant('deskewed_mean_canopy', map_kind='deskewed_mean', points='canopy')]


def row_axes(sim: ScanSimulator, t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit along-track (path tangent) and left vectors in the world, horizontal."""
    m = sim.motion
    s = m._s_at(np.array([t_s]))
    heading = float(np.interp(s, m.s_m, m.heading_rad)[0]) + m.orchard.heading_rad
    along = np.array([np.cos(heading), np.sin(heading), 0.0])
    return along, np.array([-along[1], along[0], 0.0])


def is_straight(sim: ScanSimulator, t_s: float) -> bool:
    """Driving (> 0.3 m/s) on a piece whose path heading is steady for +-1.5 s."""
    m = sim.motion
    t = np.array([t_s - STRAIGHT_WINDOW_S, t_s, t_s + STRAIGHT_WINDOW_S, t_s + 0.1])
    s = m._s_at(t)
    heading = np.interp(s[:3], m.s_m, m.heading_rad)
    speed = (s[3] - s[1]) / 0.1
    return bool(np.ptp(heading) < STRAIGHT_RAD and speed > MIN_SPEED_MPS)


def pose_error(T_est: np.ndarray, T_true: np.ndarray, along: np.ndarray,
               left: np.ndarray) -> tuple[float, float, float]:
    """Signed (along-track m, lateral m, yaw rad) of an estimate against the truth."""
    e = T_est[:3, 3] - T_true[:3, 3]
    yaw = Rotation.from_matrix(T_true[:3, :3].T @ T_est[:3, :3]).as_rotvec()
    yaw_world = float((T_true[:3, :3] @ yaw)[2])
    return float(e @ along), float(e @ left), yaw_world


def exact_deskew(sim: ScanSimulator, points_xyz: np.ndarray, time_offset_s: np.ndarray,
                 index: int) -> np.ndarray:
    """Every point in the sensor frame at the stamp, from the true pose of its firing."""
    t0 = index / sim.config.scan_rate_hz
    offsets, inverse = np.unique(time_offset_s, return_inverse=True)
    T = sim.sensor_poses(np.concatenate([[t0], t0 + offsets.astype(float)]))
    T_stamp_fire = np.linalg.inv(T[0])[None] @ T[1:]
    Ti = T_stamp_fire[inverse.reshape(-1)]
    return np.einsum('nij,nj->ni', Ti[:, :3, :3], points_xyz) + Ti[:, :3, 3]


@dataclass
class TestScan:
    """One scan ready for registration: downsampled points per kind, classes, nu."""

    index: int
    T_true: np.ndarray
    points: dict  # 'distorted' / 'deskewed' -> (n, 3) sensor frame, the 0.4 m points
    surface: np.ndarray  # (n,) surface codes of those points
    smoothness: np.ndarray | None  # (n,) from nu


def prepare_scan(sim: ScanSimulator, index: int, reg: RegistrationConfig,
                 pipe: PipelineConfig, spectral: SpectralFilter | None) -> TestScan:
    """Simulate scan `index`, crop it as the pipeline does, downsample as the registration."""
    s = sim.scan(index)
    scan = s.scan
    r2 = np.einsum('ij,ij->i', scan.points_xyz, scan.points_xyz)
    crop = np.flatnonzero((r2 >= pipe.min_range_m ** 2) & (r2 <= pipe.max_range_m ** 2))
    cropped = scan.select(crop)
    keep = voxel_downsample_indices(cropped.points_xyz, reg.voxel_size_m)
    distorted = cropped.points_xyz[keep]
    deskewed = exact_deskew(sim, distorted, cropped.time_offset_s[keep], index)
    smooth = None
    if spectral is not None:
        nu = spectral.scan_frequencies(cropped).nu
        smooth = smoothness_from_nu(nu[keep], reg.smooth_nu)
    return TestScan(index, s.T_world_sensor,
                    {'distorted': distorted, 'deskewed': deskewed},
                    s.surface[crop][keep], smooth)


def class_mask(surface: np.ndarray, points: str) -> np.ndarray:
    """Which source points a variant registers with."""
    if points == 'all':
        return np.ones(surface.shape[0], bool)
    if points == 'noncanopy':
        return surface != CANOPY
    return surface == {'ground': GROUND, 'trunk': TRUNK, 'canopy': CANOPY}[points]


class Solvers:
    """The registrations compared, all from one RegistrationConfig."""

    def __init__(self, reg: RegistrationConfig):
        self.reg = reg
        self.kernel = o3d_reg.TukeyLoss(reg.robust_kernel_scale_m)
        self.criteria = o3d_reg.ICPConvergenceCriteria(
            relative_fitness=reg.convergence_relative, relative_rmse=reg.convergence_relative,
            max_iteration=reg.max_iterations)
        self.tight = o3d_reg.ICPConvergenceCriteria(relative_fitness=1e-10,
                                                    relative_rmse=1e-10, max_iteration=100)
        scale = reg.robust_kernel_scale_m
        self.gn = {
            'gn_plane': GaussNewtonICP(PlaneResidual(), 'tukey', scale, reg.max_iterations,
                                       reg.convergence_m),
            'gn_plane_tight': GaussNewtonICP(PlaneResidual(), 'tukey', scale, 100, 1e-5),
            'gn_freq': GaussNewtonICP(SmoothnessResidual('frequency', 'beam_perpendicular'),
                                      'tukey', scale, reg.max_iterations, reg.convergence_m)}

    def register(self, solver: str, source: np.ndarray, local_map: LocalMap,
                 init: np.ndarray, smoothness: np.ndarray | None) -> tuple[np.ndarray, int]:
        """(T_world_sensor, iterations) of one registration."""
        d = self.reg.max_correspondence_distance_m
        if solver in self.gn:
            r = self.gn[solver].register(source, local_map.target(), init, d,
                                         smoothness if solver == 'gn_freq' else None)
            return r.transformation, r.n_iterations
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
        criteria = self.tight if solver == 'o3d_tight' else self.criteria
        r = o3d_reg.registration_icp(
            cloud, local_map.cloud, d, init,
            o3d_reg.TransformationEstimationPointToPlane(self.kernel), criteria)
        return np.asarray(r.transformation), -1


def class_pulls(source: np.ndarray, surface: np.ndarray, local_map: LocalMap,
                T: np.ndarray, along: np.ndarray, max_distance_m: float,
                scale_m: float) -> dict:
    """Along-track step each group of points asks for at pose T, in metres, and its share of
    the along-track information.

    Pull of group g = -sum_g w r (n . a) / sum_all w (n . a)^2: the 1-D Gauss-Newton step along
    a (point-to-plane, Tukey weights), split by group; the groups' pulls add up to the scan's.
    Groups: surface class (ground, trunk, canopy, other) x where the point is relative to the
    sensor along the track (ahead > 2 m, beside within 2 m, behind < -2 m)."""
    target = local_map.target()
    world = transform_points(T, source)
    dist, idx = target.tree.query(world, distance_upper_bound=max_distance_m)
    ok = np.isfinite(dist)
    n = target.normals_at(idx[ok])
    r = np.einsum('ij,ij->i', n, world[ok] - target.points[idx[ok]])
    u = np.abs(r) / scale_m
    w = np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
    na = n @ along
    info = max(float(np.sum(w * na * na)), 1e-12)
    x = (world[ok] - T[:3, 3]) @ along
    where = {'ahead': x > 2.0, 'beside': np.abs(x) <= 2.0, 'behind': x < -2.0}
    cls = np.where(surface[ok] <= CANOPY, surface[ok], 3)
    out = {}
    for c, cname in enumerate(('ground', 'trunk', 'canopy', 'other')):
        for wname, wsel in where.items():
            g = (cls == c) & wsel
            out[f'{cname}_{wname}'] = float(-np.sum((w * r * na)[g]) / info)
            out[f'info_{cname}_{wname}'] = float(np.sum((w * na * na)[g]) / info)
    return out


def keyframe_schedule(poses: np.ndarray, reg: RegistrationConfig) -> np.ndarray:
    """Indices of the scans the pipeline would make keyframes of (with true poses)."""
    keys = [0]
    for k in range(1, poses.shape[0]):
        T_last = poses[keys[-1]]
        moved = np.linalg.norm(poses[k, :3, 3] - T_last[:3, 3])
        turned = Rotation.from_matrix(T_last[:3, :3].T @ poses[k, :3, :3]).magnitude()
        if moved >= reg.keyframe_distance_m or turned >= reg.keyframe_rotation_rad:
            keys.append(k)
    return np.array(keys)


def oracle_run(sim: ScanSimulator, first: int, last: int, test_every: int,
               variants: list[Variant], reg: RegistrationConfig = RegistrationConfig(),
               with_pulls: bool = True, reverse: bool = False, log=None) -> dict:
    """Register every `test_every`-th scan of [first, last) from the truth against maps of
    true-pose keyframes, built as the pipeline builds them while driving.

    `reverse`: walk the drive backwards in time, so the map holds the keyframes AFTER each
    scan (seen from ahead of it, the farthest first in each voxel): the pipeline's map
    mirrored. The along-track axis stays the direction of travel.
    Returns per test scan: index, straight, since_keyframe_m (along the track from the newest
    keyframe), speed_mps, per variant {along_m, lateral_m, yaw_rad, iterations}, pulls."""
    pipe = PipelineConfig()
    order = np.arange(first, last)[::-1] if reverse else np.arange(first, last)
    poses = sim.sensor_poses(order / sim.config.scan_rate_hz)
    keys = set(order[keyframe_schedule(poses, reg)].tolist())
    maps = {}
    for kind in MAPS:
        maps[kind] = local_map_from_config(reg)
        maps[kind].voxel_keeps = MAPS[kind][1]
    solvers = Solvers(reg)
    spectral = SpectralFilter() if any(v.solver == 'gn_freq' for v in variants) else None
    rows: dict = {'index': [], 'straight': [], 'since_keyframe_m': [], 'speed_mps': []}
    res: dict = {v.name: [] for v in variants}
    pulls: dict = {}
    last_key_T = None
    n_test = 0
    for step, k in enumerate(order):
        test = step > 20 and step % test_every == 0 and last_key_T is not None
        if not (test or k in keys):
            continue
        ts = prepare_scan(sim, int(k), reg, pipe, spectral if test else None)
        t_s = k / sim.config.scan_rate_hz
        if test:
            along, left = row_axes(sim, t_s)
            rows['index'].append(int(k))
            rows['straight'].append(is_straight(sim, t_s))
            rows['since_keyframe_m'].append(float((ts.T_true[:3, 3] - last_key_T[:3, 3])
                                                  @ along))
            p = sim.sensor_poses(np.array([t_s, t_s + 0.1]))[:, :3, 3]
            rows['speed_mps'].append(float(np.linalg.norm(p[1] - p[0]) / 0.1))
            for v in variants:
                res[v.name].append(register_variant(v, ts, maps, solvers, along, left, n_test))
            if with_pulls:
                for kind in ('distorted', 'deskewed'):
                    pull = class_pulls(ts.points[kind], ts.surface, maps[kind], ts.T_true,
                                       along, reg.max_correspondence_distance_m,
                                       reg.robust_kernel_scale_m)
                    for name, value in pull.items():
                        pulls.setdefault(f'{kind}:{name}', []).append(value)
            n_test += 1
            if log is not None and n_test % 50 == 0:
                log(f'  scan {k}: {n_test} test scans')
        if k in keys:
            # After its own registration, as in the pipeline: a scan meets an older map.
            for kind, local_map in maps.items():
                pts = ts.points[MAPS[kind][0]]
                local_map.add_keyframe(transform_points(ts.T_true, pts), ts.T_true)
            last_key_T = ts.T_true
    out = {key: np.asarray(value) for key, value in rows.items()}
    for name, values in res.items():
        arr = np.asarray(values, dtype=float).reshape(-1, 4)
        out[name] = {'along_m': arr[:, 0], 'lateral_m': arr[:, 1], 'yaw_rad': arr[:, 2],
                     'iterations': arr[:, 3]}
    out['pulls'] = {key: np.asarray(value) for key, value in pulls.items()}
    return out


def register_variant(v: Variant, ts: TestScan, maps: dict, solvers: Solvers,
                     along: np.ndarray, left: np.ndarray, n_test: int) -> tuple:
    """(along m, lateral m, yaw rad, iterations) of one variant on one test scan (NaN when it
    does not run on this scan or has fewer than 10 points)."""
    skipped = (np.nan, np.nan, np.nan, -1)
    if n_test % v.every:
        return skipped
    mask = class_mask(ts.surface, v.points)
    source = ts.points[MAPS[v.map_kind][0]][mask]
    if source.shape[0] < 10:
        return skipped
    init = ts.T_true.copy()
    init[:3, 3] += v.offset_m * along
    smooth = ts.smoothness[mask] if ts.smoothness is not None else None
    T, its = solvers.register(v.solver, source, maps[v.map_kind], init, smooth)
    return pose_error(T, ts.T_true, along, left) + (its,)


def summarise(values: np.ndarray) -> dict:
    """mean, SEM, median, std, n of the finite values (NaN-safe)."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return {'n': 0}
    return {'n': int(v.size), 'mean': float(v.mean()),
            'sem': float(v.std(ddof=1) / np.sqrt(v.size)) if v.size > 1 else float('nan'),
            'median': float(np.median(v)), 'std': float(v.std())}


def timing_ate(sim: ScanSimulator, n_scans: int) -> dict:
    """ATE of the perfect trajectory against the GPS track, nearest vs interpolated stamps."""
    period_s = 1.0 / sim.config.scan_rate_hz
    t_scan = np.arange(n_scans) * period_s
    gps_t = GPS_PHASE_S + np.arange(0.0, n_scans * period_s, 1.0 / sim.config.gps_rate_hz)
    ref = Trajectory(sim.start_ns + np.round(gps_t * NS_PER_S).astype(np.int64),
                     sim.sensor_poses(gps_t) @ sim.T_sensor_gps)
    est = Trajectory(sim.start_ns + np.round(t_scan * NS_PER_S).astype(np.int64),
                     sim.sensor_poses(t_scan) @ sim.T_sensor_gps)
    speed = np.linalg.norm(np.diff(est.positions_xyz, axis=0), axis=1) / period_s
    out = {'mean_speed_mps': float(speed.mean()),
           'v_times_phase_rms_m': float(np.sqrt(np.mean((speed * GPS_PHASE_S) ** 2)))}
    for match in ('nearest', 'interpolate'):
        out[f'ate_{match}_m'] = float(ate(est, ref, mode='position', match=match).rmse_m)
    return out


def table(title: str, rows: list[tuple[str, dict]], unit: float = 1e3) -> str:
    """A markdown table of mean +- SEM (mm) per row."""
    lines = [f'### {title}', '', '| variant | n | along mean +- SEM [mm] | along median | '
             'lateral mean [mm] | yaw mean [mrad] |', '|---|---|---|---|---|---|']
    for name, s in rows:
        a, lat, yaw = s['along_m'], s['lateral_m'], s['yaw_rad']
        if a.get('n', 0) == 0:
            continue
        lines.append(f"| {name} | {a['n']} | {a['mean'] * unit:+.1f} +- {a['sem'] * unit:.1f} "
                     f"| {a['median'] * unit:+.1f} | {lat['mean'] * unit:+.1f} "
                     f"| {yaw['mean'] * 1e3:+.2f} |")
    return '\n'.join(lines)


def pool(runs: list[dict], name: str, straight_only: bool) -> dict:
    """Concatenate a variant's errors over drives; summarise each axis."""
    out = {}
    for axis in ('along_m', 'lateral_m', 'yaw_rad'):
        parts = []
        for run in runs:
            sel = run['straight'] if straight_only else np.ones(run['index'].size, bool)
            parts.append(run[name][axis][sel])
        out[axis] = summarise(np.concatenate(parts))
    return out


def binned(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> list[dict]:
    """Mean and SEM of y in bins of x."""
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        s = summarise(y[(x >= lo) & (x < hi)])
        out.append({'lo': float(lo), 'hi': float(hi), **s})
    return out


def plot(summary: dict, path: Path) -> None:
    """Six panels: bias per variant, pull per class and place, vs distance since the newest
    keyframe, offsets of the guess, forward vs time-reversed map, ground-truth timing."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 3, figsize=(18, 10))
    st = summary['straight']

    def mean_sem(entry):
        return entry.get('mean', np.nan) * 1e3, entry.get('sem', np.nan) * 1e3

    ax = axes[0, 0]
    names = [n for n in st if '_from_' not in n]
    ms = np.array([mean_sem(st[n]['along_m']) for n in names])
    ax.barh(range(len(names)), ms[:, 0], xerr=ms[:, 1],
            color=['C3' if m < 0 else 'C0' for m in ms[:, 0]])
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.invert_yaxis()
    ax.axvline(0.0, color='k', lw=0.8)
    ax.set_xlabel('along-track error [mm], mean +- SEM')
    ax.set_title('(a) from the truth against a true-pose map (straight)', fontsize=10)

    ax = axes[0, 1]
    places = ('ahead', 'beside', 'behind')
    classes = ('ground', 'trunk', 'canopy', 'other')
    for j, place in enumerate(places):
        ms = np.array([mean_sem(summary['pulls'][f'deskewed:{c}_{place}']) for c in classes])
        ax.bar(np.arange(4) + 0.27 * (j - 1), ms[:, 0], 0.27, yerr=ms[:, 1], label=place,
               capsize=2)
    ax.set_xticks(range(4), classes)
    ax.axhline(0.0, color='k', lw=0.8)
    ax.set_ylabel('along-track pull at the truth [mm]')
    ax.set_title('(b) who pulls at the truth, and which way (deskewed, straight)', fontsize=10)
    ax.legend(title='points relative to the sensor', fontsize=8)

    ax = axes[0, 2]
    for name, colour in (('o3d', 'C3'), ('deskewed', 'C2'), ('newest', 'C1')):
        b = [r for r in summary['vs_since_keyframe'][name] if r.get('n', 0) > 2]
        ax.errorbar([0.5 * (r['lo'] + r['hi']) for r in b], [r['mean'] * 1e3 for r in b],
                    yerr=[r['sem'] * 1e3 for r in b], marker='o', color=colour, label=name,
                    capsize=3)
    ax.axhline(0.0, color='k', lw=0.8)
    ax.set_xlabel('along-track distance since the newest keyframe [m]')
    ax.set_ylabel('along-track error [mm]')
    ax.set_title('(c) against the age of the newest map content (straight)', fontsize=10)
    ax.legend(fontsize=8)

    ax = axes[1, 0]
    offs = np.array((0.0,) + OFFSETS_M)
    order = np.argsort(offs)
    for solver, colour in (('o3d', 'C3'), ('o3d_tight', 'C0'), ('gn_plane', 'C2')):
        names = [solver] + [f'{solver}_from_{o:+.1f}' for o in OFFSETS_M]
        ms = np.array([mean_sem(st[n]['along_m']) for n in names])
        ax.errorbar(offs[order] * 1e3, ms[order, 0], yerr=ms[order, 1], marker='o',
                    capsize=3, color=colour, label=solver)
    ax.plot([-200, 200], [-200, 200], ':', color='grey', lw=0.8, label='stays at the guess')
    ax.axhline(0.0, color='k', lw=0.8)
    ax.set_ylim(-80, 50)
    ax.set_xlabel('initial guess offset along the track [mm]')
    ax.set_ylabel('final along-track error [mm]')
    ax.set_title('(d) does ICP come back from an offset guess? (straight)', fontsize=10)
    ax.legend(fontsize=8)

    ax = axes[1, 1]
    rev = summary.get('reversed_straight', {})
    names = [n for n in rev if rev[n]['along_m'].get('n', 0)]
    fwd = np.array([mean_sem(summary['same_drives_straight'][n]['along_m']) for n in names])
    bwd = np.array([mean_sem(rev[n]['along_m']) for n in names])
    y = np.arange(len(names))
    ax.barh(y - 0.2, fwd[:, 0], 0.4, xerr=fwd[:, 1], label='map seen from behind (pipeline)',
            color='C3')
    ax.barh(y + 0.2, bwd[:, 0], 0.4, xerr=bwd[:, 1], label='map seen from ahead (reversed)',
            color='C0')
    ax.set_yticks(y, names, fontsize=8)
    ax.invert_yaxis()
    ax.axvline(0.0, color='k', lw=0.8)
    ax.set_xlabel('along-track error [mm], mean +- SEM')
    ax.set_title(f"(e) {', '.join(summary.get('reversed_drives', []))}: the map seen from "
                 'the other side (straight)', fontsize=10)
    ax.legend(fontsize=8)

    ax = axes[1, 2]
    drives = list(summary['timing'])
    t = summary['timing']
    y = np.arange(len(drives))
    ax.barh(y - 0.2, [t[d]['ate_nearest_m'] * 1e3 for d in drives], 0.4,
            label='match: nearest (GPS 37 ms after the stamp)', color='C3')
    ax.barh(y + 0.2, [t[d]['ate_interpolate_m'] * 1e3 for d in drives], 0.4,
            label='match: interpolate', color='C0')
    ax.set_yticks(y, drives, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel('ATE RMSE of the PERFECT trajectory [mm]')
    ax.set_title('(f) ground-truth timing alone (whole drives)', fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


GROUPS = (('solvers (distorted scans and map, as the pipeline)',
           ('o3d', 'o3d_tight', 'gn_plane', 'gn_plane_tight', 'gn_freq')),
          ('scans and map', ('o3d', 'deskewed', 'newest', 'mean', 'deskewed_mean')),
          ('surface classes', ('o3d', 'o3d_ground', 'o3d_trunk', 'o3d_canopy', 'o3d_noncanopy',
                               'deskewed', 'deskewed_canopy', 'deskewed_noncanopy',
                               'deskewed_mean_canopy')))


def summarise_runs(runs: list[dict], variants: list[Variant]) -> dict:
    """Pooled (straight / all), per drive, pulls, binned by keyframe distance and speed."""
    out: dict = {'straight': {}, 'all': {}, 'per_drive': {}, 'pulls': {},
                 'vs_since_keyframe': {}, 'vs_speed': {}, 'iterations': {}}
    for v in variants:
        out['straight'][v.name] = pool(runs, v.name, True)
        out['all'][v.name] = pool(runs, v.name, False)
    for run in runs:
        out['per_drive'][run['drive']] = {
            v.name: summarise(run[v.name]['along_m'][run['straight']])
            for v in variants if v.every == 1}
    for key in runs[0]['pulls']:
        out['pulls'][key] = summarise(np.concatenate(
            [r['pulls'][key][r['straight']] for r in runs]))
    names = [v.name for v in variants]
    for name in ('o3d', 'deskewed', 'newest'):
        if name not in names:
            continue
        st = [r['straight'] for r in runs]
        y = np.concatenate([r[name]['along_m'][s] for r, s in zip(runs, st)])
        x = np.abs(np.concatenate([r['since_keyframe_m'][s] for r, s in zip(runs, st)]))
        out['vs_since_keyframe'][name] = binned(x, y, np.linspace(0.0, 1.2, 7))
        v = np.concatenate([r['speed_mps'][s] for r, s in zip(runs, st)])
        out['vs_speed'][name] = binned(v, y, np.array([0.3, 0.9, 1.2, 1.5, 2.0]))
    for name in ('gn_plane', 'gn_plane_tight', 'gn_freq'):
        if name in names:
            it = np.concatenate([r[name]['iterations'] for r in runs])
            out['iterations'][name] = summarise(it[it >= 0])
    return out


def print_tables(summary: dict, variants: list[Variant]) -> None:
    """The study's tables on stdout (markdown)."""
    st = summary['straight']
    for title, names in GROUPS:
        if not any(n in st for n in names):
            continue
        print()
        print(table(f'{title}: straight segments, pooled', [(n, st[n]) for n in names
                                                             if n in st]))
    print()
    print(table('initial guess offset: straight segments, pooled',
                [(v.name, st[v.name]) for v in variants if '_from_' in v.name]))
    if 'reversed_straight' in summary:
        print()
        print(table('map seen from ahead (time-reversed drive): straight, pooled',
                    list(summary['reversed_straight'].items())))
        print()
        print(table('the same drives forward', list(summary['same_drives_straight'].items())))
    if not summary['pulls']:
        return
    print('\n### along-track pull at the truth [mm] and share of the along-track information'
          ' (straight, pooled)\n')
    print('| points | pull distorted | pull deskewed | info share |\n|---|---|---|---|')
    for key in summary['pulls']:
        kind, name = key.split(':')
        if kind != 'distorted' or name.startswith('info'):
            continue
        d, k = summary['pulls'][key], summary['pulls'][f'deskewed:{name}']
        share = summary['pulls'][f'distorted:info_{name}']['mean']
        print(f"| {name} | {d['mean'] * 1e3:+.2f} +- {d['sem'] * 1e3:.2f} | "
              f"{k['mean'] * 1e3:+.2f} +- {k['sem'] * 1e3:.2f} | {share:.3f} |")
    for what in ('vs_since_keyframe', 'vs_speed'):
        print(f'\n### along-track error {what} (straight) [mm]')
        for name, bins in summary[what].items():
            print(f'  {name}: ' + ', '.join(
                f"{r['lo']:.1f}-{r['hi']:.1f}: {r['mean'] * 1e3:+.1f}+-{r['sem'] * 1e3:.1f}"
                f" (n {r['n']})" for r in bins if r.get('n', 0) > 1))
    print('\n### per drive, along mean [mm] (straight)')
    for drive, d in summary['per_drive'].items():
        print(f'  {drive}: ' + ', '.join(f"{n} {d[n].get('mean', np.nan) * 1e3:+.1f}"
                                         for n in ('o3d', 'deskewed', 'newest', 'o3d_canopy',
                                                   'o3d_noncanopy', 'gn_freq')))
    print('\n### ground-truth timing: ATE RMSE of the perfect trajectory (whole drive) [m]')
    for drive, t in summary['timing'].items():
        print(f"  {drive}: nearest {t['ate_nearest_m']:.4f}, interpolate "
              f"{t['ate_interpolate_m']:.4f}; rms v x 37 ms {t['v_times_phase_rms_m']:.4f}")
    print('\niterations (median): ' + ', '.join(
        f"{k} {v.get('median', np.nan):.0f}" for k, v in summary['iterations'].items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scans', type=int, default=1000,
                        help='scans per drive from its start (default 1000, ~100 s)')
    parser.add_argument('--test-every', type=int, default=10)
    parser.add_argument('--reversed-drives', type=int, default=2,
                        help='drives also walked backwards in time (map seen from ahead)')
    parser.add_argument('--quick', action='store_true', help='one drive, 300 scans')
    parser.add_argument('--no-figure', action='store_true')
    parser.add_argument('--only', nargs='*', default=None,
                        help='only these variants (e.g. deskewed deskewed_mean), no pulls')
    parser.add_argument('--out', type=Path, default=RESULTS, help='results JSON')
    args = parser.parse_args()
    drives = DRIVES[:1] if args.quick else DRIVES
    n_scans = 300 if args.quick else args.scans
    variants, rev_variants = default_variants(), reversal_variants()
    if args.only is not None:
        variants = [v for v in variants if v.name in args.only]
        rev_variants = [v for v in rev_variants if v.name in args.only]
    runs, reversed_runs, timing = [], [], {}
    t_start = time.process_time()
    for i, (scenario, seed) in enumerate(drives):
        sim, _ = ScanSimulator.for_drive(SimConfig(), scenario, seed, vary=True)
        last = min(n_scans, sim.n_scans_in_drive)
        passes = [False] + ([True] if i < args.reversed_drives else [])
        for reverse in passes:
            t0 = time.process_time()
            print(f'{scenario}-{seed}: scans 0..{last}, every {args.test_every}-th'
                  f'{" (reversed)" if reverse else ""}', flush=True)
            run = oracle_run(sim, 0, last, args.test_every,
                             rev_variants if reverse else variants, reverse=reverse,
                             with_pulls=args.only is None, log=print)
            run['drive'] = f'{scenario}-{seed}'
            (reversed_runs if reverse else runs).append(run)
            print(f"  {run['index'].size} test scans ({int(run['straight'].sum())} straight),"
                  f' {time.process_time() - t0:.0f} s CPU', flush=True)
        timing[f'{scenario}-{seed}'] = timing_ate(sim, sim.n_scans_in_drive)
    summary = summarise_runs(runs, variants)
    summary['timing'] = timing
    if reversed_runs:
        summary['reversed_straight'] = {v.name: pool(reversed_runs, v.name, True)
                                        for v in rev_variants}
        summary['same_drives_straight'] = {v.name: pool(runs[:len(reversed_runs)], v.name,
                                                        True) for v in rev_variants}
        summary['reversed_drives'] = [r['drive'] for r in reversed_runs]
    summary.update(cpu_s=time.process_time() - t_start, drives=[r['drive'] for r in runs],
                   scans_per_drive=n_scans, test_every=args.test_every)
    print_tables(summary, variants)
    print(f"\nCPU {summary['cpu_s']:.0f} s")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=1) + '\n')
    if not args.no_figure and args.only is None:
        plot(summary, FIGURE)
        print(f'wrote {args.out} and {FIGURE.relative_to(ROOT)}')


if __name__ == '__main__':
    main()
