"""ROS 2 params files (`/**: ros__parameters: ...`) <-> `GftOdomConfig`.

The node gets the same file through `--ros-args --params-file`; the offline tools read it here,
so one YAML file configures both, and every run writes its effective config back in this format.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterable

import yaml

from gft_odom.config import GftOdomConfig, flatten, with_values
from gft_odom.core.constants import NODE_NAME
from gft_odom.errors import ConfigError
from gft_odom.io.atomic import write_text_atomic


def _flatten_nested(prefix: str, tree: dict, out: dict[str, Any]) -> None:
    for key, value in tree.items():
        name = f'{prefix}.{key}' if prefix else str(key)
        if isinstance(value, dict):
            _flatten_nested(name, value, out)
        else:
            out[name] = value


def read_params_file(path: str | Path, node_name: str = NODE_NAME) -> dict[str, Any]:
    """Flattened parameters that apply to `node_name` (wildcard `/**` first, then the node)."""
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f'cannot read params file {path}: {exc.strerror or exc}') from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f'params file {path} is not valid YAML: {exc}') from exc
    if not isinstance(document, dict):
        raise ConfigError(f'params file {path}: expected a mapping of node names, '
                          f'got {type(document).__name__}')
    flat: dict[str, Any] = {}
    matched = False
    for key in ('/**', '**', node_name, '/' + node_name):
        block = document.get(key)
        if block is None:
            continue
        if not isinstance(block, dict) or 'ros__parameters' not in block:
            raise ConfigError(f'params file {path}: {key!r} has no "ros__parameters" mapping')
        params = block['ros__parameters'] or {}
        if not isinstance(params, dict):
            raise ConfigError(f'params file {path}: {key}.ros__parameters must be a mapping')
        _flatten_nested('', params, flat)
        matched = True
    if not matched:
        raise ConfigError(f'params file {path}: no "/**" or "{node_name}" entry '
                          f'(found {sorted(map(str, document))})')
    # Parameters every ROS node has; they are not ours to check.
    for ros_param in ('use_sim_time', 'qos_overrides'):
        for key in [k for k in flat if k == ros_param or k.startswith(ros_param + '.')]:
            flat.pop(key)
    return flat


def parse_override(text: str) -> tuple[str, Any]:
    """`section.key=value` with a YAML value (`0.4`, `[1, 9, 10]`, `true`, `paper`)."""
    if '=' not in text:
        raise ConfigError(f'override {text!r} must look like section.key=value')
    key, raw = text.split('=', 1)
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        raise ConfigError(f'override {text!r}: value is not valid YAML: {exc}') from exc
    return key.strip(), value


def load_config(path: str | Path | None = None,
                overrides: Iterable[str] = ()) -> GftOdomConfig:
    """Defaults, then the params file, then `--set` overrides; validated."""
    flat: dict[str, Any] = {}
    if path is not None:
        flat.update(read_params_file(path))
    for text in overrides:
        key, value = parse_override(text)
        flat[key] = value
    return with_values(GftOdomConfig(), flat)


class _ParamsDumper(yaml.SafeDumper):
    """Block mappings (one parameter a line), flow lists (`band_mask: [1, 9, 10]`)."""


_ParamsDumper.add_representer(
    list, lambda dumper, data: dumper.represent_sequence('tag:yaml.org,2002:seq', data,
                                                         flow_style=True))


def config_to_yaml(config: GftOdomConfig, header: str = '') -> str:
    """The params-file text of `config` (every parameter, nested by section)."""
    nested: dict[str, dict[str, Any]] = {}
    for key, value in flatten(config).items():
        section, name = key.split('.', 1)
        nested.setdefault(section, {})[name] = list(value) if isinstance(value, tuple) else value
    text = yaml.dump({'/**': {'ros__parameters': nested}}, Dumper=_ParamsDumper,
                     sort_keys=False, width=99)
    comment = ''.join(f'# {line}\n' for line in header.splitlines())
    return comment + text


def write_params_file(path: str | Path, config: GftOdomConfig, header: str = '') -> Path:
    """Write `config` atomically (temp file + rename): a reader never sees half a file."""
    return write_text_atomic(path, config_to_yaml(config, header))


def packaged_params_file(name: str) -> Path:
    """A params file shipped with the package: `share/gft_odom/config/` when installed with
    colcon, else the source tree's `config/` (editable installs, a checkout)."""
    candidates = [Path(__file__).resolve().parents[1] / 'config' / name]
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
        candidates.insert(0, Path(prefix) / 'share' / 'gft_odom' / 'config' / name)
    for path in candidates:
        if path.is_file():
            return path
    raise ConfigError(f'params file {name!r} not found (looked in '
                      f'{", ".join(str(p.parent) for p in candidates)})')
