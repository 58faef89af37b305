"""The `gft-odom` command: every sub-command is there, errors become one line and exit 1."""

from __future__ import annotations

import subprocess
import sys

import pytest

from gft_odom.tools.cli import build_parser, main

COMMANDS = {'simulate', 'spectrum', 'replay', 'demo', 'config', 'search-bands', 'bench'}


def test_every_sub_command_is_registered():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == 'command')
    assert COMMANDS <= set(sub.choices)


def test_package_error_is_one_line_and_exit_code_1(caplog):
    assert main(['config', '--set', 'spectral.tau_m=-1.0']) == 1
    errors = [r for r in caplog.records if r.levelname == 'ERROR']
    assert len(errors) == 1
    assert 'tau_m' in errors[0].getMessage() and '\n' not in errors[0].getMessage()


@pytest.mark.slow
def test_console_script_runs(tmp_path):
    out = tmp_path / 'p.yaml'
    proc = subprocess.run([sys.executable, '-m', 'gft_odom.tools.cli', 'config', '--set',
                           'spectral.band_mask=[1, 9, 10]', '--out', str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert 'band_mask: [1, 9, 10]' in out.read_text()


def test_help_imports_only_the_command_it_shows():
    """`--help` must not pull in open3d / matplotlib through the other sub-commands."""
    code = ('import sys\nfrom gft_odom.tools.cli import main\n'
            'try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n'
            'print(sorted(m for m in ("open3d", "matplotlib", "gft_odom.tools.cmd_bench", '
            '"gft_odom.tools.cmd_replay") if m in sys.modules))')
    top = subprocess.run([sys.executable, '-c', code, '--help'], capture_output=True,
                         text=True, timeout=120)
    assert 'search-bands' in top.stdout and 'replay' in top.stdout
    assert top.stdout.strip().endswith('[]'), top.stdout[-300:]
    replay = subprocess.run([sys.executable, '-c', code, 'replay', '--help'],
                            capture_output=True, text=True, timeout=120)
    assert '--through-node' in replay.stdout
    assert replay.stdout.strip().endswith("['gft_odom.tools.cmd_replay']"), replay.stdout[-300:]


def test_gt_takes_no_bag_written_after_it():
    parser = build_parser('search-bands')
    args = parser.parse_args(['search-bands', 'a.bag', '--gt', 'a.csv', 'b.bag', '--out', 'o'])
    assert args.bags == ['a.bag', 'b.bag'] and args.gt == ['a.csv']
    args = parser.parse_args(['search-bands', 'a.bag', 'b.bag', '--gt', 'a.csv', '--gt', 'b.csv',
                              '--out', 'o'])
    assert args.gt == ['a.csv', 'b.csv']


def test_replay_takes_params_file_as_well_as_config():
    parser = build_parser('replay')
    args = parser.parse_args(['replay', 'x.bag', '--out', 'o', '--params-file', 'p.yaml'])
    assert args.config == 'p.yaml'


def test_a_second_override_after_one_set_is_named_as_such(tmp_path, capsys):
    """`--set a=1 b=2` leaves b=2 among the bags: the error says to give it its own --set."""
    bag = tmp_path / 'drive.bag'
    bag.write_bytes(b'')
    with pytest.raises(SystemExit) as exit_info:
        main(['replay', str(bag), '--out', str(tmp_path / 'out'), '--set',
              'registration.deskew=false', 'registration.turn_check=false'])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "'registration.turn_check=false' is not a bag" in err and '--set' in err
