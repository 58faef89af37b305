"""What the README's robot recipe relies on, checked on the colcon-built package here."""

from __future__ import annotations

import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

pytestmark = [pytest.mark.slow, pytest.mark.ros]


def test_the_node_runs_with_the_python_colcon_was_run_from(installed_node):
    """`<venv>/bin/python -m colcon build` gives a node that imports the venv's open3d."""
    exe, _ = installed_node
    colcon_python = Path(sys.executable)  # conftest runs colcon next to this interpreter
    shebang = exe.read_text().splitlines()[0]
    assert shebang.startswith('#!')
    assert Path(shebang[2:].split()[0]) == colcon_python


def test_pip_only_dependencies_are_in_requirements_and_not_in_package_xml():
    wanted = {line.split('>')[0].split('=')[0].strip()
              for line in (REPO / 'requirements.txt').read_text().splitlines()
              if line.strip() and not line.startswith('#')}
    assert {'open3d', 'rosbags'} <= wanted
    deps = {e.text for e in ET.parse(REPO / 'package.xml').getroot().iter()
            if e.tag.endswith('depend')}
    assert not {d for d in deps if 'open3d' in d or 'rosbags' in d}


def test_the_large_message_profile_is_installed(installed_node):
    exe, env = installed_node
    prefix = exe.parents[2]
    assert (prefix / 'share' / 'gft_odom' / 'config' / 'fastdds_large_messages.xml').is_file()
