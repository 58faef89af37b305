"""Scan registration: ICP on open3d, a constant-velocity motion prior, a local map, fallbacks.

Two modes share one backend so that filtered/unfiltered comparisons are fair:

- `paper`: the paper's baseline. Each scan is registered to the previous scan with
  point-to-point ICP started at identity; the per-scan transforms are chained. No deskew,
  no robust kernel, no map.
- `default`: constant-velocity prediction as the initial guess, scan-to-local-map ICP
  (point-to-plane with a Tukey kernel unless configured otherwise) against a keyframe local
  map, optional deskew (per-point `time`, or the azimuth when the bag has none; off by
  default, see the config). docs/registration.md has the measurements behind these choices.

Registration never raises for bad geometry: too few points, a low fitness, a jump far from
the prediction or a motion no Jackal can make return the prediction with a `fallback_*` status
and an inflated covariance, and the next scan goes on. RegistrationError is raised only for
malformed input.

The parts, one concern each (`ScanRegistration.register` runs them in turn: predict,
downsample, deskew, match or re-acquire, trust, update the map, the result):

- here: RegistrationConfig (every parameter), ScanRegistration (the steps, re-acquisition,
  the reference update), TrustPolicy (fitness against the recent matches, the fallback run)
- core/motion_model.py: MotionModel (velocity, trusted pose, physical bounds, prediction,
  plausibility, jumps, loss of track, the twists deskew assumes)
- core/icp_backend.py: IcpBackend (one ICP call: map_tree, open3d or the Gauss-Newton solver)
- core/gauss_newton.py, core/residuals.py: the Gauss-Newton solver and its per-pair residuals
- core/map_tree_icp.py: open3d's point-to-plane ICP over the map's own KD-tree
- core/uncertainty.py: the information of the final pairs and the reported covariance
- core/local_map.py: the keyframe local map (voxel downsampling too)
- core/deskew.py: per-point times and motion compensation

Motion model: a velocity (rad/s, m/s) from the last trusted match, extrapolated over the real
stamp difference and capped by the physical bounds. Plausibility, the velocity and
re-acquisition are measured from the last trusted pose over the time since it, never from a
fallback's extrapolated one. After a gap (> `max_gap_s`) or
`max_consecutive_fallbacks` fallbacks in a row the velocity is dropped and the next scan is
re-acquired against the local map from a few initial guesses (status `recovered`), so one bad
patch of data cannot make every later prediction miss.

Frames: `T_world_sensor` is the sensor pose at the scan's stamp, world = the sensor frame at the
first registered scan. `covariance` is the (6, 6) uncertainty of this scan's registration
(x, y, z, rot_x, rot_y, rot_z; world axes, about the sensor origin), not accumulated drift.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import open3d as o3d

from gft_odom.core.constants import SCAN_PERIOD_S
from gft_odom.core.deskew import azimuth_time_offsets, deskew_points
from gft_odom.core.geometry import along_beams, finite_rows, invert_transform, transform_points
from gft_odom.core.icp_backend import RECOVERY_ITERATIONS_FACTOR as RECOVERY_ITERATIONS_FACTOR
from gft_odom.core.icp_backend import IcpBackend
from gft_odom.core.local_map import (
    KEYFRAME_EVICTIONS,
    VOXEL_KEEPS,
    LocalMap,
    to_cloud,
    voxel_downsample_indices,
)
from gft_odom.core.motion_model import MotionModel
from gft_odom.core.motion_model import delta_of_twist as delta_of_twist
from gft_odom.core.motion_model import scale_delta as scale_delta
from gft_odom.core.motion_model import transform_magnitude as transform_magnitude
from gft_odom.core.motion_model import twist_of as twist_of
from gft_odom.core.residuals import RESIDUAL_MODELS, ROUGH_RESIDUALS, smoothness_from_nu
from gft_odom.core.uncertainty import PoseUncertainty, icp_information, world_information
from gft_odom.core.uncertainty import in_world_axes as in_world_axes
from gft_odom.errors import ConfigError, RegistrationError

log = logging.getLogger(__name__)

MODES = ('default', 'paper')
# What a keyframe adds to the local map: the registration's downsampled points, or the whole
# scan downsampled at the map's voxel (denser, costs a downsample per keyframe).
MAP_POINTS_FROM = ('registration', 'scan')
ESTIMATIONS = ('auto', 'point_to_plane', 'point_to_point', 'gicp')
ROBUST_KERNELS = ('none', 'tukey', 'huber', 'cauchy')
SOLVERS = ('open3d', 'gauss_newton', 'map_tree')
MAP_NORMALS = ('rebuild', 'on_demand', 'kept')
MAP_UPDATES = ('auto', 'inline', 'background')
VOXEL_PRIORITIES = ('first', 'smoothest')
# Every status `register` / `advance_with_prediction` can return.
STATUSES = ('first', 'ok', 'recovered', 'fallback_too_few_points', 'fallback_low_fitness',
            'fallback_diverged', 'fallback_implausible', 'fallback_degenerate')
# Matches whose median fitness min_relative_fitness refers to (and the fewest it needs).
RECENT_FITNESS_WINDOW = 10
RECENT_FITNESS_MIN = 3
# Poses trusted enough to update the velocity and the reference (map or previous scan).
TRUSTED_STATUSES = ('first', 'ok', 'recovered')
# Failed matches from the prediction that `retry_failed_match` re-acquires at once.
RETRIED_STATUSES = ('fallback_low_fitness', 'fallback_diverged', 'fallback_implausible')


@dataclass(frozen=True)
class RegistrationConfig:
    """Parameters of ScanRegistration; defaults chosen by benchmarks/bench_registration.py."""

    # 'default' (our design) or 'paper' (scan-to-scan point-to-point ICP from identity).
    mode: str = 'default'
    # 'auto' = point_to_point in paper mode (as the paper), point_to_plane in default mode.
    estimation: str = 'auto'
    # Source voxel: ~3k of the ~26k points of a VLP-16 orchard scan, plenty for 6 DoF.
    voxel_size_m: float = 0.4
    # Largest point pair ICP accepts: a few voxels, above the worst prediction error at 2 m/s.
    max_correspondence_distance_m: float = 1.0
    max_iterations: int = 30
    # Stop when the relative fitness and rmse changes fall below this: 1e-4 gave the same ATE
    # as 1e-6 on the simulated drives at half the ICP time.
    convergence_relative: float = 1e-4
    # Robust kernel of point_to_plane and gicp in default mode (point_to_point has none).
    robust_kernel: str = 'tukey'
    # Tukey c: residuals beyond it get zero weight; ~4 sigma of canopy sway + range noise.
    robust_kernel_scale_m: float = 0.3
    # Solver 'map_tree': the Tukey scale of a rough scan point (smoothness 0: canopy), blended
    # linearly to robust_kernel_scale_m at smoothness 1 (ground, trunks). 0: every pair
    # robust_kernel_scale_m (also without frequencies). Session 18 study, docs/registration.md.
    rough_kernel_scale_m: float = 0.0
    # Each source point moved along its beam by this times (1 - smoothness), before the
    # match and into the map (positive: away from the sensor; unknown smoothness: not
    # moved; without frequencies nothing moves). Session 22 study, docs/registration.md:
    # toward the sensor (the canopy's entry point) doubled the training ATE; 0.1 m away
    # gained 9 % there, and 16 % with the frequencies shuffled: a stretch, not the
    # frequency's choice. Not run on held-out drives. 0: off.
    rough_beam_shift_m: float = 0.0
    # GICP covariance regulariser (open3d epsilon).
    gicp_epsilon: float = 1e-3
    # Local map (default mode): voxel, radius around the newest keyframe, hard point cap.
    # 60 keyframes, not 15: on the four long varied training drives (docs/benchmarks.md) a
    # 15 m memory drifted (mean ATE 0.222 m over ~230 m); 60 more than halved it (0.101 m).
    map_voxel_size_m: float = 0.3
    map_max_range_m: float = 40.0
    map_max_points: int = 80000
    map_keyframes: int = 60
    # Which keyframe a full map drops: 'oldest' (a window in time) or 'farthest' from the
    # newest keyframe (a window in space, as kiss-icp's range-cropped voxel map). 'farthest'
    # with 1 rad rotation keyframes helped on three training drives and lost track on the
    # fourth (1.38 m ATE, 49 fallbacks), so the default stays 'oldest'.
    map_keyframe_eviction: str = 'oldest'
    # What a keyframe adds: the registration's downsampled points, or the whole scan at the
    # map voxel ('scan': denser, a downsample per keyframe). Studied, not the default.
    map_points_from: str = 'registration'
    # Which point a voxel seen by several keyframes keeps. 'oldest': the map stays anchored
    # to what was seen first instead of following each new keyframe's small error (GenZ-ICP
    # and kiss-icp never replace a filled voxel either). With retry_failed_match: mean ATE
    # 0.097 -> 0.070 m on the seven training drives (docs/benchmarks.md, round 3).
    # 'mean' keeps the centroid of every keyframe's point in the voxel (all the views);
    # 'mean_rough' lets the frequency choose: the oldest point where the voxel is smooth on
    # average (ground, trunks), the mean where it is rough (canopy, whose returns depend on
    # the viewpoint). 'nearest': the point seen from closest. Session 14, docs/registration.md.
    map_voxel_keeps: str = 'oldest'
    # Anchors: when a keyframe leaves the window its points of smoothness >= this (graph
    # frequency nu / smooth_nu: ground, trunks, posts) stay in the map (served while within
    # map_max_range_m), so a row met again after the window has moved on registers against
    # what it showed before; canopy, which looks different from another row, leaves with the
    # keyframe. Without frequencies (--no-filter) nothing stays; at 0 every point stays.
    # Training drives 111-114, 118 (docs/registration.md, session 6), mean ATE: no anchors
    # 0.093 m, smooth points 0.090 m, every point 0.087 m. Every point was the training's
    # choice, but it lost track on held-out every_other_row-202 (5.0 m, against 0.259 m
    # without anchors and 0.144 m with the smooth points), so the default keeps the smooth
    # points: that choice saw a held-out drive (docs/registration.md says so).
    map_anchors: bool = True
    map_anchor_smoothness: float = 0.75
    # Memory bound of a long run (~64 bytes a point); beyond it the farthest anchors go.
    map_anchor_max_points: int = 2_000_000
    # Rough anchors: > 0 keeps the rest of a leaving keyframe too (canopy; every point when
    # there is no frequency), served only while the newest keyframe sees a point from within
    # this angle of the side it was measured from. Porous canopy seen from the far lane is
    # another cloud; smooth anchors are served from any side. 0: rough points leave.
    # Chosen on the training drives (session 9: mean ATE 0.090 -> 0.087 m); on the eight
    # held-out drives (session 14) it gained where rows are met again late (spiral-203,
    # every_other_row-212) and lost 12 % on every_other_row-202 (docs/registration.md).
    map_anchor_rough_view_deg: float = 60.0
    # This share of the rough anchors (drawn by voxel) is served from any side as well. The
    # shuffled control, which serves a random share from any side, beat the frequency on the
    # drives that meet rows again from the other side (session 15). Mean ATE with 0.25
    # against 0: training -2 %, held-out -7 % (session 15), drives 231-234 never used for a
    # choice -3 % (session 16); as good without frequencies (docs/registration.md). 0: none.
    map_anchor_rough_any_side_share: float = 0.25
    keyframe_distance_m: float = 1.0
    keyframe_rotation_rad: float = 0.2
    normal_neighbours: int = 15
    # Below this many downsampled points ICP is not attempted.
    min_points: int = 100
    # open3d fitness = inlier pairs / source points; below it the result is not trusted.
    min_fitness: float = 0.3
    # Default mode: a fitness below this fraction of the median of the last matches is not
    # trusted either. Scan-to-map fitness is steady (0.8-0.97 on the simulated drives); a
    # copy of a scan rotated 90 deg still reached 0.48 near the prediction, enough for
    # min_fitness, and would have entered the map at a keyframe.
    min_relative_fitness: float = 0.7
    # Largest correction to the constant-velocity prediction per scan period: a Jackal
    # (2 m/s, ~2 rad/s top speed) cannot change its velocity by more within 0.1 s. Scaled
    # by the time the prediction covers: a scan 30 ms after the last may stray 0.3 x as far
    # (session 18: with deskew, mirrored copies 30 ms after a row scan were trusted 0.2 rad
    # off; docs/robustness.md).
    max_translation_jump_m: float = 0.5
    max_rotation_jump_rad: float = 0.25
    # Physical bounds: a Clearpath Jackal tops out at 2.0 m/s. The rotation bound applies to
    # the whole rotation angle (yaw dominates on a ground robot; bumps add roll and pitch).
    # A registration implying faster motion over the real stamp difference is rejected
    # (`fallback_implausible`, never enters the map); predictions are capped by the same.
    max_speed_mps: float = 2.0
    max_yaw_rate_rps: float = 4.0
    # Relative slack on both bounds for stamp jitter and ICP noise over short steps; a copy
    # of a scan rotated 90 deg 30 ms later implies 52 rad/s, far beyond it.
    motion_margin: float = 0.5
    # A stamp step longer than this is a gap: the velocity is not extrapolated over it and the
    # scan is re-acquired against the map (zero motion and last velocity as initial guesses).
    max_gap_s: float = 1.0
    # This many fallbacks in a row drop the velocity and re-acquire the same way.
    max_consecutive_fallbacks: int = 3
    # A match from the prediction that fails (low fitness, diverged, implausible) is tried
    # again at once the way re-acquisition does (several guesses, coarse then fine ICP),
    # and kept as `recovered` if that passes the fitness checks and the bounds. At the start
    # of a pivot the yaw rate jumps within a scan and ICP from the prediction can slide
    # along the row (0.45 m at fitness 0.90 on training drive every_other_row-118).
    retry_failed_match: bool = True
    # Re-acquisition runs a coarse ICP with the correspondence distance widened by this
    # factor from each guess, then the normal ICP; the best plausible fit wins.
    recovery_correspondence_factor: float = 3.0
    # Re-acquisition also tries the velocity before the loss with its yaw rate changed by
    # k x recovery_yaw_rate_step_rps, k = 1..recovery_yaw_guesses, either way (0: none). At
    # the onset of a fast turn in open ground (a headland past the block's edge) ICP from a
    # guess without the turn slides along the track instead of turning: the ground fits any
    # yaw, and the far row ends that fix it are outside the correspondence gate. Turned
    # guesses are tried only when no other guess gives an acceptable fit, and a turned fit
    # must fit better than every other guess's, refused ones included (else it is a local
    # minimum, not a turn). Edge drives 221 / 222: ATE 57 / 60 m -> 5.6 / 38 m: better, but
    # still lost; a drive whose plain guesses never fail is unchanged (docs/registration.md).
    recovery_yaw_guesses: int = 2
    recovery_yaw_rate_step_rps: float = 1.0
    # ... and only when the best plain fit is below this x the recent matches' median fitness:
    # a missed turn leaves every plain fit poor (edge drive 221: 0.77-0.80, ~0.92-0.95 before),
    # while a platform beyond the speed bound fits well and is refused on every scan (the
    # turned guesses would only add their cost there: 103 ms median in the node test).
    recovery_turn_relative_fitness: float = 0.95
    # A trusted match that fits below recovery_turn_relative_fitness x the recent median is
    # matched again from turned guesses (the current velocity with its yaw rate changed as
    # above), and the best turned fit replaces it when it fits better by
    # turn_check_fitness_margin (and passes every check a match does). At a turn's onset in
    # open ground ICP from the prediction settles on a pose turned too little, and it is
    # trusted: on edge drive 221 (scan 422) at fitness 0.83 where ICP from the true motion
    # gives 0.92, against 0.001-0.006 between near ties elsewhere. Session 20: edge drives
    # 221-224 ATE 25.9 / 24.8 / 71.6 / 0.19 m -> 4.3 / 1.4 / 0.07 / 0.12 m, the ten held-out
    # drives unchanged (docs/registration.md).
    turn_check: bool = True
    turn_check_fitness_margin: float = 0.03
    # Each turned guess of the turn check is matched with the scan deskewed by the motion it
    # stands for (as the scan is deskewed again once trusted: the mean of the recent twist
    # and the guess's), not by the prediction's. At a turn's onset the prediction has no turn,
    # so its deskew bends the sweep the wrong way by up to the missed yaw rate x the scan
    # period (0.2 rad at 2 rad/s), and a turned pose matched with that sweep fits poorly.
    turn_guess_deskew: bool = True
    # The solver of default mode: 'map_tree' (core/map_tree_icp.py: open3d's point-to-plane
    # ICP step for step, over a search index built once per map rebuild, not once per call:
    # the same trajectory, 0.74-0.87x the latency median on the held-out drives), 'open3d'
    # (its ICP: one residual type for every pair) or 'gauss_newton' (core/gauss_newton.py: a
    # residual type and weight per pair, set by residual_model). 'map_tree' is
    # point-to-plane: with estimation gicp or point_to_point, open3d's ICP runs. Paper mode
    # always uses open3d's point-to-point ICP.
    solver: str = 'map_tree'
    # Solver 'map_tree': Anderson acceleration over this many past steps (0: off, open3d's
    # iterates). ICP's pose slides towards the optimum a near-constant share per iteration;
    # the extrapolation gets there in fewer iterations, kept only where it lowers the energy.
    anderson_memory: int = 0
    # When the map's kNN normals are estimated (solvers 'map_tree' and 'gauss_newton'):
    # 'rebuild' (every map point's, at each keyframe: open3d's estimate_normals, most of a
    # keyframe's map update, which runs after the pose) or 'on_demand' (a point's when a
    # pair first uses it, carried over a rebuild while its neighbours stay its own: the same
    # normals, so the same trajectory; the work moves into the matches, before the pose,
    # docs/registration.md sessions 12-13) or 'kept' (a point's once, when it enters the map,
    # kept while it stays: only the new points' at a keyframe, not what a fresh estimate
    # would give where new neighbours came; session 15).
    map_normals: str = 'rebuild'
    # When a keyframe's map rebuild is done: 'inline' (before the next scan is matched) or
    # 'background' (on a thread, while the next scan is matched against the map before it;
    # the scan after that adopts it). A keyframe's rebuild (~150 ms at the p95) then no
    # longer holds up the next scan, and the poses do not depend on the thread's speed.
    # 'background' needs solver 'map_tree' or 'gauss_newton', map_normals 'rebuild',
    # point-to-plane estimation and no 'planarity' model; 'auto' is 'background' where
    # those hold and 'inline' elsewhere. Not the default (session 16): 2 % ATE on the
    # training drives; where a scan's work nears the period the thread's share of the cores
    # lengthens the queue (lawnmower-111, paced p95 1.2 s against 0.33 s inline); and a
    # platform beyond the speed bound is no longer told within 16 scans (test_bounds_watch):
    # its matches against the older map scatter.
    map_update: str = 'inline'
    # Gauss-Newton only (core/residuals.py): 'plane' (every pair point-to-plane, weight 1),
    # 'frequency' (the scan point's graph frequency decides: smooth -> plane, rough -> the
    # rough residual), 'planarity' (the map neighbourhood's covariance decides, GenZ-ICP-style).
    residual_model: str = 'plane'
    # What rough points contribute: 'beam_perpendicular' (point-to-point across the beam
    # only: canopy returns sit at random depths along it) or 'point' (GenZ-ICP's).
    rough_residual: str = 'beam_perpendicular'
    rough_weight: float = 1.0
    # rough_residual 'beam_covariance': how many times less certain a rough (canopy) return
    # is along its beam than across it (its depth in the foliage).
    rough_depth_ratio: float = 5.0
    # 'frequency': smoothness = nu / smooth_nu clipped to [0, 1] (ground and trunks ~0.5,
    # canopy ~0 on the scan-line graph).
    smooth_nu: float = 0.4
    # 'planarity': smoothness = 1 - surface variation / this (a plane 0, a blob 1/3).
    rough_surface_variation: float = 0.1
    # Which point of a source voxel registration uses (and a keyframe adds to the map):
    # 'first' (in scan order) or 'smoothest' (the highest graph frequency nu: a ground or
    # trunk return is preferred to a canopy return of the same voxel; needs nu).
    voxel_priority: str = 'first'
    # Gauss-Newton stops when the update's norm (m, rad) falls below this.
    convergence_m: float = 1e-4
    # Gauss-Newton: match like with like. The map remembers each point's smoothness (its
    # scan point's nu / smooth_nu), and a scan point picks, among its nearest map points,
    # the one nearest once a smoothness mismatch d counts as affinity_m * d of distance:
    # canopy pairs with canopy, ground and trunks with their own surface. 0: distance alone
    # (also what --no-filter gives: no frequencies, nothing to compare).
    frequency_affinity_m: float = 0.0
    # Gauss-Newton: the constant-velocity prediction as a soft prior on the match, worth this
    # many pairs along every axis (rotations scaled by the median range squared). Where the
    # scene constrains a direction (thousands of pairs) it is negligible; where it does not
    # (open ground past a row end: along the track and yaw) it holds the prediction instead of
    # letting the estimate slide. 0: no prior.
    motion_prior_weight: float = 0.0
    # Motion compensation (default mode only). An undeskewed sweep registers to about its
    # mid-sweep pose, ~50 ms after the stamp it is published with. Session 5 found it mixed
    # (better on two of three training drives, and 5 of 9 mirrored copies of a row scan
    # trusted). Session 18, on the anchored map: training mean ATE 0.085 -> 0.055 m (window 2),
    # every drive better; the mirrored copies are refused by jump bounds scaled to the 30 ms
    # they come after (docs/registration.md). config/no_deskew.yaml turns it off.
    deskew: bool = True
    # Deskew with forward motion and yaw rate only (ground robot); false: full 6-DoF twist.
    deskew_planar: bool = True
    # Deskew velocity = mean twist of the last this many trusted scans (ICP noise averages out,
    # but a mean over many lags where the yaw rate jumps). With 5, held-out lawnmower-205 lost
    # 0.14 rad of heading at the onset of a 1 rad/s turn (ATE 3.8 m); training drives, mean
    # ATE: window 1 0.057 m, 2 0.055 m, 5 0.057 m (session 18, docs/registration.md).
    deskew_velocity_window: int = 2
    scan_period_s: float = SCAN_PERIOD_S
    # Azimuth-derived times only: ROS velodyne drivers stamp with the last packet by default
    # (timestamp_first_packet: false); set true when the bag's header.stamp is the sweep end.
    azimuth_stamp_at_sweep_end: bool = False
    # Return the full-resolution deskewed scan in the result (costs ~2 ms for 30k points).
    output_deskewed_points: bool = False
    # 1-sigma floor of an accepted registration and the inflated values of a fallback.
    min_std_m: float = 0.005
    min_std_rad: float = 0.001
    fallback_std_m: float = 1.0
    fallback_std_rad: float = 0.3

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""
        if self.mode not in MODES:
            raise ConfigError(f'mode must be one of {MODES}, got {self.mode!r}')
        if self.estimation not in ESTIMATIONS:
            raise ConfigError(f'estimation must be one of {ESTIMATIONS}, got {self.estimation!r}')
        if self.map_keyframe_eviction not in KEYFRAME_EVICTIONS:
            raise ConfigError(f'map_keyframe_eviction must be one of {KEYFRAME_EVICTIONS}, '
                              f'got {self.map_keyframe_eviction!r}')
        if self.map_voxel_keeps not in VOXEL_KEEPS:
            raise ConfigError(f'map_voxel_keeps must be one of {VOXEL_KEEPS}, '
                              f'got {self.map_voxel_keeps!r}')
        if self.map_points_from not in MAP_POINTS_FROM:
            raise ConfigError(f'map_points_from must be one of {MAP_POINTS_FROM}, '
                              f'got {self.map_points_from!r}')
        if self.voxel_priority not in VOXEL_PRIORITIES:
            raise ConfigError(f'voxel_priority must be one of {VOXEL_PRIORITIES}, '
                              f'got {self.voxel_priority!r}')
        if self.solver not in SOLVERS:
            raise ConfigError(f'solver must be one of {SOLVERS}, got {self.solver!r}')
        if self.map_normals not in MAP_NORMALS:
            raise ConfigError(f'map_normals must be one of {MAP_NORMALS}, '
                              f'got {self.map_normals!r}')
        if self.map_normals != 'rebuild' and self.solver == 'open3d':
            raise ConfigError(f"map_normals {self.map_normals!r} needs solver 'map_tree' or "
                              "'gauss_newton' (open3d's ICP estimates its own)")
        if self.map_update not in MAP_UPDATES:
            raise ConfigError(f'map_update must be one of {MAP_UPDATES}, '
                              f'got {self.map_update!r}')
        if self.map_update == 'background' and not self._background_map_possible:
            raise ConfigError("map_update 'background' needs mode 'default', solver "
                              "'map_tree' or 'gauss_newton', map_normals 'rebuild', "
                              "point-to-plane estimation and no 'planarity' residual model "
                              "('auto' falls back to 'inline' where these do not hold)")
        if self.residual_model not in RESIDUAL_MODELS:
            raise ConfigError(f'residual_model must be one of {RESIDUAL_MODELS}, '
                              f'got {self.residual_model!r}')
        if self.rough_residual not in ROUGH_RESIDUALS:
            raise ConfigError(f'rough_residual must be one of {ROUGH_RESIDUALS}, '
                              f'got {self.rough_residual!r}')
        if self.residual_model != 'plane' and self.solver != 'gauss_newton':
            raise ConfigError(f"residual_model {self.residual_model!r} needs solver "
                              f"'gauss_newton' (open3d's ICP has one residual type)")
        if self.anderson_memory and self.solver != 'map_tree':
            raise ConfigError("anderson_memory needs solver 'map_tree'")
        if self.frequency_affinity_m > 0.0 and self.solver != 'gauss_newton':
            raise ConfigError("frequency_affinity_m needs solver 'gauss_newton' (open3d's "
                              "ICP pairs by distance alone)")
        if self.robust_kernel not in ROBUST_KERNELS:
            raise ConfigError(
                f'robust_kernel must be one of {ROBUST_KERNELS}, got {self.robust_kernel!r}')
        for name in ('motion_prior_weight', 'frequency_affinity_m', 'rough_weight',
                     'motion_margin', 'rough_kernel_scale_m'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ConfigError(f'{name} must be a finite number >= 0, got {value}')
        if self.rough_kernel_scale_m > 0.0 and self.solver != 'map_tree':
            raise ConfigError("rough_kernel_scale_m needs solver 'map_tree'")
        if not (math.isfinite(self.rough_beam_shift_m) and abs(self.rough_beam_shift_m) <= 1.0):
            raise ConfigError('rough_beam_shift_m must be a finite number in [-1, 1] m, got '
                              f'{self.rough_beam_shift_m}')
        positive = ('voxel_size_m', 'max_correspondence_distance_m', 'robust_kernel_scale_m',
                    'gicp_epsilon', 'map_voxel_size_m', 'map_max_range_m',
                    'keyframe_distance_m', 'keyframe_rotation_rad', 'max_translation_jump_m',
                    'max_rotation_jump_rad', 'scan_period_s', 'convergence_relative',
                    'min_std_m', 'min_std_rad', 'fallback_std_m', 'fallback_std_rad',
                    'max_speed_mps', 'max_yaw_rate_rps', 'max_gap_s', 'smooth_nu',
                    'rough_surface_variation', 'convergence_m', 'rough_depth_ratio',
                    'recovery_yaw_rate_step_rps')
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f'{name} must be a finite number > 0, got {value}')
        minimum = {'max_iterations': 1, 'map_max_points': 100, 'map_keyframes': 1,
                   'map_anchor_max_points': 1,
                   'normal_neighbours': 5, 'min_points': 3, 'max_consecutive_fallbacks': 1,
                   'deskew_velocity_window': 1, 'recovery_yaw_guesses': 0,
                   'anderson_memory': 0}
        for name, lowest in minimum.items():
            if getattr(self, name) < lowest:
                raise ConfigError(f'{name} must be >= {lowest}, got {getattr(self, name)}')
        for name in ('min_fitness', 'min_relative_fitness', 'map_anchor_smoothness',
                     'recovery_turn_relative_fitness', 'map_anchor_rough_any_side_share',
                     'turn_check_fitness_margin'):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f'{name} must be in [0, 1], got {getattr(self, name)}')
        if not 0.0 <= self.map_anchor_rough_view_deg <= 180.0:
            raise ConfigError(f'map_anchor_rough_view_deg must be in [0, 180], got '
                              f'{self.map_anchor_rough_view_deg}')
        if not (math.isfinite(self.recovery_correspondence_factor)
                and self.recovery_correspondence_factor >= 1.0):
            raise ConfigError(f'recovery_correspondence_factor must be >= 1, got '
                              f'{self.recovery_correspondence_factor}')
        if self.max_gap_s < self.scan_period_s:
            raise ConfigError(f'max_gap_s ({self.max_gap_s}) must be >= scan_period_s '
                              f'({self.scan_period_s})')
        if self.fallback_std_m < self.min_std_m or self.fallback_std_rad < self.min_std_rad:
            raise ConfigError('fallback_std_m/_rad must be >= min_std_m/_rad '
                              '(a fallback is never more certain than a match)')

    @property
    def _background_map_possible(self) -> bool:
        return (self.mode == 'default' and self.solver != 'open3d'
                and self.map_normals == 'rebuild' and self.residual_model != 'planarity'
                and self.resolved_estimation == 'point_to_plane')

    @property
    def resolved_map_update(self) -> str:
        """'inline' or 'background', what 'auto' stands for with these settings."""
        if self.map_update != 'auto':
            return self.map_update
        return 'background' if self._background_map_possible else 'inline'

    @property
    def resolved_estimation(self) -> str:
        """The estimator 'auto' stands for in this mode."""
        if self.estimation != 'auto':
            return self.estimation
        return 'point_to_point' if self.mode == 'paper' else 'point_to_plane'


@dataclass
class RegistrationResult:
    """Outcome of one scan: pose, increment, match quality, health, timings."""

    T_world_sensor: np.ndarray  # (4, 4) sensor pose at the stamp
    T_prev_curr: np.ndarray  # (4, 4) motion since the previous scan
    fitness: float  # inlier pairs / source points (open3d), 0 when not matched
    inlier_rmse_m: float
    n_points_used: int  # downsampled source points
    status: str  # one of STATUSES
    covariance: np.ndarray  # (6, 6), inflated on fallback
    timings_s: dict[str, float] = field(default_factory=dict)
    deskewed_points: np.ndarray | None = None  # (N, 3) sensor frame at the stamp
    # (rot_x, rot_y, rot_z, v_x, v_y, v_z) rad/s, m/s in the sensor frame at the stamp: the
    # motion model's velocity after this scan (zeros when unknown, e.g. after a loss).
    twist: np.ndarray = field(default_factory=lambda: np.zeros(6))
    # (6, 6) Gauss-Newton information of the match (x, y, z, rot_x, rot_y, rot_z; the same
    # axes as `covariance`), None on a fallback: its small eigenvalues are weak directions.
    information: np.ndarray | None = None
    # The speed (m/s) and rotation rate (rad/s) a match refused as implausible implied, since
    # the last trusted pose; None unless status is fallback_implausible from the match.
    refused_speed_mps: float | None = None
    refused_rate_rps: float | None = None

    @property
    def fell_back(self) -> bool:
        """True when ICP was not trusted and the prediction was used."""
        return self.status.startswith('fallback')


def local_map_from_config(cfg: RegistrationConfig) -> LocalMap:
    """The local map of default mode, from the `map_*` / keyframe fields."""
    return LocalMap(
        voxel_size_m=cfg.map_voxel_size_m, max_range_m=cfg.map_max_range_m,
        max_points=cfg.map_max_points, max_keyframes=cfg.map_keyframes,
        keyframe_distance_m=cfg.keyframe_distance_m,
        keyframe_rotation_rad=cfg.keyframe_rotation_rad,
        normal_neighbours=cfg.normal_neighbours, eviction=cfg.map_keyframe_eviction,
        voxel_keeps=cfg.map_voxel_keeps,
        anchor_smoothness=cfg.map_anchor_smoothness if cfg.map_anchors else None,
        anchor_max_points=cfg.map_anchor_max_points,
        rough_anchor_view_rad=(math.radians(cfg.map_anchor_rough_view_deg)
                               if cfg.map_anchor_rough_view_deg > 0.0 else None),
        rough_anchor_any_side_share=cfg.map_anchor_rough_any_side_share)


class TrustPolicy:
    """Whether a match's fitness is trusted, and the run of fallbacks that ends tracking.

    A fitness is judged against the recent trusted matches as well as `min_fitness`:
    scan-to-map fitness is steady, and a wrong fit near the prediction can still pass the
    absolute bound.
    """

    def __init__(self, config: RegistrationConfig):
        self.config = config
        self.reset()

    def reset(self) -> None:
        """No match yet, no fallback."""
        self.recent_fitness: deque[float] = deque(maxlen=RECENT_FITNESS_WINDOW)  # trusted
        self.n_fallbacks = 0
        self.consecutive_fallbacks = 0

    def relatively_unfit(self, fitness: float) -> bool:
        """Below `min_relative_fitness` x the median fitness of the recent trusted matches."""
        return self.below_recent(fitness, self.config.min_relative_fitness)

    def below_recent(self, fitness: float, ratio: float) -> bool:
        """Below `ratio` x the median fitness of the recent trusted matches (False while
        there are too few to tell)."""
        return (len(self.recent_fitness) >= RECENT_FITNESS_MIN
                and fitness < ratio * float(np.median(self.recent_fitness)))

    def trusted(self, fitness: float | None) -> None:
        """A trusted pose ends the fallback run; a match's `fitness` joins the recent ones."""
        if fitness is not None:
            self.recent_fitness.append(fitness)
        self.consecutive_fallbacks = 0

    def fell_back(self) -> bool:
        """Count a fallback; True once the run is long enough to drop the velocity."""
        self.n_fallbacks += 1
        self.consecutive_fallbacks += 1
        return self.consecutive_fallbacks >= self.config.max_consecutive_fallbacks


