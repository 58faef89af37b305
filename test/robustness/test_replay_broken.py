"""`gft-odom replay` on broken input: exit 1, one clear line, no half-written results."""

from __future__ import annotations

import logging
import os
import random
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gft_odom.config import GftOdomConfig
from gft_odom.errors import GftOdomError
from gft_odom.io.bags import BagWriter
from gft_odom.io.pointcloud2 import encode_cloud
from gft_odom.replay import run_replay, write_results
from gft_odom.sim.simulator import SimConfig
from gft_odom.sim.writer import simulate_to_bag
from gft_odom.tools import cli

N_SCANS = 5


@pytest.fixture(scope='module')
def small_bags(tmp_path_factory):
    """The same short drive as a ROS 1 .bag and a rosbag2 folder, with its ground truth."""
    out = tmp_path_factory.mktemp('broken_src')
    sim = SimConfig(azimuth_step_deg=0.8)
    ros2 = simulate_to_bag(out / 'ros2', n_scans=N_SCANS, seed=11, config=sim, topdown_png=False)
    ros1 = simulate_to_bag(out / 'ros1', n_scans=N_SCANS, seed=11, config=sim, fmt='ros1',
                           topdown_png=False)
    return ros1, ros2


def _truncated_ros1(src, tmp: Path) -> list[str]:
    data = src[0].bag_path.read_bytes()
    (tmp / 'truncated.bag').write_bytes(data[:len(data) // 2])
    return [str(tmp / 'truncated.bag')]


def _corrupt_ros1(src, tmp: Path) -> list[str]:
    data = bytearray(src[0].bag_path.read_bytes())
    rng = random.Random(7)
    for i in range(4096, len(data), 997):  # past the version line, through chunks and index
        data[i] = rng.randrange(256)
    (tmp / 'corrupt.bag').write_bytes(bytes(data))
    return [str(tmp / 'corrupt.bag')]


def _truncated_ros2(src, tmp: Path) -> list[str]:
    folder = tmp / 'truncated_ros2'
    shutil.copytree(src[1].bag_path, folder)
    db = next(folder.glob('*.db3'))
    data = db.read_bytes()
    db.write_bytes(data[:len(data) // 2])
    return [str(folder)]


def _missing_topic(src, tmp: Path) -> list[str]:
    return [str(src[0].bag_path), '--topic', '/ouster/points']


def _empty_bag(src, tmp: Path) -> list[str]:
    with BagWriter(tmp / 'empty', fmt='ros2'):
        pass
    return [str(tmp / 'empty')]


def _only_malformed_scans(src, tmp: Path) -> list[str]:
    with BagWriter(tmp / 'malformed', fmt='ros2') as writer:
        for i in range(3):
            blob = encode_cloud({'range': np.ones(50, np.float32)})  # no x/y/z fields
            writer.write_cloud('/velodyne_points', 10**18 + i * 10**8, blob, 'velodyne')
    return [str(tmp / 'malformed')]


def _ground_truth_without_overlap(src, tmp: Path) -> list[str]:
    gt = tmp / 'gt_elsewhere.tum'
    gt.write_text(''.join(f'{1000.0 + 0.1 * i:.1f} {i} 0 0 0 0 0 1\n' for i in range(10)))
    return [str(src[0].bag_path), '--gt', str(gt)]


def _unreadable_path(src, tmp: Path) -> list[str]:
    return [str(tmp / 'no_such_dir' / 'base_1.bag')]


def _not_a_bag(src, tmp: Path) -> list[str]:
    (tmp / 'notes.bag').write_text('this is not a bag\n')
    return [str(tmp / 'notes.bag')]


# case -> (argument builder, words the one error line must contain)
CASES = {
    'truncated_ros1': (_truncated_ros1, ['truncated.bag', 'not a readable bag']),
    'corrupt_ros1': (_corrupt_ros1, ['corrupt.bag']),
    'truncated_ros2': (_truncated_ros2, ['truncated_ros2', 'not a readable bag']),
    'missing_topic': (_missing_topic, ['/ouster/points', 'not in bag', '/velodyne_points']),
    'empty_bag': (_empty_bag, ['/velodyne_points', 'not in bag', 'none']),
    'only_malformed_scans': (_only_malformed_scans, ['no decodable scan', '3 message(s)']),
    'gt_no_overlap': (_ground_truth_without_overlap, ['ground truth', 'overlap']),
    'unreadable_path': (_unreadable_path, ['does not exist']),
    'not_a_bag': (_not_a_bag, ['notes.bag', 'not', 'ROS 1 bag']),
}


def _leftovers(parent: Path, name: str) -> list[Path]:
    return sorted(parent.glob(f'{name}*'))


@pytest.mark.parametrize('case', sorted(CASES))
def test_replay_refuses_broken_input_with_one_line(case, small_bags, tmp_path, caplog):
    build, words = CASES[case]
    args = build(small_bags, tmp_path)
    out = tmp_path / 'results'
    with caplog.at_level(logging.WARNING):
        code = cli.main(['replay', *args, '--out', str(out), '--quiet', '--no-figures'])
    assert code == 1
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1, [r.getMessage() for r in errors]
    message = errors[0].getMessage()
    assert '\n' not in message and errors[0].exc_info is None
    for word in words:
        assert word in message, message
    assert _leftovers(tmp_path, 'results') == []  # no folder, no .partial-XXXX


def test_replay_error_through_the_real_command_is_one_line(tmp_path):
    missing = tmp_path / 'nowhere.bag'
    proc = subprocess.run([sys.executable, '-m', 'gft_odom.tools.cli', 'replay', str(missing),
                           '--out', str(tmp_path / 'out'), '--quiet'],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and 'Traceback' not in proc.stderr, proc.stderr
    assert str(missing) in lines[0] and lines[0].startswith('ERROR')
    assert not (tmp_path / 'out').exists()


def test_results_unwritable_location_is_one_line(small_bags, tmp_path, caplog):
    blocker = tmp_path / 'a_file'
    blocker.write_text('x')
    code = cli.main(['replay', str(small_bags[0].bag_path), '--out', str(blocker / 'out'),
                     '--quiet', '--no-figures', '--max-scans', '3'])
    assert code == 1
    assert any(str(blocker) in r.getMessage() for r in caplog.records
               if r.levelno >= logging.ERROR)


@pytest.fixture(scope='module')
def replay_result(small_bags):
    config = GftOdomConfig()
    return run_replay([small_bags[1].bag_path], config, gt_path=small_bags[1].gt_csv_path), config


def test_results_folder_appears_complete_or_not_at_all(replay_result, tmp_path, monkeypatch):
    replay, config = replay_result
    import gft_odom.figures as figures

    def broken_plot(*args, **kwargs):
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(figures, 'plot_map', broken_plot)
    out = tmp_path / 'run'
    with pytest.raises(GftOdomError, match='No space left'):
        write_results(replay, config, out, figures=True)
    assert _leftovers(tmp_path, 'run') == []
    monkeypatch.undo()
    paths = write_results(replay, config, out, figures=True)
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in paths.values())
    assert all(p.stat().st_size > 0 for p in paths.values())
    assert _leftovers(tmp_path, 'run') == [out]


def test_existing_results_folder_keeps_its_other_files(replay_result, tmp_path, monkeypatch):
    replay, config = replay_result
    out = tmp_path / 'run'
    out.mkdir()
    (out / 'notes.txt').write_text('mine')
    (out / 'metrics.json').write_text('{"old": true}')
    import gft_odom.replay as replay_module

    def failing_tum(path, traj):
        raise OSError(5, 'Input/output error')

    monkeypatch.setattr(replay_module, 'write_tum', failing_tum)
    with pytest.raises(GftOdomError, match='Input/output'):
        write_results(replay, config, out, figures=False)
    assert (out / 'metrics.json').read_text() == '{"old": true}'  # old run untouched
    assert sorted(p.name for p in out.iterdir()) == ['metrics.json', 'notes.txt']
    monkeypatch.undo()
    write_results(replay, config, out, figures=False)
    assert (out / 'notes.txt').read_text() == 'mine'
    assert '"n_scans": %d' % N_SCANS in (out / 'metrics.json').read_text()
    assert _leftovers(tmp_path, 'run') == [out]


@pytest.mark.parametrize('existing', [False, True], ids=['new_folder', 'existing_folder'])
def test_results_get_the_modes_of_the_users_umask(replay_result, tmp_path, existing):
    replay, config = replay_result
    out = tmp_path / 'run'
    if existing:
        out.mkdir()
    previous = os.umask(0o022)
    try:
        paths = write_results(replay, config, out, figures=True)
    finally:
        os.umask(previous)
    assert stat.S_IMODE(out.stat().st_mode) == 0o755  # not mkdtemp's private 0700
    for path in paths.values():
        assert stat.S_IMODE(path.stat().st_mode) == 0o644, path.name  # not mkstemp's 0600
