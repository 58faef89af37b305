"""Shared fixtures: DDS isolation for tests that talk ROS between processes, a service caller,
the colcon-built node and a small simulated drive."""

from __future__ import annotations

import faulthandler
import os
import random
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SERVICE_ATTEMPTS = 3  # requests sent before a service counts as not answering
# After the session, the longest the interpreter may take to exit.
EXIT_WATCHDOG_S = float(os.environ.get('GFT_ODOM_EXIT_WATCHDOG_S', '120'))
_session_status: list[int] = [0]
# Plain helper modules beside this file (helpers.py) are importable from every test.
sys.path.insert(0, str(Path(__file__).resolve().parent))


def pytest_sessionfinish(session, exitstatus):
    """Name the threads the tests leave running: one of them can keep the interpreter from
    exiting."""
    _session_status[0] = int(exitstatus)
    left = [t.name for t in threading.enumerate()
            if t is not threading.main_thread() and not t.daemon]
    if left:
        sys.stderr.write(f'\nthreads left running after the tests: {left}\n')


def pytest_unconfigure(config):
    """If the interpreter has not exited EXIT_WATCHDOG_S after the session (seen once in CI
    under load: every test passed, then no exit), print every thread's stack and exit with the
    session's status, so the hang is diagnosed instead of eating CI's time."""
    def watchdog() -> None:
        time.sleep(EXIT_WATCHDOG_S)
        sys.stderr.write(f'\npytest did not exit {EXIT_WATCHDOG_S:.0f} s after the session; '
                         'the stacks of its threads:\n')
        faulthandler.dump_traceback(all_threads=True)
        sys.stderr.flush()
        os._exit(_session_status[0])
    threading.Thread(target=watchdog, name='gft_odom-exit-watchdog', daemon=True).start()


@pytest.fixture(scope='session')
def ros_domain_id() -> int:
    """A per-run DDS domain, so parallel runs on one host do not hear each other."""
    return random.Random(os.getpid()).randint(10, 200)


@pytest.fixture
def ros_env(ros_domain_id, monkeypatch) -> dict[str, str]:
    """Environment for DDS tests: traffic stays on this host, in this run's domain."""
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    monkeypatch.setenv('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    return dict(os.environ)


@pytest.fixture(scope='session')
def orchard_bag(tmp_path_factory):
    """A short simulated orchard drive (rosbag2, full VLP-16 geometry) with its ground truth."""
    from gft_odom.sim.writer import simulate_to_bag
    out = tmp_path_factory.mktemp('orchard')
    return simulate_to_bag(out, scenario='row', n_scans=15, seed=3, topdown_png=False)


@pytest.fixture(scope='session')
def installed_node(tmp_path_factory):
    """colcon build of this package into a fresh workspace; the script `ros2 run` would start."""
    ws = tmp_path_factory.mktemp('ws')
    colcon = Path(sys.executable).with_name('colcon')
    proc = subprocess.run(
        [str(colcon), '--log-base', str(ws / 'log'), 'build', '--base-paths', str(REPO),
         '--build-base', str(ws / 'build'), '--install-base', str(ws / 'install')],
        cwd=ws, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    prefix = ws / 'install' / 'gft_odom'
    exe = prefix / 'lib' / 'gft_odom' / 'filter_odom_node'
    assert exe.is_file()
    site = next((prefix / 'lib').glob('python3*/site-packages'))
    assert (site / 'gft_odom' / 'ros' / 'node.py').is_file()
    assert (prefix / 'share' / 'gft_odom' / 'config' / 'filter_odom.yaml').is_file()
    assert (prefix / 'share' / 'gft_odom' / 'launch' / 'filter_odom.launch.py').is_file()
    env = dict(os.environ)
    # What `source install/setup.bash` does for this package.
    env['PYTHONPATH'] = os.pathsep.join([str(site), env.get('PYTHONPATH', '')]).rstrip(os.pathsep)
    env['AMENT_PREFIX_PATH'] = str(prefix)
    return exe, env


@pytest.fixture
def closed_figures(monkeypatch):
    """The matplotlib figures the code under test closes, kept open for the test to inspect."""
    from gft_odom.figures import pyplot

    plt = pyplot()
    kept, close = [], plt.close
    monkeypatch.setattr(plt, 'close', lambda fig=None: kept.append(fig))
    yield kept
    for fig in kept:
        close(fig)


@pytest.fixture
def refuses_file(tmp_path):
    """`refuses_file(read, text, error, match, name)`: `read` of a file holding `text` raises
    `error` with a message matching `match`."""
    def check(read, text: str, error: type[Exception], match: str, name: str = 'input.txt'):
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(error, match=match):
            read(path)

    return check


@pytest.fixture
def ros_node(ros_env):
    """An rclpy node of this test process in its own context: (node, spin_until)."""
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    node = rclpy.create_node('test_client', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def spin_until(done, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        return bool(done())

    try:
        yield node, spin_until
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.fixture
def ros_service_caller(ros_node):
    """`call(srv_type, service_name, request)`: a ROS service of another process, from here."""
    node, spin_until = ros_node
    clients = {}

    def call(srv_type, name: str, request, timeout_s: float = 30.0):
        if name not in clients:
            clients[name] = node.create_client(srv_type, name)
        assert clients[name].wait_for_service(timeout_sec=timeout_s), f'no service {name}'
        # A service seen is not yet a response path matched both ways: the first answer can
        # be lost, so an unanswered (idempotent) request is sent again.
        for _ in range(SERVICE_ATTEMPTS):
            future = clients[name].call_async(request)
            if spin_until(future.done, 10.0):
                return future.result()
        raise AssertionError(f'{name} did not answer {SERVICE_ATTEMPTS} requests')

    return call