class Match(NamedTuple):
    """What matching (or re-acquiring) one scan found; the pose is the prediction's unless
    trusted."""

    status: str
    T_world_sensor: np.ndarray
    fitness: float
    rmse: float
    information: np.ndarray | None  # in the target's axes; None unless trusted
    velocity: np.ndarray | None = None  # re-acquisition: the velocity it leaves behind


@dataclass
class _Sweep:
    """One scan on its way through `register`: the whole scan and what the steps make of it."""

    points_xyz: np.ndarray  # (N, 3) the whole scan, sensor frame
    time_offset_s: np.ndarray | None  # (N,) per-point times from the bag, if any
    nu: np.ndarray | None  # (N,) per-point graph frequency, if any
    keep: np.ndarray | None = None  # indices of the downsampled points
    source_xyz: np.ndarray | None = None  # the points ICP matches (downsampled, deskewed)
    point_smoothness: np.ndarray | None = None  # theirs, as the map remembers it (or None)
    offsets_s: np.ndarray | None = None  # (N,) point times; set only when deskewed
    dt_s: float = 0.0  # since the previous scan
    scan_motion: np.ndarray | None = None  # its own motion, when re-deskewed with it
    map_motion: np.ndarray | None = None  # the motion the re-deskewed points assume

    @property
    def n_used(self) -> int:
        """How many points ICP matches."""
        return int(self.source_xyz.shape[0])

    def deskewed(self, motion: np.ndarray) -> np.ndarray:
        """The downsampled points deskewed with `motion` over the scan's `dt_s` (needs
        `offsets_s`)."""
        return deskew_points(self.points_xyz[self.keep], self.offsets_s[self.keep], motion,
                             self.dt_s)


