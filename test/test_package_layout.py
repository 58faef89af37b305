"""What colcon and `ros2 run` / `ros2 launch` rely on, checked without a ROS install."""

from __future__ import annotations

import ast
import configparser
import py_compile
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_launch_file_compiles_and_names_an_existing_params_file(tmp_path):
    launch = REPO / 'launch' / 'filter_odom.launch.py'
    py_compile.compile(str(launch), cfile=str(tmp_path / 'launch.pyc'), doraise=True)
    tree = ast.parse(launch.read_text())
    constants = {node.targets[0].id: node.value.value for node in tree.body
                 if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant)}
    assert (REPO / 'config' / constants['PARAMS_FILE']).is_file()
    text = launch.read_text()
    assert "executable='filter_odom_node'" in text and "package='gft_odom'" in text


def test_package_xml_is_format_3_ament_python_with_the_runtime_dependencies():
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'gft_odom'
    assert root.find('export/build_type').text == 'ament_python'
    exec_deps = {e.text for e in root.findall('exec_depend')}
    assert {'rclpy', 'sensor_msgs', 'nav_msgs', 'geometry_msgs', 'std_msgs'} <= exec_deps


def test_scripts_install_where_ros2_run_looks():
    cfg = configparser.ConfigParser()
    cfg.read(REPO / 'setup.cfg')
    assert cfg['develop']['script_dir'] == '$base/lib/gft_odom'
    assert cfg['install']['install_scripts'] == '$base/lib/gft_odom'
    assert (REPO / 'resource' / 'gft_odom').is_file()
    setup_py = (REPO / 'setup.py').read_text()
    assert "'filter_odom_node = gft_odom.ros.node:main'" in setup_py
    assert "find_packages(exclude=['test', 'test.*'])" in setup_py
