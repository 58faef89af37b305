"""One source of truth: dataclass defaults, config/*.yaml and the params-file I/O agree."""

from __future__ import annotations

from pathlib import Path

import pytest

from gft_odom.config import GftOdomConfig, flatten, parameter_types, with_values
from gft_odom.errors import ConfigError
from gft_odom.params_file import config_to_yaml, load_config, read_params_file, write_params_file
from gft_odom.tools.cmd_config import HEADER

CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'


def test_default_params_file_is_generated_from_the_dataclasses():
    text = (CONFIG_DIR / 'filter_odom.yaml').read_text()
    assert text == config_to_yaml(GftOdomConfig(), header=HEADER), (
        'config/filter_odom.yaml is out of date: regenerate it with '
        '`gft-odom config --out config/filter_odom.yaml`')


@pytest.mark.parametrize('path', sorted(CONFIG_DIR.glob('*.yaml')), ids=lambda p: p.name)
def test_every_params_file_loads_with_known_keys_and_types(path):
    flat = read_params_file(path)
    types = parameter_types()
    assert set(flat) <= set(types)
    config = load_config(path)
    for key, value in flat.items():
        got = flatten(config)[key]
        assert got == (tuple(value) if isinstance(value, list) else value), key
        if types[key] is float:
            # ROS refuses an int for a double parameter: the files must write 1.0, not 1.
            assert isinstance(value, float), f'{path.name}: {key} must be written as a float'


MODE_OVERLAYS = {
    'paper_mode_gft.yaml': {'spectral.n_bands': 4, 'spectral.band_mask': (3, 4),
                            'spectral.method': 'signal', 'spectral.graph': 'slice',
                            'registration.mode': 'paper'},
    'no_deskew.yaml': {'registration.deskew': False},
}


@pytest.mark.parametrize('name', sorted(MODE_OVERLAYS))
def test_mode_configs_are_overlays_on_the_defaults(name):
    path = CONFIG_DIR / name
    assert len(path.read_text().splitlines()) <= 25
    overrides = MODE_OVERLAYS[name]
    assert {k: tuple(v) if isinstance(v, list) else v
            for k, v in read_params_file(path).items()} == overrides
    loaded = flatten(load_config(path))
    defaults = flatten(GftOdomConfig())
    for key, value in loaded.items():
        assert value == overrides.get(key, defaults[key]), key
    assert all(defaults[key] != value for key, value in overrides.items())


def test_round_trip_through_a_params_file(tmp_path):
    config = with_values(GftOdomConfig(), {'spectral.tau_m': 0.4, 'spectral.band_mask': [1, 9],
                                           'registration.mode': 'paper'})
    path = write_params_file(tmp_path / 'effective.yaml', config, header='test')
    assert load_config(path) == config
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_overrides_win_over_the_file(tmp_path):
    path = write_params_file(tmp_path / 'a.yaml',
                             with_values(GftOdomConfig(), {'spectral.tau_m': 0.4}))
    config = load_config(path, ['spectral.tau_m=0.45', 'spectral.band_mask=[2, 3]'])
    assert config.spectral.tau_m == 0.45
    assert config.spectral.band_mask == (2, 3)


@pytest.mark.parametrize('flat, message', [
    ({'spectral.tau': 0.3}, 'did you mean spectral.tau_m'),
    ({'spectral.tau_m': 'wide'}, 'expected float'),
    ({'spectral.n_bands': 2.5}, 'expected int'),
    ({'pipeline.use_spectral_filter': 1}, 'expected bool'),
    ({'spectral.band_mask': 3}, 'expected a list'),
    ({'node.base_to_sensor_xyz_m': [0.0, 0.0]}, 'base_to_sensor_xyz_m'),
    ({'pipeline.min_range_m': -1.0}, 'min_range_m'),
])
def test_invalid_values_are_refused_with_the_reason(flat, message):
    with pytest.raises(ConfigError, match=message):
        with_values(GftOdomConfig(), flat)


def test_broken_params_files_give_clear_errors(tmp_path, refuses_file):
    refuses_file(load_config, '/**: {ros__parameters: [unclosed', ConfigError, 'not valid YAML')
    refuses_file(load_config, 'some_node:\n  ros__parameters:\n    a: 1\n', ConfigError,
                 'no "/\\*\\*" or "filter_odom_node" entry')
    with pytest.raises(ConfigError, match='cannot read'):
        load_config(tmp_path / 'missing.yaml')
