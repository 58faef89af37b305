"""The import graph goes one way down: core <- io <- config/sim <- pipeline <- tools/ros."""

from __future__ import annotations

import ast
from pathlib import Path

import gft_odom

PACKAGE_DIR = Path(gft_odom.__file__).parent

# Lower number = lower layer. A module may import its own layer and the ones below.
LAYERS = {
    'errors': 0, 'core': 0,
    'io': 1,
    'config': 2, 'params_file': 2, 'sim': 2,
    'pipeline': 3, 'replay': 3, 'bands': 3, 'figures': 3, 'bench': 3, 'tables': 3,
    'tools': 4, 'ros': 4,
}
ROS_MODULES = {'rclpy', 'sensor_msgs', 'nav_msgs', 'geometry_msgs', 'std_msgs',
               'builtin_interfaces', 'rosgraph_msgs', 'tf2_ros', 'tf2_msgs', 'rcl_interfaces',
               'std_srvs', 'diagnostic_msgs'}
FORBIDDEN_EXTERNAL = {
    0: ROS_MODULES | {'yaml', 'argparse', 'tqdm', 'matplotlib', 'rosbags'},
    1: ROS_MODULES | {'argparse', 'tqdm'},
    2: ROS_MODULES | {'argparse'},
    3: ROS_MODULES | {'argparse'},
    4: set(),
}
# Within the top layer, only ros/ talks ROS: the CLI reaches the node through gft_odom.ros.
FORBIDDEN_EXTERNAL_PER_PACKAGE = {'tools': ROS_MODULES}


def _layer_of(module_parts: tuple[str, ...]) -> int:
    return LAYERS[module_parts[0].removesuffix('.py')]


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def test_imports_go_one_way_down():
    violations = []
    for path in sorted(PACKAGE_DIR.rglob('*.py')):
        rel = path.relative_to(PACKAGE_DIR).parts
        if rel == ('__init__.py',):
            continue
        layer = _layer_of(rel)
        for name in _imports(path):
            parts = name.split('.')
            if parts[0] == 'gft_odom' and len(parts) > 1:
                target = LAYERS.get(parts[1], 4)
                if target > layer:
                    violations.append(f'{"/".join(rel)} (layer {layer}) imports {name} '
                                      f'(layer {target})')
            elif parts[0] in FORBIDDEN_EXTERNAL[layer] | FORBIDDEN_EXTERNAL_PER_PACKAGE.get(
                    rel[0], set()):
                violations.append(f'{"/".join(rel)} (layer {layer}) imports {name}')
    assert not violations, '\n'.join(violations)


def test_layer_table_knows_every_top_level_module():
    tops = {p.name.removesuffix('.py') for p in PACKAGE_DIR.iterdir()
            if (p.suffix == '.py' or p.is_dir()) and not p.name.startswith(('_', '.'))}
    assert tops <= set(LAYERS), f'add {sorted(tops - set(LAYERS))} to LAYERS'
