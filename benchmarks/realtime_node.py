"""Live-sensor input test: full VLP-16 clouds at 10 Hz, in real time, to the installed node.

Like a velodyne driver on the same host: every 0.1 s one ~29 k-point cloud (a simulated row
drive played forward and back) stamped with the wall clock is published on `/velodyne_points`
with best-effort (sensor-data) or reliable QoS (the stock ROS 2 velodyne driver's
`rclcpp::QoS(10)`); the colcon-built filter_odom_node runs with `config/filter_odom.yaml`
(input QoS `node.input_reliability: auto`: it subscribes as the publisher is). Counts the scans
answered on `~/odometry`, the publish -> odometry latency and the input QoS the node chose.
Writes benchmarks/results/realtime_node_<reliability>_<driver profile>.json.

    .venv/bin/python benchmarks/realtime_node.py --seconds 30 --reliability reliable \
        --driver-profile default
"""

from __future__ import annotations

import argparse
import json
import random
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from soak_node import (  # noqa: E402
    add_driver_profile_argument,
    build_node,
    ping_pong,
    spinner,
    use_driver_profile,
    wait_for_node,
)

REPO = Path(__file__).resolve().parents[1]
NODE = '/filter_odom_node'
TOPIC = '/velodyne_points'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seconds', type=float, default=90.0)
    parser.add_argument('--rate-hz', type=float, default=10.0)
    parser.add_argument('--scans', type=int, default=30, help='scans in the simulated drive')
    parser.add_argument('--reliability', choices=('best_effort', 'reliable'),
                        default='best_effort')
    parser.add_argument('--node-arg', action='append', default=[],
                        help='extra --ros-args for the node, e.g. -p node.input_queue_depth:=5')
    parser.add_argument('--env', action='append', default=[], metavar='NAME=VALUE',
                        help='extra environment of the node process')
    add_driver_profile_argument(parser)
    parser.add_argument('--tag', default='', help='suffix of the result file name')
    parser.add_argument('--out', default=str(REPO / 'benchmarks' / 'results'))
    args = parser.parse_args(argv)

    use_driver_profile(args.driver_profile)
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    from gft_odom.io.bags import ScanBagReader
    from gft_odom.ros import through_node
    from gft_odom.ros.conversions import ns_to_stamp, stamp_to_ns
    from gft_odom.sim.writer import simulate_to_bag

    work = Path(tempfile.mkdtemp(prefix='gft_realtime_'))
    print(f'simulating {args.scans} full VLP-16 scans, building the node in {work} ...',
          flush=True)
    sim = simulate_to_bag(work / 'sim', n_scans=args.scans, seed=101, topdown_png=False)
    with ScanBagReader([sim.bag_path]) as reader:
        messages = [through_node.ros_message_from_bag(raw) for _, raw in reader.iter_messages()]
    points_per_scan = float(np.mean([m.width * m.height for m in messages]))
    bytes_per_scan = float(np.mean([len(m.data) for m in messages]))
    exe, env = build_node(work / 'ws')
    domain_id = random.randint(100, 200)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=str(domain_id))
    env.update(dict(kv.split('=', 1) for kv in args.env))
    node_log = work / 'node.log'
    params = REPO / 'config' / 'filter_odom.yaml'
    cmd = [str(exe), '--ros-args', '--params-file', str(params), '-r', f'points:={TOPIC}']
    for extra in args.node_arg:
        cmd += extra.split()
    with open(node_log, 'w') as log_file:
        proc = subprocess.Popen(cmd, env=env, stdout=log_file, stderr=subprocess.STDOUT)

    context, node, executor = through_node.start_feeder('realtime_feeder', domain_id)
    answered: dict[int, float] = {}
    node.create_subscription(
        Odometry, f'{NODE}/odometry',
        lambda m: answered.setdefault(stamp_to_ns(m.header.stamp), time.monotonic()),
        QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    qos = (qos_profile_sensor_data if args.reliability == 'best_effort'
           else QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    pub = node.create_publisher(PointCloud2, TOPIC, qos)

    spin_for = spinner(executor)
    wait_for_node(node, pub, proc, node_log, spin_for)

    period_s = 1.0 / args.rate_hz
    sent: dict[int, float] = {}
    order = ping_pong(len(messages))
    t_start = time.monotonic()
    next_send = t_start
    print(f'publishing for {args.seconds:g} s at {args.rate_hz:g} Hz, {args.reliability} '
          f'({points_per_scan:.0f} points, {bytes_per_scan / 1e6:.2f} MB per scan) ...',
          flush=True)
    try:
        while time.monotonic() < t_start + args.seconds:
            if time.monotonic() >= next_send:
                msg = messages[next(order)]
                stamp_ns = time.time_ns()
                msg.header.stamp = ns_to_stamp(stamp_ns)
                sent[stamp_ns] = time.monotonic()
                pub.publish(msg)
                next_send += period_s
            spin_for(next_send - time.monotonic())
        spin_for(3.0)  # answers still in flight
    finally:
        through_node.stop_feeder(context, node, executor)
        through_node.stop_node_process(proc, timeout_s=20.0)

    stamps = np.array(sorted(sent))
    latency_ms = np.array([1e3 * (answered[s] - sent[s]) if s in answered else np.nan
                           for s in stamps])
    ok = np.isfinite(latency_ms)
    log_text = node_log.read_text()
    final = re.search(r'final counts: (.*)', log_text)
    input_qos = re.findall(r'input \S+: (.*)', log_text)
    figures = {
        'seconds': args.seconds, 'rate_hz': args.rate_hz, 'reliability': args.reliability,
        'driver_profile': args.driver_profile,
        'node_args': ' '.join(args.node_arg), 'node_env': ' '.join(args.env),
        'points_per_scan_mean': points_per_scan, 'bytes_per_scan_mean': bytes_per_scan,
        'scans_sent': int(stamps.size), 'scans_answered': int(ok.sum()),
        'answered_fraction': float(ok.mean()) if stamps.size else None,
        'latency_median_ms': float(np.median(latency_ms[ok])) if ok.any() else None,
        'latency_p95_ms': float(np.percentile(latency_ms[ok], 95)) if ok.any() else None,
        'node_final_counts': final.group(1) if final else None,
        'node_input_qos': input_qos,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = (f'realtime_node_{args.reliability}_{args.driver_profile}'
            f'{"_" + args.tag if args.tag else ""}.json')
    (out / name).write_text(json.dumps(figures, indent=2) + '\n')
    print(f'node log: {node_log}')
    print(json.dumps(figures, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
