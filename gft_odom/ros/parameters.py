"""ROS parameters from the config dataclasses: descriptors, start-up-only names, unknown keys.

The dataclasses are the one source of truth: a parameter's description is the comment written
above its field, its unit comes from the SI suffix of its name.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import inspect
import re

from rcl_interfaces.msg import ParameterDescriptor

from gft_odom.config import GftOdomConfig, flatten
from gft_odom.errors import ConfigError

# Read only when the node starts (a change needs a restart): declared read_only.
STARTUP_ONLY_PREFIXES = ('registration.', 'node.odom_frame', 'node.base_frame', 'evaluation.',
                         'node.base_to_sensor', 'node.publish_tf', 'ground_truth.',
                         'node.input_queue_depth', 'node.input_reliability',
                         'localisation.map_frame')
# Parameters every rclpy node has, and the qos_overrides namespace rclpy reads itself.
ROS_OWN_PARAMETERS = ('use_sim_time', 'start_type_description_service')
ROS_OWN_PREFIXES = ('qos_overrides.',)
UNIT_SUFFIXES = {
    '_m': 'm', '_s': 's', '_rad': 'rad', '_deg': 'deg', '_mps': 'm/s', '_rps': 'rad/s',
    '_radps': 'rad/s', '_hz': 'Hz', '_m2': 'm^2', '_ns': 'ns', '_mb': 'MB',
}
_FIELD = re.compile(r'^\s+(\w+)\s*:')


def is_startup_only(name: str) -> bool:
    """Whether the parameter is read at start-up only (a change needs a restart)."""
    return name.startswith(STARTUP_ONLY_PREFIXES)


def unit_of(name: str) -> str | None:
    """The unit named by the SI suffix of a parameter (`tau_m` -> m), None if it has none."""
    for suffix in sorted(UNIT_SUFFIXES, key=len, reverse=True):
        if name.endswith(suffix):
            return UNIT_SUFFIXES[suffix]
    return None


@functools.lru_cache(maxsize=None)
def _field_comments(cls) -> dict[str, str]:
    """`{field: the comment lines just above it}` from the dataclass source."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    comments: dict[str, str] = {}
    pending: list[str] = []
    for line in lines:
        stripped = line.strip()
        if stripped.startswith('#'):
            pending.append(stripped.lstrip('#').strip())
            continue
        match = _FIELD.match(line)
        if match and pending:
            comments[match.group(1)] = ' '.join(pending)
        pending = []
    return comments


def describe(name: str) -> str:
    """One line: what the parameter does, its unit, and whether it needs a restart."""
    section_name, field_name = name.split('.', 1)
    section = next(f for f in dataclasses.fields(GftOdomConfig) if f.name == section_name)
    cls = section.default_factory
    text = _field_comments(cls).get(field_name) or (inspect.getdoc(cls) or '').split('\n')[0]
    unit = unit_of(name)
    parts = [text.rstrip('.') + '.' if text else name]
    if unit:
        parts.append(f'Unit: {unit}.')
    if is_startup_only(name):
        parts.append('Read at start-up only.')
    return ' '.join(parts)


def descriptor(name: str) -> ParameterDescriptor:
    """ParameterDescriptor from the dataclass field: description, unit, read-only."""
    return ParameterDescriptor(name=name, description=describe(name),
                               read_only=is_startup_only(name))


def check_overrides(override_names, known=None) -> None:
    """Refuse a params-file key the node does not have, naming the closest valid one."""
    known = list(flatten(GftOdomConfig()) if known is None else known)
    for name in sorted(override_names):
        if name in known or name in ROS_OWN_PARAMETERS or name.startswith(ROS_OWN_PREFIXES):
            continue
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
        hint = f'; did you mean {close[0]!r}?' if close else ''
        raise ConfigError(f'unknown parameter {name!r} (params file or -p){hint}')


def check_params_files(argv) -> None:
    """Each `--params-file` of the command line exists and is YAML, before rcl reads it.

    rcl would refuse it too, but with two lines and a C source location; this says it once.
    """
    import yaml
    args = list(argv or [])
    for i, arg in enumerate(args[:-1]):
        if arg != '--params-file':
            continue
        path = args[i + 1]
        try:
            with open(path) as f:
                yaml.safe_load(f)
        except OSError as exc:
            raise ConfigError(f'params file {path}: {exc.strerror}') from None
        except yaml.YAMLError as exc:
            where = getattr(exc, 'problem_mark', None)
            line = f' (line {where.line + 1})' if where is not None else ''
            problem = getattr(exc, 'problem', None) or str(exc).split('\n')[0]
            raise ConfigError(f'params file {path} is not valid YAML{line}: {problem}') from None