def _delegated(part: str, name: str, settable: bool = False) -> property:
    """`name` of one of ScanRegistration's parts, readable where callers always found it."""
    def get(self):
        return getattr(getattr(self, part), name)

    def put(self, value) -> None:
        setattr(getattr(self, part), name, value)
    return property(get, put if settable else None, doc=f'`self.{part}.{name}`')


class ScanRegistration:
    """Registers consecutive scans and keeps the odometry state (pose, velocity, local map)."""

    # The parts' state and checks, where callers and tests have always found them.
    T_world_sensor = _delegated('motion', 'T_world_sensor')
    T_world_trusted = _delegated('motion', 'T_world_trusted')
    trusted_stamp_ns = _delegated('motion', 'trusted_stamp_ns')
    last_stamp_ns = _delegated('motion', 'last_stamp_ns')
    velocity = _delegated('motion', 'velocity', settable=True)
    recovering = _delegated('motion', 'recovering')
    last_implied_rates = _delegated('motion', 'last_implied_rates')
    capped = _delegated('motion', 'capped')
    predicted_delta = _delegated('motion', 'predicted_delta')
    is_plausible = _delegated('motion', 'is_plausible')
    n_fallbacks = _delegated('trust', 'n_fallbacks')
    consecutive_fallbacks = _delegated('trust', 'consecutive_fallbacks')
    min_var = _delegated('uncertainty', 'min_var')
    fallback_var = _delegated('uncertainty', 'fallback_var')

    def __init__(self, config: RegistrationConfig = RegistrationConfig()):
        config.validate()
        self.config = config
        self.mode = config.mode
        self.local_map = local_map_from_config(config)
        self.icp = IcpBackend(config, self.local_map)  # also sets what the map computes
        self.estimation = self.icp.estimation
        # Paper mode has no map to re-acquire against: it never drops the velocity.
        self.motion = MotionModel(config, track_loss=config.mode == 'default')
        self.trust = TrustPolicy(config)
        self.uncertainty = PoseUncertainty.from_config(config)
        self.deskew = config.deskew and config.mode == 'default'
        self._background_map = (config.resolved_map_update == 'background'
                                and self.icp.solves_on_map_target)
        self.reset()

    @classmethod
    def from_config(cls, cfg: RegistrationConfig) -> 'ScanRegistration':
        """Same as the constructor (kept for the callers that name it)."""
        return cls(cfg)

    def reset(self) -> None:
        """Forget everything: the next scan is the first again."""
        self.motion.reset()
        self.trust.reset()
        self.n_registered = 0
        # turn_check: the matches checked from turned guesses, and those a turn replaced.
        self.n_turn_checks = 0
        self.n_turns_found = 0
        self._prev_scan: o3d.geometry.PointCloud | None = None  # paper mode's target
        self.local_map.clear()
        self._map_provisional = False
        # A keyframe a deferred `register` left for `update_map`: (world points, pose,
        # smoothness or None).
        self._pending_keyframe: tuple | None = None
        self._adopt_at_scan = 0
        # The last registered scan's (time offsets, motion, dt) when it was deskewed.
        self._last_deskew: tuple | None = None

    @property
    def has_reference(self) -> bool:
        """A map (default) or a previous scan (paper) to register against."""
        if self.mode == 'paper':
            return self._prev_scan is not None
        return len(self.local_map) > 0 or self._pending_keyframe is not None

    @property
    def map_update_pending(self) -> bool:
        """A deferred `register` left a keyframe for `update_map`."""
        return self._pending_keyframe is not None

    def update_map(self) -> float:
        """Add the keyframe the last `register` left pending, and build the solvers' target
        (its KD-tree) for the next match; the seconds it took (0 when nothing was pending).

        The next `register` does it first when the caller did not, so deferring changes no
        pose: it only lets a caller publish the pose before the map work (a keyframe's
        rebuild and normals, most of the p95 latency)."""
        pending, self._pending_keyframe = self._pending_keyframe, None
        if pending is None:
            return 0.0
        t0 = time.perf_counter()
        # The first keyframe is built at once: the next scan has no other map.
        background = self._background_map and len(self.local_map) > 0
        self.local_map.add_keyframe(*pending, background=background)
        if background:
            self._adopt_at_scan = self.n_registered + 1  # served from the scan after next
        elif self.icp.solves_on_map_target and len(self.local_map):
            self.local_map.target()
        return time.perf_counter() - t0

    def _serve_map(self, timings: dict[str, float]) -> None:
        """map_update 'background': the rebuild a keyframe started is served from the second
        scan after it (the next one is matched against the map before it), whenever the
        thread finished; the wait is this scan's."""
        if self.local_map.rebuild_in_flight and self.n_registered >= self._adopt_at_scan:
            timings['map_wait'] = self.local_map.adopt()

    def advance_with_prediction(self, stamp_ns: int,
                                status: str = 'fallback_degenerate') -> RegistrationResult:
        """Take the motion prediction as the pose at `stamp_ns` without matching anything:
        for scans the caller knows ICP cannot observe (a flat cloud). Counted as a fallback."""
        if status not in STATUSES or not status.startswith('fallback'):
            raise RegistrationError(f'advance_with_prediction needs a fallback status from '
                                    f'{STATUSES}, got {status!r}')
        t_start = time.perf_counter()
        self.update_map()
        timings: dict[str, float] = {}
        self._serve_map(timings)
        _, T_pred = self.motion.predict(stamp_ns)
        return self._finish(stamp_ns, status, T_pred, t_start, timings)

    def register(self, points_xyz: np.ndarray, stamp_ns: int,
                 time_offset_s: np.ndarray | None = None,
                 nu: np.ndarray | None = None,
                 defer_map_update: bool = False) -> RegistrationResult:
        """Register one scan (sensor frame, any number of points) and update the state.

        `nu` (N,): every point's graph frequency (NaN: none), read by residual_model
        'frequency'; without it every pair is weighted alike. `defer_map_update`: a keyframe
        this scan makes waits for `update_map` (or the next `register`), so the pose is
        returned before the map's rebuild."""
        sweep = _Sweep(*self._check_input(points_xyz, time_offset_s, nu))
        timings: dict[str, float] = {}
        self.update_map()  # a keyframe a deferred call left, when its caller did not
        t_start = time.perf_counter()
        self._serve_map(timings)
        # 1. Predict: the velocity over the real stamp difference, capped (a gap drops it).
        sweep.dt_s, T_pred = self.motion.predict(stamp_ns)
        # 2. Downsample: one point per voxel, which keeps its time and frequency.
        self._downsample(sweep, timings)
        # 3. Deskew those points with the recent velocity.
        self._deskew(sweep, timings)
        # 4. Match against the reference or re-acquire (the first scan and too few points
        # are not matched).
        status, T_new, match, refused = self._match_or_reacquire(sweep, T_pred, stamp_ns,
                                                                 timings)
        # 5. A trusted scan is deskewed again with its own motion: the map gets that cloud.
        self._redeskew(sweep, stamp_ns, status, T_new)
        # 6-8. Trust the pose or count a fallback, update the map, the result.
        result = self._finish(stamp_ns, status, T_new, t_start, timings, sweep, match)
        if not defer_map_update:
            timings['map_update'] = self.update_map()
        return self._with_extras(result, sweep, refused)

    # ------------------------------------------------------------ the steps

    def _downsample(self, sweep: _Sweep, timings: dict[str, float]) -> None:
        """The source points (one per voxel: the first in scan order, or the smoothest) and
        their smoothness for the solver and the map."""
        t0 = time.perf_counter()
        cfg, nu = self.config, sweep.nu
        priority = nu if cfg.voxel_priority == 'smoothest' else None
        sweep.keep = voxel_downsample_indices(sweep.points_xyz, cfg.voxel_size_m, priority)
        sweep.source_xyz = sweep.points_xyz[sweep.keep]
        source_smoothness = (smoothness_from_nu(nu[sweep.keep], cfg.smooth_nu)
                             if nu is not None and cfg.residual_model == 'frequency' else None)
        # The map remembers the smoothness of its points (unknown kept NaN) when it is read.
        remembered = nu is not None and (cfg.map_anchors or (
            self.icp.solver is not None and cfg.frequency_affinity_m > 0.0))
        sweep.point_smoothness = (smoothness_from_nu(nu[sweep.keep], cfg.smooth_nu,
                                                     unknown=np.nan) if remembered else None)
        self.icp.use_smoothness(source_smoothness, sweep.point_smoothness)
        if cfg.rough_beam_shift_m != 0.0 and nu is not None:
            self._shift_rough_points(sweep)
        timings['downsample'] = time.perf_counter() - t0

    def _shift_rough_points(self, sweep: _Sweep) -> None:
        """`rough_beam_shift_m`: the kept points moved along their beams by their roughness
        (in the scan itself, so that the deskew after the match carries it into the map)."""
        cfg = self.config
        roughness = 1.0 - smoothness_from_nu(sweep.nu[sweep.keep], cfg.smooth_nu,
                                             unknown=1.0)
        points = sweep.points_xyz.copy()
        points[sweep.keep] = along_beams(points[sweep.keep], cfg.rough_beam_shift_m * roughness)
        sweep.points_xyz = points
        sweep.source_xyz = points[sweep.keep]

    def _deskew(self, sweep: _Sweep, timings: dict[str, float]) -> None:
        """Deskew the source points with the mean twist of the recent trusted scans."""
        t0 = time.perf_counter()
        if self.deskew and sweep.source_xyz.shape[0]:
            sweep.offsets_s = self._time_offsets(sweep.points_xyz, sweep.time_offset_s)
            sweep.source_xyz = sweep.deskewed(self.motion.deskew_motion(sweep.dt_s))
        timings['deskew'] = time.perf_counter() - t0

    def _match_or_reacquire(self, sweep: _Sweep, T_pred: np.ndarray, stamp_ns: int,
                            timings: dict[str, float]):
        """(status, pose, match or None, refused rates): the first scan, too few points,
        re-acquisition after a loss, or ICP against the reference (retried the way
        re-acquisition does when it fails and `retry_failed_match`)."""
        n_used = sweep.n_used
        refused = (None, None)  # the rates a match refused as implausible implied
        if n_used < self.config.min_points:
            if not self.has_reference:
                log.warning('scan %d has %d points after downsampling (< min_points %d) and '
                            'there is no reference yet', stamp_ns, n_used,
                            self.config.min_points)
            return 'fallback_too_few_points', T_pred, None, refused
        if not self.has_reference:
            return 'first', (T_pred if self.n_registered else np.eye(4)), None, refused
        t0 = time.perf_counter()
        if self.motion.recovering and self.mode == 'default':
            match = self._reacquire(sweep.source_xyz, T_pred, stamp_ns)
        else:
            self.motion.last_implied_rates = (None, None)  # set by is_plausible in the match
            match = Match(*self._match(sweep.source_xyz, T_pred, stamp_ns))
            if match.status == 'fallback_implausible':
                refused = self.motion.last_implied_rates
            if (match.status in RETRIED_STATUSES and self.mode == 'default'
                    and self.config.retry_failed_match):
                retried = self._reacquire(sweep.source_xyz, T_pred, stamp_ns, retry=True)
                match = retried if retried.status == 'recovered' else match
            if self._turn_check_due(match):
                match = self._turn_check(sweep, T_pred, stamp_ns, match)
        timings['icp'] = time.perf_counter() - t0
        return match.status, match.T_world_sensor, match, refused

    def _redeskew(self, sweep: _Sweep, stamp_ns: int, status: str, T_new: np.ndarray) -> None:
        """Deskew a trusted scan again with its own motion (only when it was deskewed)."""
        if sweep.offsets_s is None or status not in ('ok', 'recovered') or not sweep.dt_s > 0.0:
            return
        # This scan's motion as deskew assumes it, worked out before the trusted pose moves.
        sweep.scan_motion = self.motion.scan_motion(stamp_ns, T_new, sweep.dt_s)
        sweep.map_motion = self.motion.deskew_motion(sweep.dt_s, sweep.scan_motion)
        sweep.source_xyz = sweep.deskewed(sweep.map_motion)

    def _finish(self, stamp_ns: int, status: str, T_new: np.ndarray, t_start: float,
                timings: dict[str, float], sweep: _Sweep | None = None,
                match: Match | None = None) -> RegistrationResult:
        """Trust the pose (motion model, fitness) or count a fallback, update the reference,
        move the pose; the result."""
        t0 = time.perf_counter()
        fitness, rmse, information = (match[2], match[3], match[4]) if match else (0.0, 0.0, None)
        # Axes the ICP information is expressed in: world (map) or the previous scan (paper).
        R_world_target = self.T_world_trusted[:3, :3] if self.mode == 'paper' else np.eye(3)
        T_prev_curr = invert_transform(self.T_world_sensor) @ T_new
        n_used = 0 if sweep is None else sweep.n_used
        if status in TRUSTED_STATUSES:
            # The velocity spans the motion since the last trusted pose: after fallbacks the
            # previous pose was extrapolated, and its error is not this scan's motion.
            self.motion.trust(stamp_ns, T_new, status, None if match is None else match[5])
            self.trust.trusted(None if match is None else fitness)
            self._update_reference(sweep, T_new, status)
        else:
            log.debug('scan %d: %s (fitness %.3f, %d points)', stamp_ns, status, fitness, n_used)
            if self.trust.fell_back():
                self.motion.lose_track(f'{self.trust.consecutive_fallbacks} fallbacks in a row')
        self.motion.advance(stamp_ns, T_new)
        self.n_registered += 1
        timings['update'] = time.perf_counter() - t0
        timings['total'] = time.perf_counter() - t_start
        return RegistrationResult(
            T_world_sensor=T_new.copy(), T_prev_curr=T_prev_curr, fitness=fitness,
            inlier_rmse_m=rmse, n_points_used=n_used, status=status,
            covariance=self.uncertainty.covariance(status, information, R_world_target),
            timings_s=timings, twist=self.velocity.copy(),
            information=world_information(status, information, R_world_target))

    def _with_extras(self, result: RegistrationResult, sweep: _Sweep,
                     refused: tuple) -> RegistrationResult:
        """The rates a refused match implied; the deskewed scan when asked for (with the
        twists as this scan left them)."""
        if result.status == 'fallback_implausible':
            result.refused_speed_mps, result.refused_rate_rps = refused
        # What deskewing this scan takes, for `deskewed_like_last` (the map's snapshot).
        self._last_deskew = None if sweep.offsets_s is None else (
            sweep.offsets_s, self.motion.deskew_motion(sweep.dt_s, sweep.scan_motion),
            sweep.dt_s)
        if self.config.output_deskewed_points:
            result.deskewed_points = (sweep.points_xyz.copy() if self._last_deskew is None
                                      else deskew_points(sweep.points_xyz, *self._last_deskew))
        return result

    def deskewed_like_last(self, points_xyz: np.ndarray) -> np.ndarray:
        """The last registered scan's points (as it was given, after the crop) deskewed as
        the map got them; as they are when that scan was not deskewed or they do not match."""
        last = self._last_deskew
        if last is None or last[0].shape[0] != points_xyz.shape[0]:
            return points_xyz
        offsets_s, motion, dt_s = last
        return deskew_points(points_xyz, offsets_s, motion, dt_s)

    # ------------------------------------------------------------ matching

    def _match(self, source_xyz: np.ndarray, T_pred: np.ndarray, stamp_ns: int) -> Match:
        """ICP from the prediction (default) or from identity (paper); then sanity checks:
        finite, fitness, physically possible and close to the prediction, both measured from
        the last trusted pose (after fallbacks the previous pose is only a prediction)."""
        cfg = self.config
        source = to_cloud(source_xyz)
        if self.mode == 'paper':
            target = self._prev_scan
            init = np.eye(4)  # scan-to-scan, relative to the last trusted scan (the target)
        else:
            target = self.local_map.cloud
            init = T_pred
        result = self.icp.register(source, target, init, cfg.max_correspondence_distance_m,
                                   prior=self.mode == 'default')
        T_est = np.asarray(result.transformation)
        if self.mode == 'paper':
            T_est = self.T_world_trusted @ T_est
        refusal = self._refusal(T_est, float(result.fitness), T_pred, stamp_ns)
        if refusal is not None:
            return Match(refusal, T_pred, float(result.fitness), float(result.inlier_rmse),
                         None)
        return self._fitted('ok', result, T_est, source_xyz, target)

    def _refusal(self, T_est: np.ndarray, fitness: float, T_pred: np.ndarray,
                 stamp_ns: int) -> str | None:
        """Why a match's pose `T_est` is not trusted (its fallback status), or None: every
        check a match passes (the turn check's fits pass the same)."""
        if not np.all(np.isfinite(T_est)):
            return 'fallback_diverged'
        if fitness < self.config.min_fitness or (self.mode == 'default'
                                                 and self.trust.relatively_unfit(fitness)):
            return 'fallback_low_fitness'
        motion, elapsed_s = self.motion.since_trusted(stamp_ns, T_est)
        if not self.motion.is_plausible(motion, elapsed_s):
            log.debug('ICP implies motion beyond the bounds over %.3f s', elapsed_s)
            return 'fallback_implausible'
        if self.motion.jumped(T_pred, T_est, stamp_ns):
            return 'fallback_diverged'
        return None

    def _fitted(self, status: str, result, T_est: np.ndarray, source_xyz: np.ndarray,
                target, velocity: np.ndarray | None = None) -> Match:
        """A trusted Match of an ICP `result` (pose `T_est`): its fitness, RMSE and
        information."""
        rmse = float(result.inlier_rmse)
        return Match(status, T_est, float(result.fitness), rmse,
                     icp_information(source_xyz, self.icp.matched(target), result, rmse),
                     velocity)

    def _implied_or(self, velocity: np.ndarray | None, stamp_ns: int,
                    T_est: np.ndarray) -> np.ndarray | None:
        """The velocity the motion since the last trusted pose implies (`velocity` when
        there is none to measure)."""
        implied = self.motion.implied_velocity(stamp_ns, T_est)
        return velocity if implied is None else implied

    def _turn_check_due(self, match: Match) -> bool:
        """A trusted match that fits poorly for the recent matches (`turn_check`)."""
        return (self.config.turn_check and self.mode == 'default'
                and match.status in ('ok', 'recovered')
                and self.trust.below_recent(match.fitness,
                                            self.config.recovery_turn_relative_fitness))

    def _turn_check(self, sweep: _Sweep, T_pred: np.ndarray, stamp_ns: int,
                    match: Match) -> Match:
        """`match`, or the best fit from the turned guesses when it fits better by
        `turn_check_fitness_margin` and passes every check a match does."""
        cfg = self.config
        target = self.local_map.cloud
        self.n_turn_checks += 1
        best = None
        for guess_velocity, init in self.motion.turn_guesses(stamp_ns, retry=True):
            source_xyz = self._deskewed_as(sweep, guess_velocity)
            result = self.icp.register(to_cloud(source_xyz), target, init,
                                       cfg.max_correspondence_distance_m)
            T_est, fitness = np.asarray(result.transformation), float(result.fitness)
            if (fitness < match.fitness + cfg.turn_check_fitness_margin
                    or (best is not None and fitness <= best[0].fitness)
                    or self._refusal(T_est, fitness, T_pred, stamp_ns) is not None):
                continue
            best = (result, T_est, source_xyz)
        if best is None:
            return match
        self.n_turns_found += 1
        result, T_est, source_xyz = best
        velocity = match.velocity
        if match.status == 'recovered':  # re-acquisition keeps the velocity it implies
            velocity = self._implied_or(velocity, stamp_ns, T_est)
        return self._fitted(match.status, result, T_est, source_xyz, target, velocity)

    def _deskewed_as(self, sweep: _Sweep, velocity: np.ndarray) -> np.ndarray:
        """The source points deskewed as they would be were `velocity` the scan's motion
        (`turn_guess_deskew`); the sweep's own (deskewed with the prediction's) otherwise."""
        if not self.config.turn_guess_deskew or sweep.offsets_s is None or not sweep.dt_s > 0.0:
            return sweep.source_xyz
        return sweep.deskewed(self.motion.deskew_motion(sweep.dt_s,
                                                        delta_of_twist(velocity, sweep.dt_s)))

    def _reacquire(self, source_xyz: np.ndarray, T_pred: np.ndarray, stamp_ns: int,
                   retry: bool = False) -> Match:
        """Re-acquire against the map from a few initial guesses (the motion model's, from
        the last trusted pose). From each: a coarse ICP with a widened correspondence
        distance, then the normal one with more iterations. The plausible fit with the best
        fitness wins; no jump check (the guesses are rough). Only when no plain guess gives
        one, and their best fit is below `recovery_turn_relative_fitness` x the recent ones, are
        turned guesses tried; a turned fit must fit better than every plain guess's, refused
        ones included.

        `retry`: a second chance for a scan whose match from the prediction failed, with the
        current velocity as the one before the loss; the fit must pass every check a match
        does (relative fitness, the jump from the prediction too), and the velocity becomes
        the motion it implies."""
        cfg = self.config
        source, target = to_cloud(source_xyz), self.local_map.cloud
        wide_m = cfg.max_correspondence_distance_m * cfg.recovery_correspondence_factor
        best, status = None, 'fallback_low_fitness'
        best_plain_fitness = 0.0  # of any fit from a plain guess, refused ones included
        for turned in (False, True):
            if turned and (best is not None or not self.trust.below_recent(
                    best_plain_fitness, cfg.recovery_turn_relative_fitness)):
                # The last resort, and only for a poor fit: a plain fit that explains the scan
                # as well as the recent matches was refused for the bounds or the jump, not a
                # missed turn (a platform beyond the speed bound: every scan lands here).
                break
            guesses = (self.motion.turn_guesses(stamp_ns, retry) if turned
                       else self.motion.reacquisition_guesses(stamp_ns, retry))
            for velocity, init in guesses:
                coarse = self.icp.register(source, target, init, wide_m)
                result = self.icp.register(source, target, np.asarray(coarse.transformation),
                                           cfg.max_correspondence_distance_m, recovery=True)
                T_est = np.asarray(result.transformation)
                if not np.all(np.isfinite(T_est)) or result.fitness < cfg.min_fitness:
                    continue
                if not turned:
                    best_plain_fitness = max(best_plain_fitness, float(result.fitness))
                elif result.fitness <= best_plain_fitness:
                    continue  # a turned guess that fits no better is a local minimum
                if retry and (self.trust.relatively_unfit(float(result.fitness))
                              or self.motion.jumped(T_pred, T_est, stamp_ns)):
                    continue
                if not self.motion.is_plausible(*self.motion.since_trusted(stamp_ns, T_est)):
                    status = 'fallback_implausible'
                    continue
                if best is None or result.fitness > best[0].fitness:
                    best = (result, T_est, velocity)
        if best is None:
            return Match(status, T_pred, 0.0, 0.0, None)
        result, T_est, velocity = best
        if retry:
            velocity = self._implied_or(velocity, stamp_ns, T_est)
        return self._fitted('recovered', result, T_est, source_xyz, target, velocity)

    # ------------------------------------------------------------ the reference

    def _update_reference(self, sweep: _Sweep | None, T_world_sensor: np.ndarray,
                          status: str) -> None:
        """Paper: the scan becomes the target. Default: a keyframe when due, its points from
        `_keyframe_points` (only built then, with their smoothness)."""
        if sweep is None:
            return
        if self.mode == 'paper':
            self._prev_scan = to_cloud(sweep.source_xyz)
            return
        if status == 'first':
            # Its motion is unknown, so it could not be deskewed: replaced by the first match.
            self._map_provisional = self.deskew
        elif self._map_provisional:
            self.local_map.clear()
            self._map_provisional = False
        if self.local_map.needs_keyframe(T_world_sensor) or len(self.local_map) == 0:
            points, smoothness = self._keyframe_points(sweep)
            self._pending_keyframe = (transform_points(T_world_sensor, points),
                                      T_world_sensor.copy(), smoothness)

    def _keyframe_points(self, sweep: _Sweep) -> tuple[np.ndarray, np.ndarray | None]:
        """The points a keyframe adds, and their smoothness when the map keeps it: the
        registration's, or (map_points_from 'scan') the whole scan at the map voxel,
        deskewed as the registration's were."""
        cfg = self.config
        if cfg.map_points_from == 'registration' or sweep.source_xyz.shape[0] == 0:
            return sweep.source_xyz, sweep.point_smoothness
        dense = voxel_downsample_indices(sweep.points_xyz, cfg.map_voxel_size_m)
        smooth = (None if sweep.point_smoothness is None else smoothness_from_nu(
            sweep.nu[dense], cfg.smooth_nu, unknown=np.nan))
        if sweep.map_motion is None:
            return sweep.points_xyz[dense], smooth
        return deskew_points(sweep.points_xyz[dense], sweep.offsets_s[dense], sweep.map_motion,
                             sweep.dt_s), smooth

    # ------------------------------------------------------------ input

    def _check_input(self, points_xyz, time_offset_s, nu=None):
        points = np.asarray(points_xyz, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3:
            raise RegistrationError(f'points_xyz must have shape (N, 3), got {points.shape}')
        if nu is not None:
            nu = np.asarray(nu, dtype=float).reshape(-1)
            if nu.shape[0] != points.shape[0]:
                raise RegistrationError(f'nu has {nu.shape[0]} values for {points.shape[0]} '
                                        'points')
        if time_offset_s is not None:
            time_offset_s = np.asarray(time_offset_s, dtype=float).reshape(-1)
            if time_offset_s.shape[0] != points.shape[0]:
                raise RegistrationError(
                    f'time_offset_s has {time_offset_s.shape[0]} values for '
                    f'{points.shape[0]} points')
        finite = finite_rows(points)
        if time_offset_s is not None:
            finite &= np.isfinite(time_offset_s)
        if not finite.all():
            points = points[finite]
            time_offset_s = None if time_offset_s is None else time_offset_s[finite]
            nu = None if nu is None else nu[finite]
        return points, time_offset_s, nu

    def _time_offsets(self, points_xyz: np.ndarray, time_offset_s: np.ndarray | None):
        if time_offset_s is not None:
            return time_offset_s
        return azimuth_time_offsets(points_xyz, self.config.scan_period_s,
                                    self.config.azimuth_stamp_at_sweep_end)

