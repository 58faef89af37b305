"""Scan registration: each scan against a local map of recent keyframes (or, in the paper's
mode, against the previous scan), one concern per module.

- `config`: the parameters a user sets (`RegistrationConfig`)
- `scan_registration`: the facade, `ScanRegistration.register` as its steps (predict,
  downsample, deskew, match or re-acquire, re-deskew, trust, update the map)
- `motion`: velocity, the platform's bounds, prediction, plausibility, loss of track, deskew's
  twist
- `matching`: point-to-plane ICP over the map's search index; the paper's point-to-point ICP
- `local_map`, `anchors`, `voxels`, `map_index`: the keyframe window, what outlives it, the
  view rule, the voxel grid, the nearest-neighbour index
- `trust`: fitness against the recent matches, the run of fallbacks
- `recovery`: re-acquisition, the retry of a failed match, the turn check
- `uncertainty`: the information of a match and the reported covariance
"""

from gft_odom.core.registration.config import MODES, RegistrationConfig
from gft_odom.core.registration.scan_registration import (
    RETRIED_STATUSES,
    STATUSES,
    TRUSTED_STATUSES,
    RegistrationResult,
    ScanRegistration,
)

__all__ = ['MODES', 'RETRIED_STATUSES', 'STATUSES', 'TRUSTED_STATUSES', 'RegistrationConfig',
           'RegistrationResult', 'ScanRegistration']
