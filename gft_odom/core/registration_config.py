"""Every parameter of the scan registration, and the choices each names.

One source of truth: the node declares its ROS parameters from these fields and the params
files are generated from them (`gft_odom/ros/parameters.py`); docs/registration.md has the
measurements behind the defaults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gft_odom.core.constants import SCAN_PERIOD_S
from gft_odom.core.local_map import KEYFRAME_EVICTIONS, VOXEL_KEEPS
from gft_odom.core.residuals import RESIDUAL_MODELS, ROUGH_RESIDUALS
from gft_odom.errors import ConfigError

MODES = ('default', 'paper')
# What a keyframe adds to the local map: the registration's downsampled points, or the whole
# scan downsampled at the map's voxel (denser, costs a downsample per keyframe).
MAP_POINTS_FROM = ('registration', 'scan')
ESTIMATIONS = ('auto', 'point_to_plane', 'point_to_point', 'gicp')
ROBUST_KERNELS = ('none', 'tukey', 'huber', 'cauchy')
SOLVERS = ('open3d', 'gauss_newton', 'map_tree')
MAP_NORMALS = ('rebuild', 'on_demand', 'kept', 'in_time')
MAP_UPDATES = ('auto', 'inline', 'background')
VOXEL_PRIORITIES = ('first', 'smoothest')

# Every field that names one of a few choices, and those choices.
CHOICES = {'mode': MODES, 'estimation': ESTIMATIONS, 'map_keyframe_eviction': KEYFRAME_EVICTIONS,
           'map_voxel_keeps': VOXEL_KEEPS, 'map_points_from': MAP_POINTS_FROM,
           'voxel_priority': VOXEL_PRIORITIES, 'solver': SOLVERS, 'map_normals': MAP_NORMALS,
           'map_update': MAP_UPDATES, 'residual_model': RESIDUAL_MODELS,
           'rough_residual': ROUGH_RESIDUALS, 'robust_kernel': ROBUST_KERNELS}


@dataclass(frozen=True)
class RegistrationConfig:
    """Parameters of ScanRegistration; defaults chosen by benchmarks/bench_registration.py."""

    # 'default' (our design) or 'paper' (scan-to-scan point-to-point ICP from identity).
    mode: str = 'default'
    # 'auto' = point_to_point in paper mode (as the paper), point_to_plane in default mode.
    estimation: str = 'auto'
    # Source voxel: ~3k of the ~26k points of a VLP-16 orchard scan, plenty for 6 DoF.
    # 0.3 m: 11.7 % better on the training drives, 4.1 % worse on the record; 0.39 / 0.41 m
    # move the training mean by -2.5 / +8.0 % (session 43: a screen's noise floor).
    voxel_size_m: float = 0.4
    # The source voxel grid's origin shifted by this along x, y and z of the sensor frame:
    # the same voxel size, other voxel boundaries. A benchmark's knob for the noise floor of
    # a screen (session 44), not a tuning one.
    voxel_grid_offset_m: float = 0.0
    # Largest point pair ICP accepts: a few voxels, above the worst prediction error at 2 m/s.
    # It is also the trust policy's fitness (the share of points with a pair). 0.4 m (with
    # min_relative_fitness 0.5 and noise_gate_m 1.0) was 13 % better on the training drives
    # and kept all twenty edge drives (18 at 1 m), but the record was level (0.0614 -> 0.0609
    # m, six drives worse), the twist noisier, and the frequency lost to its shuffled control
    # (sessions 35 and 36, docs/registration.md): not the default.
    max_correspondence_distance_m: float = 1.0
    # The noise a match's covariance is scaled by (its inlier RMSE) is measured over the
    # scan's points within this distance of the map at its pose (0: ICP's own pairs, within
    # the correspondence gate). Within a narrow gate the distances are cut short and the
    # covariance claims more than the match knows: on the simulated U-turn of the tests at a
    # 0.4 m gate, 79 % of the forward-speed errors within 2 sigma, 95 % with this at 1 m
    # (97 % at a 1 m gate; session 36).
    noise_gate_m: float = 0.0
    max_iterations: int = 30
    # A match stopped by max_iterations while still turning (its rotation from the prediction
    # above this) carries on for turn_continue_iterations more (0: off). At a turn's onset
    # (0 -> 2 rad/s within a scan) the prediction misses most of the yaw, and in open ground
    # ICP turns the pose ~1 mrad an iteration: the cap stops it 0.04-0.09 rad short, and
    # the error stays (edge drive 226, scans 1136-1138, docs/registration.md, session 30).
    # Converging every capped match instead costs accuracy on the training drives (the
    # converged optimum on porous canopy is biased too: session 11); turning ones are ~0.1 %
    # of the matches of an orchard drive. At 0.02 it keeps edge drives 221 / 226 (1.36 / 1.90
    # -> 0.06 / 0.08 m) but loses 223, 227, 243 and 263, and the record's mean goes 0.0614 ->
    # 0.0622 m: at a turn's onset on the edge drives it is a lottery, so off. The carried-on
    # iterations have no motion prior (motion_prior_weight, solver 'gauss_newton').
    turn_continue_min_rad: float = 0.0
    turn_continue_iterations: int = 70
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
    # Solver 'map_tree': a rough scan point (smoothness 0: canopy; unknown counts as rough)
    # pairs only within this times the match's correspondence gate, blended linearly to the
    # whole gate at smoothness 1 (ground, trunks); above 1 a rough point's gate is the wider.
    # 0: one gate for every point (also without frequencies). A pair on a plane is right at
    # any distance along it, one in porous canopy is likely another leaf: but on the training
    # drives 0.4 (canopy within 0.4 m, the rest 1 m) was level with the default (0.0558 m
    # both) and the inverse (smooth points 0.4 m, canopy 1 m) 0.0574 m, where one 0.4 m gate
    # for all gave 0.0486 m (session 37, docs/registration.md): off.
    rough_gate_ratio: float = 0.0
    # The match from the prediction is refined within this gate from where it ended at
    # max_correspondence_distance_m (0: off). The trust policy, the turn check and the
    # covariance read the wide match (its fitness and RMSE), so min_relative_fitness stays
    # (the synthetic open-ground turn a 0.4 m gate loses at 0.7 is kept). Turned guesses and
    # re-acquisition are not refined. At 0.4: training 0.0558 -> 0.0492 m, the record level
    # (0.0614 -> 0.0611 m; GenZ-ICP ahead on 203), and there the frequency lost to its
    # shuffled control (0.0599 m), as at a 0.4 m gate (session 37, docs/registration.md): off.
    refine_correspondence_distance_m: float = 0.0
    # The Tukey scale follows how far the motion model's predictions have been off
    # (core/threshold.py, kiss-icp's adaptive threshold): this times the root mean square of
    # the prediction errors at map_max_range_m of the trusted matches from the prediction
    # (status ok; not re-acquisition's), errors under
    # adaptive_min_motion_m not counted; robust_kernel_scale_m until one is. 0: off, the
    # fixed scale. The correspondence gate stays max_correspondence_distance_m (the trust
    # policy's fitness is the share of points within it). Off: on the training drives it was
    # worse on the mean at every setting tried (+21 % at 0.25) and lost drives at 0.2 and
    # with a window (the errors measure how a route turns, not its surfaces' noise; session
    # 33, docs/registration.md).
    adaptive_kernel_ratio: float = 0.0
    adaptive_min_motion_m: float = 0.1
    # The mean is over the last this many counted matches (0: all of them, as kiss-icp).
    adaptive_window_scans: int = 0
    # Solver 'map_tree': a graduated kernel. Iteration i of a match weighs its residuals with
    # the scale max(the kernel's, kernel_anneal_from_m x kernel_anneal_factor^i), so that a
    # guess further off than the kernel (a turn's onset) is still pulled in, while the end of
    # the match is weighed as without it. 0: off. From 1.0 m to a 0.2 m scale it was 2.2 %
    # better on the training drives and 20.5 % worse on the ten record drives (0.0614 ->
    # 0.0740 m; session 33, docs/registration.md).
    kernel_anneal_from_m: float = 0.0
    kernel_anneal_factor: float = 0.7
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
    # The window's points served by the rough anchors' rule too (their side within this
    # angle, or the any-side share): a lane's canopy leaves the map while the next lane sees
    # the row from its other side (above 0 it needs map_anchors, whose smoothness threshold
    # tells smooth from rough). 0: the window serves every point from any side. The default
    # since session 40, with map_smooth_view_deg 60 (every point gated); the session 28
    # default served the window from any side. Mean ATE, ten record drives 0.0614 -> 0.0561
    # m; drives 231-234 never used for a choice 0.0469 -> 0.0432 m; edge drives kept 18 -> 19
    # of 20 (the fourteen never used: all kept, mean 0.126 -> 0.105 m). Session 40,
    # docs/registration.md.
    map_window_rough_view_deg: float = 60.0
    # Where those view rules apply (rough anchors, the window's gate), smooth points too are
    # served only from within this angle of their side: a trunk's or a wall's far face is
    # another surface as well. 180: from any side. Training drives with the window gate at
    # 60: 60 -> 0.0481, 120 -> 0.0471, 180 -> 0.0460 m; held out 180 lost three of six edge
    # drives and 60 one (session 39), so 60 is the default although training chose 180.
    map_smooth_view_deg: float = 60.0
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
    # Within a 0.4 m gate it wants 0.5: even the true pose fits only ~0.57 x the recent
    # matches while turning into unseen ground (session 36).
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
    # What the turn check compares its fits by: the share of the scan's points within this
    # distance of the map at each pose (0: ICP's fitness, the share with a pair within
    # max_correspondence_distance_m). In open ground at a turn's onset every heading fits
    # ~0.85-0.88 within 1 m (the ground pairs with any), while within 0.3 m the true turn
    # fits 0.68 against 0.57 for the missed one (edge drive 227, docs/registration.md,
    # session 25). Edge drives 222 / 227: 0.171 / 7.52 -> 0.107 / 2.60 m, the others unchanged.
    turn_check_gate_m: float = 0.3
    # The turn check first matches each turned guess for this many ICP iterations; only the
    # better half of them, and any that then fit at least as well as the match it checks (by
    # the score above), carry on to max_iterations in all; 0: every guess to max_iterations.
    # Turned ICPs start 0.1-0.2 rad off and 80-90 % of them run to the cap (~25 ms each,
    # four a check: the scans over 100 ms). A latency option, meant to keep every pose: on
    # edge drives 221-224 and 227 (where the rule was chosen) and on seven of eight edge
    # seeds never used it does, but on edge 252 it stopped the guess that would have won and
    # lost track (0.178 -> 17.6 m ATE). Off by default since session 27
    # (docs/registration.md, sessions 26 and 27).
    turn_check_screen_iterations: int = 0
    # A trusted match whose share of points within turn_check_gate_m of the map is below
    # this x the median share of the recent matches is checked too (0: only the fitness
    # trigger above). At a turn's onset in open ground the ground keeps ICP's fitness near
    # the recent ones while the match is already turned too little: edge drive 226, scan 751
    # (0.20 rad behind), fitness 0.96 x the recent median, share within 0.3 m 0.86 x. At 0.9
    # the mean ATE of edge drives 221-228 went 0.86 -> 1.00 m (better on two, worse on three;
    # 226 unchanged: no turned fit beat its match) and training drive 118 0.094 -> 0.085 m:
    # not the default (docs/registration.md, session 27).
    turn_check_share_ratio: float = 0.0
    # Re-acquisition (and the retry of a failed match) picks among its plausible fits by the
    # turn check's score (the share of points within turn_check_gate_m of the map), not by
    # ICP's fitness within max_correspondence_distance_m, which open ground gives any heading.
    # False: by ICP's fitness. Edge drives 226 / 242 / 243: 1.81 / 15.0 / 3.69 ->
    # 0.14 / 11.0 / 9.21 m ATE: not the default (docs/registration.md, session 28).
    reacquisition_by_share: bool = False
    # Re-acquisition (and the retry) gives up (a fallback) when its best fit scores below a
    # fit it refused for the motion bounds or the jump by more than turn_check_fitness_margin:
    # a match that slid along the track leaves a wrong last trusted pose, from which the true
    # pose looks implausible and a poor, wrongly turned fit plausible (edge drive 242, scan
    # 319: the right fit refused at share 0.79, one turned 0.34 rad wrong taken at 0.37).
    # False: the best plausible fit is taken.
    reacquisition_beats_refused: bool = True
    # A match beyond the motion bounds from the last trusted pose is still plausible when it
    # is within them from the trusted pose before that one (over the longer time), and its
    # velocity is then the motion since that one; only for a scan at least half a period
    # after the last trusted pose (sooner, it is more likely a copy). Near the speed bound
    # (1.8 m/s against 2 m/s x 1.5) an along-track slide of 0.1 m in one trusted match makes
    # the true next pose look beyond the bounds, and the refusals that follow drop the
    # velocity (edge drive 226, scans 757-774). With the rule above, chosen on edge drives
    # 221 / 226 / 242 / 243 (mean ATE 5.55 -> 0.89 m); on four new edge seeds 2.21 -> 0.09 m,
    # training drives 0.0545 -> 0.0558 m (docs/registration.md, session 28).
    plausible_from_previous_trusted: bool = True
    # A match beyond the bounds (or the jump) from the trusted poses that fits as well as the
    # recent ones is remembered; the next match within the bounds from it is trusted, and the
    # refused one becomes the trusted pose before it. Two agreeing fits outvote a trusted pose
    # that slid: edge drive 221 slid 0.5 m at a headland corner, then refused three good
    # matches in a row, lost track and re-acquired 0.41 rad off. Off: 221 7.40 -> 2.84 m (still
    # lost), level on the nineteen other edge drives, no pose of the record changes
    # (docs/registration.md, session 42).
    plausible_from_refused: bool = False
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
    # would give where new neighbours came; session 15) or 'in_time' ('rebuild' when the
    # rebuild's normals and KD-tree, at their measured cost per point, fit before the next
    # scan is due (one scan_period_s after the scan arrived, as far as the pipeline can
    # tell), else 'on_demand' for that map, with the time left spent on the nearest normals:
    # the same normals either way, so the same trajectory; session 34).
    map_normals: str = 'rebuild'
    # 'in_time': how long after the next scan is due a rebuild's normals and KD-tree may
    # still end. Normals left to the pairs cost their matches 2-4x more per point, so holding
    # the next scan up briefly was thought the cheaper way; paced on lawnmower-111, 0.03 s
    # changed neither the median nor the p95 against 0 (session 34).
    map_normals_slack_s: float = 0.03
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
    # Rough source points (smoothness below map_anchor_smoothness) are thinned to one per
    # voxel of this size (0: off, every rough point of the source voxel kept), so that canopy,
    # which constrains the pose least, holds a smaller share of the match and of the
    # keyframe's points than ground and trunks (needs nu; without it nothing is thinned).
    # Not a steady gain on the training drives (0.5-0.8 m: -3.7 to +13 %), and less than a
    # denser source voxel with no thinning (session 43): off.
    rough_voxel_size_m: float = 0.0
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
        for name, choices in CHOICES.items():
            if getattr(self, name) not in choices:
                raise ConfigError(f'{name} must be one of {choices}, got {getattr(self, name)!r}')
        if self.map_normals != 'rebuild' and self.solver == 'open3d':
            raise ConfigError(f"map_normals {self.map_normals!r} needs solver 'map_tree' or "
                              "'gauss_newton' (open3d's ICP estimates its own)")
        if self.map_update == 'background' and not self._background_map_possible:
            raise ConfigError("map_update 'background' needs mode 'default', solver "
                              "'map_tree' or 'gauss_newton', map_normals 'rebuild', "
                              "point-to-plane estimation and no 'planarity' residual model "
                              "('auto' falls back to 'inline' where these do not hold)")
        if self.residual_model != 'plane' and self.solver != 'gauss_newton':
            raise ConfigError(f"residual_model {self.residual_model!r} needs solver "
                              f"'gauss_newton' (open3d's ICP has one residual type)")
        if not 0.0 < self.kernel_anneal_factor < 1.0:
            raise ConfigError('kernel_anneal_factor must be in (0, 1), got '
                              f'{self.kernel_anneal_factor}')
        if self.anderson_memory and self.solver != 'map_tree':
            raise ConfigError("anderson_memory needs solver 'map_tree'")
        if self.turn_continue_min_rad > 0.0 and (self.mode != 'default'
                                                 or self.solver == 'open3d'):
            raise ConfigError("turn_continue_min_rad needs mode 'default' and solver "
                              "'map_tree' or 'gauss_newton' (open3d's ICP does not say "
                              "whether its iteration cap stopped it)")
        if self.adaptive_kernel_ratio > 0.0:
            if self.mode != 'default' or self.robust_kernel == 'none':
                raise ConfigError("adaptive_kernel_ratio needs mode 'default' and a "
                                  "robust_kernel (the paper's ICP and 'none' have no scale)")
            if not self.adaptive_min_motion_m > 0.0:
                raise ConfigError('adaptive_kernel_ratio needs adaptive_min_motion_m > 0 (the '
                                  'smallest error counted, so the floor of the scale)')
        if self.kernel_anneal_from_m > 0.0:
            self._check_graduated_kernel()
        if self.frequency_affinity_m > 0.0 and self.solver != 'gauss_newton':
            raise ConfigError("frequency_affinity_m needs solver 'gauss_newton' (open3d's "
                              "ICP pairs by distance alone)")
        for name in ('motion_prior_weight', 'frequency_affinity_m', 'rough_weight',
                     'motion_margin', 'rough_kernel_scale_m', 'turn_check_gate_m',
                     'turn_continue_min_rad', 'adaptive_kernel_ratio',
                     'adaptive_min_motion_m', 'kernel_anneal_from_m', 'noise_gate_m',
                     'rough_gate_ratio', 'refine_correspondence_distance_m',
                     'rough_voxel_size_m', 'voxel_grid_offset_m'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ConfigError(f'{name} must be a finite number >= 0, got {value}')
        if not self.voxel_grid_offset_m < self.voxel_size_m:
            raise ConfigError(f'voxel_grid_offset_m ({self.voxel_grid_offset_m}) must be below '
                              f'voxel_size_m ({self.voxel_size_m}): a whole voxel is the '
                              f'same grid')
        if not self.refine_correspondence_distance_m < self.max_correspondence_distance_m:
            raise ConfigError(f'refine_correspondence_distance_m '
                              f'({self.refine_correspondence_distance_m}) must be below '
                              f'max_correspondence_distance_m '
                              f'({self.max_correspondence_distance_m}): it narrows the gate')
        for name in ('rough_kernel_scale_m', 'rough_gate_ratio'):
            if getattr(self, name) > 0.0 and self.solver != 'map_tree':
                raise ConfigError(f"{name} needs solver 'map_tree'")
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
                   'anderson_memory': 0, 'turn_check_screen_iterations': 0,
                   'turn_continue_iterations': 1, 'adaptive_window_scans': 0}
        for name, lowest in minimum.items():
            if getattr(self, name) < lowest:
                raise ConfigError(f'{name} must be >= {lowest}, got {getattr(self, name)}')
        for name in ('min_fitness', 'min_relative_fitness', 'map_anchor_smoothness',
                     'recovery_turn_relative_fitness', 'map_anchor_rough_any_side_share',
                     'turn_check_fitness_margin', 'turn_check_share_ratio'):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f'{name} must be in [0, 1], got {getattr(self, name)}')
        for name in ('turn_check_share_ratio', 'reacquisition_by_share'):
            if getattr(self, name) and self.turn_check_gate_m <= 0.0:
                raise ConfigError(f'{name} needs turn_check_gate_m > 0 (the share is of the '
                                  'points within that distance of the map)')
        for name in ('map_anchor_rough_view_deg', 'map_window_rough_view_deg'):
            if not 0.0 <= getattr(self, name) <= 180.0:
                raise ConfigError(f'{name} must be in [0, 180], got {getattr(self, name)}')
        if not 0.0 < self.map_smooth_view_deg <= 180.0:
            raise ConfigError('map_smooth_view_deg must be in (0, 180] (180: smooth points '
                              f'are served from any side), got {self.map_smooth_view_deg}')
        if not self.map_anchors and (self.map_window_rough_view_deg > 0.0
                                     or self.map_smooth_view_deg < 180.0):
            # The view rules tell smooth from rough by the anchors' threshold.
            raise ConfigError('map_anchors false needs the map served from any side: set '
                              'map_window_rough_view_deg 0 and map_smooth_view_deg 180 too '
                              f'(got {self.map_window_rough_view_deg} and '
                              f'{self.map_smooth_view_deg})')
        if self.map_smooth_view_deg < 180.0 and not (self.map_anchor_rough_view_deg > 0.0
                                                     or self.map_window_rough_view_deg > 0.0):
            raise ConfigError('map_smooth_view_deg below 180 needs a view rule to apply to: '
                              'map_anchor_rough_view_deg > 0 or map_window_rough_view_deg > 0')
        if not (math.isfinite(self.recovery_correspondence_factor)
                and self.recovery_correspondence_factor >= 1.0):
            raise ConfigError(f'recovery_correspondence_factor must be >= 1, got '
                              f'{self.recovery_correspondence_factor}')
        if not (math.isfinite(self.map_normals_slack_s) and self.map_normals_slack_s >= 0.0):
            raise ConfigError(f'map_normals_slack_s must be a finite number >= 0, got '
                              f'{self.map_normals_slack_s}')
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
    def reads_scan_frequencies_before_pose(self) -> bool:
        """Whether a scan's match reads its own frequencies (else only its keyframe does,
        after the pose): the options of `ScanRegistration._downsample` and the ICP backend
        that read them."""
        return (self.voxel_priority == 'smoothest' or self.residual_model == 'frequency'
                or self.rough_beam_shift_m != 0.0 or self.rough_kernel_scale_m > 0.0
                or self.rough_gate_ratio > 0.0 or self.frequency_affinity_m > 0.0)

    @property
    def resolved_map_update(self) -> str:
        """'inline' or 'background', what 'auto' stands for with these settings."""
        if self.map_update != 'auto':
            return self.map_update
        return 'background' if self._background_map_possible else 'inline'

    def _check_graduated_kernel(self) -> None:
        """kernel_anneal_from_m only where its schedule runs as documented: the map-tree ICP
        (point-to-plane), one scale for all pairs, no Anderson steps (their energy test
        compares scales), no continued match (a continuation would start the schedule again),
        and a schedule that ends within max_iterations."""
        if (self.solver != 'map_tree' or self.mode != 'default'
                or self.resolved_estimation != 'point_to_plane'):
            raise ConfigError("kernel_anneal_from_m needs mode 'default', solver 'map_tree' "
                              "and point_to_plane estimation")
        clashes = [name for name in ('anderson_memory', 'rough_kernel_scale_m',
                                     'turn_continue_min_rad', 'turn_check_screen_iterations')
                   if getattr(self, name)]
        if clashes:
            raise ConfigError(f'kernel_anneal_from_m cannot be combined with {clashes}')
        if not self.kernel_anneal_from_m > self.robust_kernel_scale_m:
            raise ConfigError(f'kernel_anneal_from_m ({self.kernel_anneal_from_m}) must exceed '
                              f'robust_kernel_scale_m ({self.robust_kernel_scale_m})')
        steps = math.ceil(math.log(self.robust_kernel_scale_m / self.kernel_anneal_from_m)
                          / math.log(self.kernel_anneal_factor))
        if steps >= self.max_iterations:
            raise ConfigError(f'the graduated kernel takes {steps} iterations to reach '
                              f'robust_kernel_scale_m, max_iterations is {self.max_iterations}')

    @property
    def resolved_estimation(self) -> str:
        """The estimator 'auto' stands for in this mode."""
        if self.estimation != 'auto':
            return self.estimation
        return 'point_to_point' if self.mode == 'paper' else 'point_to_plane'


