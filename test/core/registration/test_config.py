"""The registration's parameters: valid defaults, a clear error naming a bad field."""

from __future__ import annotations

import dataclasses

import pytest

from gft_odom.core.registration import RegistrationConfig, ScanRegistration
from gft_odom.errors import ConfigError


def test_default_config_is_valid_and_builds_both_modes():
    cfg = RegistrationConfig()
    cfg.validate()
    assert ScanRegistration(cfg).deskew
    paper = ScanRegistration(dataclasses.replace(cfg, mode='paper'))
    assert paper.mode == 'paper' and not paper.deskew  # the paper fits each sweep rigidly


@pytest.mark.parametrize('field, value, message', [
    ('mode', 'fast', 'mode'),
    ('voxel_size_m', 0.0, 'voxel_size_m'),
    ('max_correspondence_distance_m', float('nan'), 'max_correspondence_distance_m'),
    ('max_iterations', 0, 'max_iterations'),
    ('robust_kernel_scale_m', -0.3, 'robust_kernel_scale_m'),
    ('map_keyframes', 0, 'map_keyframes'),
    ('map_max_points', 10, 'map_max_points'),
    ('fallback_std_m', 0.001, 'fallback_std'),
    ('max_speed_mps', 0.0, 'max_speed_mps'),
    ('max_yaw_rate_rps', float('inf'), 'max_yaw_rate_rps'),
    ('max_gap_s', 0.05, 'max_gap_s'),
])
def test_invalid_config_names_the_field(field, value, message):
    cfg = dataclasses.replace(RegistrationConfig(), **{field: value})
    with pytest.raises(ConfigError, match=message):
        cfg.validate()
    with pytest.raises(ConfigError):
        ScanRegistration(cfg)


def test_config_fields_are_ros_parameter_types():
    for f in dataclasses.fields(RegistrationConfig):
        value = getattr(RegistrationConfig(), f.name)
        assert type(value) in (bool, int, float, str), f.name
        assert f.type in ('bool', 'int', 'float', 'str'), f.name
