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


# Python module -> rosdep key, for every third-party import of gft_odom/ and launch/.
ROSDEP_KEYS = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm',
    'hypothesis': 'python3-hypothesis', 'pytest': 'python3-pytest',
}
# No usable rosdep key: installed by pip (requirements.txt), or optional extras of the tools.
# apsw: rosbags' sqlite; kiss_icp, genz_icp, evo, evalio: the benchmarks' peers and metrics.
PIP_ONLY = {'open3d', 'rosbags', 'apsw', 'ray', 'kiss_icp', 'genz_icp', 'evo', 'evalio'}
ROS_PACKAGE_PREFIXES = ('rcl', 'rclpy', 'launch', 'ament_')


def _third_party_imports(paths) -> set[str]:
    import sys
    names: set[str] = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names.update(alias.name.split('.')[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split('.')[0])
    return {n for n in names if n not in sys.stdlib_module_names and n != 'gft_odom'}


def _is_ros_package(name: str) -> bool:
    return name.endswith(('_msgs', '_srvs', '_interfaces', '_ros')) or name.startswith(
        ROS_PACKAGE_PREFIXES)


def test_package_xml_declares_every_ros_package_the_code_imports():
    root = ET.parse(REPO / 'package.xml').getroot()
    exec_deps = {e.text for e in root.findall('exec_depend')}
    test_deps = {e.text for e in root.findall('test_depend')}
    code = _third_party_imports([*(REPO / 'gft_odom').rglob('*.py'),
                                 *(REPO / 'launch').glob('*.py')])
    assert {'rclpy', 'launch', 'launch_ros', 'ament_index_python'} <= code  # the scan works
    missing = sorted(ROSDEP_KEYS.get(n, n) for n in code - PIP_ONLY
                     if ROSDEP_KEYS.get(n, n) not in exec_deps)
    assert not missing, f'add <exec_depend> for {missing} to package.xml'
    unknown = sorted(n for n in code - PIP_ONLY if n not in ROSDEP_KEYS and not _is_ros_package(n))
    assert not unknown, f'map {unknown} to a rosdep key (ROSDEP_KEYS) or list it as PIP_ONLY'
    local = {p.stem for p in (REPO / 'test').rglob('*.py')}  # test/helpers.py and the like
    tests = _third_party_imports((REPO / 'test').rglob('*.py')) - PIP_ONLY - local
    missing_test = sorted(ROSDEP_KEYS.get(n, n) for n in tests
                          if ROSDEP_KEYS.get(n, n) not in exec_deps | test_deps)
    assert not missing_test, f'add <test_depend> for {missing_test} to package.xml'


def test_one_version_in_setup_package_xml_and_the_package():
    import re

    import gft_odom
    setup_version = re.search(r"version='([^']+)'", (REPO / 'setup.py').read_text()).group(1)
    xml_version = ET.parse(REPO / 'package.xml').getroot().findtext('version')
    assert setup_version == xml_version == gft_odom.__version__
    changelog = (REPO / 'CHANGELOG.md').read_text()
    assert f'## [{gft_odom.__version__}]' in changelog
