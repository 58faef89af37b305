"""Degeneracy told: the weakest translation direction, on information matrices and on simulated
drives along an orchard row and across open ground."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gft_odom.core.degeneracy import translation_information, weakest_translation


def test_weakest_direction_of_a_diagonal_information():
    info = np.diag([10.0, 1000.0, 5000.0, 50.0, 50.0, 50.0])
    weak = weakest_translation(info)
    assert weak.axis == 'x' and weak.text == 'translation along x'
    assert weak.ratio == pytest.approx(10.0 / 5000.0)
    np.testing.assert_allclose(weak.direction, [1.0, 0.0, 0.0])
    assert weakest_translation(None) is None


def test_the_direction_is_expressed_in_the_axes_asked_for():
    info = np.diag([10.0, 1000.0, 5000.0, 50.0, 50.0, 50.0])
    yaw = np.deg2rad(90.0)
    R_base_info = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0],
                            [0.0, 0.0, 1.0]])
    weak = weakest_translation(info, R_base_info)
    assert weak.axis == 'y' and weak.text == 'translation along y'
    diagonal = weakest_translation(info, R_base_info @ np.array(
        [[np.cos(0.7), -np.sin(0.7), 0.0], [np.sin(0.7), np.cos(0.7), 0.0], [0, 0, 1.0]]))
    assert diagonal.text.startswith('translation along (')


def test_rotation_coupling_weakens_the_translation():
    """A translation that a rotation can imitate is weaker than its own block says."""
    info = np.diag([100.0, 100.0, 100.0, 1.0, 1.0, 1.0])
    info[0, 5] = info[5, 0] = 9.0  # x and yaw trade off
    assert translation_information(info)[0, 0] == pytest.approx(100.0 - 81.0)
    assert weakest_translation(info).axis == 'x'


def _strip(orchard, keep_trees: bool):
    """The simulated orchard, or open ground: the same terrain without trunks and crowns."""
    from gft_odom.sim.orchard import Canopies, Cylinders
    if keep_trees:
        return orchard
    cyl, can = orchard.cylinders, orchard.canopies
    return dataclasses.replace(
        orchard,
        cylinders=Cylinders(cyl.base_m[:0], cyl.axis[:0], cyl.length_m[:0], cyl.radius_m[:0],
                            cyl.surface[:0]),
        canopies=Canopies(can.centre_m[:0], can.radii_m[:0], can.sway_amplitude[:0],
                          can.sway_frequency_hz[:0], can.sway_phase_rad[:0]))


def weak_directions_of_drive(keep_trees: bool, n_scans: int = 10) -> list:
    """WeakDirection (base_link axes) of every match of a simulated row drive."""
    from gft_odom.config import GftOdomConfig
    from gft_odom.pipeline import OdometryPipeline
    from gft_odom.sim.simulator import ScanSimulator, SimConfig
    sim = ScanSimulator.from_config(SimConfig(azimuth_step_deg=0.4), 'row', n_scans, 3)
    sim.orchard = _strip(sim.orchard, keep_trees)
    pipeline = OdometryPipeline(GftOdomConfig())
    found = []
    for i in range(n_scans):
        result = pipeline.register_frame(sim.scan(i).scan)
        if result.information is not None:
            R_base_world = pipeline.T_base_sensor[:3, :3] @ result.T_world_sensor[:3, :3].T
            found.append(weakest_translation(result.information, R_base_world))
    return found


@pytest.mark.slow
def test_along_a_row_x_is_weakest_and_open_ground_leaves_the_plane_free():
    """Measured: along the row the weakest direction is along it (x) at ~0.3 of the strongest
    direction's information; on open ground only the terrain's slopes hold x and y: ~0.002."""
    from gft_odom.config import NodeConfig
    threshold = NodeConfig().weak_direction_warn_ratio
    row = weak_directions_of_drive(keep_trees=True)
    open_ground = weak_directions_of_drive(keep_trees=False)
    assert len(row) >= 7 and len(open_ground) >= 7
    assert all(w.axis == 'x' and abs(w.direction[0]) > 0.95 for w in row)
    assert all(0.15 < w.ratio < 0.6 for w in row)
    assert all(w.ratio < threshold for w in open_ground)
    assert all(abs(w.direction[2]) < 0.2 for w in open_ground)  # horizontal: z is held
