"""One exception root for the package, one subclass per concern.

Library code raises these; only the CLI turns them into exit codes and the node into log lines.
"""


class GftOdomError(Exception):
    """Root of every error gft_odom raises on purpose."""


class ConfigError(GftOdomError):
    """A parameter value or parameter file is invalid."""


class CodecError(GftOdomError):
    """A PointCloud2 message cannot be decoded or encoded."""


class BagError(GftOdomError):
    """A bag cannot be read or written (missing file or topic, wrong type, corrupt data)."""


class GroundTruthError(GftOdomError):
    """A ground-truth or trajectory file cannot be read or matched."""


class SpectralError(GftOdomError):
    """The spectral filter got input it cannot process."""


class RegistrationError(GftOdomError):
    """Scan registration got input it cannot process."""


class SimulationError(GftOdomError):
    """The orchard simulator got an invalid request."""


class MapError(GftOdomError):
    """A map to localise in is missing, unreadable, empty or in another frame."""
