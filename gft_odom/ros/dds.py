"""Fast DDS transport profile for LiDAR-sized messages (config/fastdds_large_messages.xml).

Measured here (benchmarks/realtime_node.py): a best-effort 10 Hz VLP-16 stream on one host lost
a quarter of its clouds with Fast DDS's default 512 KB shared-memory segment, and none with a
16 MB one. The variable must be set before the process's first DDS participant is created.
"""

from __future__ import annotations

import os

PROFILE_FILE = 'fastdds_large_messages.xml'
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def use_large_message_profile(environ=os.environ) -> str | None:
    """Point Fast DDS at the packaged profile unless the user chose a profile or another RMW.

    Returns the path set, or None when nothing was changed.
    """
    from gft_odom.errors import ConfigError
    from gft_odom.params_file import packaged_params_file
    if environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp') != 'rmw_fastrtps_cpp':
        return None
    if any(environ.get(name) for name in PROFILE_VARIABLES):
        return None
    try:
        path = str(packaged_params_file(PROFILE_FILE))
    except ConfigError:
        return None
    environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = path
    return path
