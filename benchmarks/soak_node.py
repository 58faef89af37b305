"""Soak test: the colcon-built filter_odom_node fed at 10 Hz for N minutes; poses, RSS, latency.

By default one lap of the simulated `loop` drive (up one lane, a headland turn, down another,
back to the start; the path closes) is played again and again: a continuous drive with no
reversal, stamped with the wall clock at 10 Hz like a sensor. `--pattern ping-pong` plays a
row drive forward then backward instead (the velocity flips at each end). Every answered pose
is compared with the ground truth of its scan: ATE RMSE after rigid alignment of positions,
the largest error, and the error over time. Every second the node's RSS is read from
/proc/<pid>/status; the latency of a scan is publish -> its odometry received. A scan the node
never answers is counted as dropped. The summary FAILS (exit 1) when tracking is lost (ATE
RMSE above 1 % of the distance driven), fewer than 99 % of the scans are answered, or RSS
grows after the warm-up. Writes benchmarks/results/soak_node.{json,md,png}.

    .venv/bin/python benchmarks/soak_node.py --minutes 10 --params-file config/filter_odom.yaml
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
NODE = '/filter_odom_node'
TOPIC = '/velodyne_points'


def build_node(ws: Path) -> tuple[Path, dict]:
    """colcon build into `ws`; the executable `ros2 run` would start and its environment."""
    colcon = Path(sys.executable).with_name('colcon')
    ws.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(
        [str(colcon), '--log-base', str(ws / 'log'), 'build', '--base-paths', str(REPO),
         '--build-base', str(ws / 'build'), '--install-base', str(ws / 'install')],
        cwd=ws, capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise SystemExit('colcon build failed:\n' + proc.stdout[-3000:] + proc.stderr[-3000:])
    prefix = ws / 'install' / 'gft_odom'
    site = next((prefix / 'lib').glob('python3*/site-packages'))
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(site), env.get('PYTHONPATH', '')]).rstrip(os.pathsep)
    env['AMENT_PREFIX_PATH'] = str(prefix)
    return prefix / 'lib' / 'gft_odom' / 'filter_odom_node', env


def rss_mb(pid: int) -> float | None:
    try:
        text = Path(f'/proc/{pid}/status').read_text()
    except OSError:
        return None
    match = re.search(r'VmRSS:\s+(\d+) kB', text)
    return int(match.group(1)) / 1024.0 if match else None


def ping_pong(n: int):
    """0, 1, ..., n-1, n-2, ..., 1, 0, 1, ... forever."""
    order = list(range(n)) + list(range(n - 2, 0, -1))
    while True:
        yield from order


def laps(n: int):
    """0, 1, ..., n-1, 0, 1, ... forever (one closed lap, driven again and again)."""
    while True:
        yield from range(n)


# Pass/fail of the summary.
MAX_ATE_FRACTION_OF_DISTANCE = 0.01
MIN_ANSWERED_FRACTION = 0.99
MAX_RSS_SLOPE_MB_PER_MIN = 1.0


def pose_errors(sent_index: np.ndarray, answered_T: list, truth_base: np.ndarray):
    """Position errors [m] of the answered poses after rigid alignment to the ground truth of
    their scans, and the distance driven by the ground truth over the sent scans."""
    from gft_odom.core.alignment import umeyama_alignment
    est = np.array([T[:3, 3] for T in answered_T])
    ref = truth_base[sent_index, :3, 3]
    R, t, _ = umeyama_alignment(est, ref)
    return np.linalg.norm(est @ R.T + t - ref, axis=1)


def add_driver_profile_argument(parser) -> None:
    """--driver-profile: the feeder's (the driver's) Fast DDS transports."""
    parser.add_argument('--driver-profile', choices=('default', 'large'), default='large',
                        help="the feeder's (the driver's) Fast DDS transports: the defaults, or "
                             'config/fastdds_large_messages.xml, as the README asks of a driver '
                             '(full-resolution clouds are larger than the default 512 KB '
                             'shared-memory segment)')


def use_driver_profile(choice: str) -> None:
    """Set (or clear) this process's Fast DDS profile, before its first participant; the node
    picks the large-message profile up by itself."""
    if choice == 'large':
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(
            REPO / 'config' / 'fastdds_large_messages.xml')
    else:
        os.environ.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)


def spinner(executor):
    """spin_for(seconds): run the executor's callbacks for that long."""
    def spin_for(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=max(0.0, min(0.005, end - time.monotonic())))
    return spin_for


