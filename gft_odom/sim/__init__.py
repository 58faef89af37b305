"""Synthetic citrus orchard and Velodyne VLP-16 simulator: the project's demo and test data.

`generate_orchard` builds a scene from a seed, `make_motion` a Jackal trajectory through it,
`ScanSimulator` casts the VLP-16's rays, `simulate_to_bag` writes a CitrusFarm-like dataset.
"""

from gft_odom.sim.motion import SCENARIOS, RobotMotion, make_motion
from gft_odom.sim.orchard import Orchard, generate_orchard
from gft_odom.sim.simulator import ScanSimulator, SimConfig, SimScan
from gft_odom.sim.writer import SimulationResult, simulate_to_bag

__all__ = ['SCENARIOS', 'Orchard', 'RobotMotion', 'ScanSimulator', 'SimConfig', 'SimScan',
           'SimulationResult', 'generate_orchard', 'make_motion', 'simulate_to_bag']