def wait_for_node(node, pub, proc, node_log, spin_for, timeout_s: float = 60.0) -> None:
    """Until the node subscribes to `pub` and publishes odometry (or exit with its log)."""
    deadline = time.monotonic() + timeout_s
    while not (pub.get_subscription_count() and node.count_publishers(f'{NODE}/odometry')):
        if time.monotonic() > deadline or proc.poll() is not None:
            raise SystemExit(f'node did not come up; log: {node_log}')
        spin_for(0.05)
    spin_for(2.0)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--minutes', type=float, default=10.0)
    parser.add_argument('--rate-hz', type=float, default=10.0)
    parser.add_argument('--pattern', choices=('laps', 'ping-pong'), default='laps')
    parser.add_argument('--scans', type=int, default=None,
                        help='scans in the simulated drive (default: one lap, or 40 for '
                        'ping-pong)')
    parser.add_argument('--params-file', default=None,
                        help='params file for the node (default: the package defaults)')
    parser.add_argument('--azimuth-step-deg', type=float, default=0.4,
                        help='0.2 is the real VLP-16; 0.4 halves the points per scan')
    add_driver_profile_argument(parser)
    parser.add_argument('--out', default=str(REPO / 'benchmarks' / 'results'))
    args = parser.parse_args(argv)
    use_driver_profile(args.driver_profile)

    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import PointCloud2

    from gft_odom.config import GftOdomConfig
    from gft_odom.core.geometry import invert_transform
    from gft_odom.io.bags import ScanBagReader
    from gft_odom.io.tum import read_tum
    from gft_odom.pipeline import base_to_sensor
    from gft_odom.ros.conversions import ns_to_stamp, stamp_to_ns
    from gft_odom.ros.through_node import (
        ros_message_from_bag,
        start_feeder,
        stop_feeder,
        stop_node_process,
    )
    from gft_odom.sim.simulator import ScanSimulator, SimConfig
    from gft_odom.sim.writer import simulate_to_bag

    work = Path(tempfile.mkdtemp(prefix='gft_soak_'))
    sim_config = SimConfig(azimuth_step_deg=args.azimuth_step_deg)
    scenario = 'loop' if args.pattern == 'laps' else 'row'
    n_scans = args.scans
    if n_scans is None and args.pattern == 'laps':
        # The motion model of a loop laps: one lap's worth of scans closes the path.
        probe = ScanSimulator.from_config(sim_config, 'loop', 1000, seed=101)
        n_scans = int(round(probe.motion.duration_s * sim_config.scan_rate_hz))
    n_scans = n_scans or 40
    print(f'simulating {n_scans} scans ({scenario}), building the node in {work} ...',
          flush=True)
    sim = simulate_to_bag(work / 'sim', scenario=scenario, n_scans=n_scans, seed=101,
                          config=sim_config, topdown_png=False)
    with ScanBagReader([sim.bag_path]) as reader:
        messages = [ros_message_from_bag(raw)
                    for _, raw in reader.iter_messages()]
    T_base_sensor = base_to_sensor(GftOdomConfig())
    truth_base = read_tum(sim.gt_tum_path).poses @ invert_transform(T_base_sensor)
    points_per_scan = float(np.mean([m.width * m.height for m in messages]))
    exe, env = build_node(work / 'ws')
    domain_id = random.randint(100, 200)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=str(domain_id))
    node_log = work / 'node.log'
    ros_args = ['--ros-args', '-r', f'points:={TOPIC}']
    if args.params_file:
        ros_args += ['--params-file', str(Path(args.params_file).resolve())]
    with open(node_log, 'w') as log_file:
        proc = subprocess.Popen([str(exe), *ros_args], env=env,
                                stdout=log_file, stderr=subprocess.STDOUT)

    context, node, executor = start_feeder('soak_feeder', domain_id)
    answered: dict[int, float] = {}
    poses: dict[int, np.ndarray] = {}

    def on_odometry(m) -> None:
        stamp = stamp_to_ns(m.header.stamp)
        answered.setdefault(stamp, time.monotonic())
        p, q = m.pose.pose.position, m.pose.pose.orientation
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        T[:3, 3] = p.x, p.y, p.z
        poses[stamp] = T

    node.create_subscription(Odometry, f'{NODE}/odometry', on_odometry,
                             QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    pub = node.create_publisher(PointCloud2, TOPIC,
                                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    spin_for = spinner(executor)
    wait_for_node(node, pub, proc, node_log, spin_for)

    period_s = 1.0 / args.rate_hz
    sent: dict[int, float] = {}
    sent_scan: dict[int, int] = {}
    rss_t, rss_v = [], []
    order = laps(len(messages)) if args.pattern == 'laps' else ping_pong(len(messages))
    t_start = time.monotonic()
    t_end = t_start + 60.0 * args.minutes
    next_send = next_rss = t_start
    print(f'soaking for {args.minutes} min at {args.rate_hz} Hz '
          f'({points_per_scan:.0f} points/scan) ...', flush=True)
    try:
        while time.monotonic() < t_end:
            now = time.monotonic()
            if now >= next_rss:
                value = rss_mb(proc.pid)
                if value is None:
                    raise SystemExit(f'node exited; log: {node_log}')
                rss_t.append(now - t_start)
                rss_v.append(value)
                next_rss += 1.0
            if now >= next_send:
                index = next(order)
                msg = messages[index]
                stamp_ns = time.time_ns()
                msg.header.stamp = ns_to_stamp(stamp_ns)
                sent[stamp_ns] = time.monotonic()
                sent_scan[stamp_ns] = index
                pub.publish(msg)
                next_send += period_s
            spin_for(min(next_send, next_rss) - time.monotonic())
        spin_for(3.0)  # the answers still in flight
    finally:
        stop_feeder(context, node, executor)
        stop_node_process(proc, timeout_s=20.0)

    stamps = np.array(sorted(sent))
    sent_t = np.array([sent[s] - t_start for s in stamps])
    latency_ms = np.array([1e3 * (answered[s] - sent[s]) if s in answered else np.nan
                           for s in stamps])
    ok = np.isfinite(latency_ms)
    rss_t, rss_v = np.array(rss_t), np.array(rss_v)
    warm = rss_t >= 0.2 * rss_t[-1]  # after the first 20 %: caches, map and Path filled
    slope = float(np.polyfit(rss_t[warm] / 60.0, rss_v[warm], 1)[0]) if warm.sum() > 2 else None
    log_text = node_log.read_text()
    final = re.search(r'final counts: (.*)', log_text)
    got = [s for s in stamps if s in poses]
    index = np.array([sent_scan[s] for s in stamps])
    steps = np.linalg.norm(np.diff(truth_base[index, :3, 3], axis=0), axis=1)
    distance_m = float(steps.sum())
    errors = (pose_errors(np.array([sent_scan[s] for s in got]), [poses[s] for s in got],
                          truth_base) if len(got) >= 3 else np.full(1, np.inf))
    ate_m = float(np.sqrt(np.mean(errors ** 2)))
    figures = {
        'minutes': args.minutes, 'rate_hz': args.rate_hz,
        'azimuth_step_deg': args.azimuth_step_deg, 'points_per_scan_mean': points_per_scan,
        'scans_sent': int(stamps.size), 'scans_answered': int(ok.sum()),
        'scans_dropped': int((~ok).sum()),
        'dropped_fraction': float((~ok).mean()) if stamps.size else None,
        'latency_median_ms': float(np.median(latency_ms[ok])) if ok.any() else None,
        'latency_p95_ms': float(np.percentile(latency_ms[ok], 95)) if ok.any() else None,
        'latency_max_ms': float(np.max(latency_ms[ok])) if ok.any() else None,
        'rss_start_mb': float(rss_v[0]), 'rss_end_mb': float(rss_v[-1]),
        'rss_max_mb': float(rss_v.max()),
        'rss_slope_after_warmup_mb_per_min': slope,
        'node_exit_code': proc.returncode,
        'node_final_counts': final.group(1) if final else None,
        'tracebacks_in_node_log': log_text.count('Traceback'),
        'pattern': args.pattern, 'params_file': args.params_file,
        'scans_in_drive': len(messages), 'distance_m': distance_m,
        'ate_rmse_m': ate_m, 'ate_max_m': float(np.max(errors)),
        'ate_fraction_of_distance': ate_m / distance_m if distance_m > 0 else None,
    }
    failures = []
    if not ate_m <= MAX_ATE_FRACTION_OF_DISTANCE * distance_m:
        failures.append(f'tracking lost: ATE RMSE {ate_m:.2f} m > '
                        f'{100 * MAX_ATE_FRACTION_OF_DISTANCE:g} % of {distance_m:.0f} m')
    if not ok.mean() >= MIN_ANSWERED_FRACTION:
        failures.append(f'only {100 * ok.mean():.1f} % of the scans answered '
                        f'(< {100 * MIN_ANSWERED_FRACTION:g} %)')
    if slope is not None and slope > MAX_RSS_SLOPE_MB_PER_MIN:
        failures.append(f'RSS grows {slope:.2f} MB/min after the warm-up')
    figures['failures'] = '; '.join(failures) or 'none'
    error_t = np.array([sent[s] - t_start for s in got])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'soak_node.json').write_text(json.dumps(figures, indent=2) + '\n')
    (out / 'soak_node.md').write_text(
        '| figure | value |\n|---|---|\n'
        + ''.join(f'| {k} | {v:.3g} |\n' if isinstance(v, float) else f'| {k} | {v} |\n'
                  for k, v in figures.items()))
    _plot(out / 'soak_node.png', rss_t, rss_v, sent_t, latency_ms, figures, error_t,
          errors if len(got) >= 3 else np.zeros(0))
    print(f'node log: {node_log}')
    print(json.dumps(figures, indent=2))
    for failure in failures:
        print(f'FAIL: {failure}')
    return 1 if failures else 0


def _plot(path: Path, rss_t, rss_v, sent_t, latency_ms, figures, error_t, errors) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    ax1.plot(rss_t / 60.0, rss_v, color='tab:blue')
    ax1.set_ylabel('node RSS [MB]')
    ax1.set_title(f'filter_odom_node soak: {figures["minutes"]:g} min at '
                  f'{figures["rate_hz"]:g} Hz, {figures["points_per_scan_mean"]:.0f} points/scan')
    ax1.grid(alpha=0.3)
    ok = np.isfinite(latency_ms)
    ax2.plot(sent_t[ok] / 60.0, latency_ms[ok], '.', ms=2, color='tab:red', label='answered')
    if (~ok).any():
        ax2.plot(sent_t[~ok] / 60.0, np.zeros((~ok).sum()), '|', color='0.4', ms=6,
                 label=f'dropped ({(~ok).sum()})')
    ax2.set_ylabel('publish -> odometry [ms]')
    ax2.grid(alpha=0.3)
    ax2.legend(loc='upper right')
    if errors.size == error_t.size and errors.size:
        ax3.plot(error_t / 60.0, errors, '.', ms=2, color='tab:green')
    ax3.set_ylabel('position error [m]')
    ax3.set_xlabel('time [min]')
    ax3.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == '__main__':
    sys.exit(main())
