"""Benchmark of record: gft_odom against its peers on long, varied, held-out drives.

Usage:
  .venv/bin/python benchmarks/bench_record.py
      [--drives held-out|training|new-held-out|edge|confirm|edge-confirm|edge-new|
                edge-screen|edge-late|edge-slid|stress]
      [--jobs N]
      [--cache DIR]
      [--only LABEL ...] [--out benchmarks/results]

Simulates the drives once into the cache (`~/.cache/gft_odom/drives` or $GFT_ODOM_DRIVES;
~0.09 s per full-resolution scan, ~4 min a drive on one core), then runs every entry on every
drive and writes record_<drives>.json / .md and record_<drives>_ate_over_distance.png. The
record is ten drives: `--drives held-out` (six) and `--drives new-held-out` (four).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from gft_odom.bench.drives import (
    CONFIRM_DRIVES,
    EDGE_CONFIRM_DRIVES,
    EDGE_DRIVES,
    EDGE_LATE_DRIVES,
    EDGE_NEW_DRIVES,
    EDGE_SCREEN_DRIVES,
    EDGE_SLID_DRIVES,
    HELD_OUT_DRIVES,
    NEW_HELD_OUT_DRIVES,
    STRESS_DRIVES,
    TRAINING_DRIVES,
    default_cache_dir,
    ensure_drives,
)
from gft_odom.bench.record import Entry, run_record, write_record
from gft_odom.bench.report import machine_info

RESULTS = Path(__file__).resolve().parent / 'results'
# --drives: the drive set by name (its results go to <kind>_<name>.*).
DRIVE_SETS = {'held-out': HELD_OUT_DRIVES, 'training': TRAINING_DRIVES,
              'new-held-out': NEW_HELD_OUT_DRIVES, 'edge': EDGE_DRIVES,
              'confirm': CONFIRM_DRIVES, 'edge-confirm': EDGE_CONFIRM_DRIVES,
              'edge-new': EDGE_NEW_DRIVES, 'edge-screen': EDGE_SCREEN_DRIVES,
              'edge-late': EDGE_LATE_DRIVES, 'edge-slid': EDGE_SLID_DRIVES,
              'stress': STRESS_DRIVES}

# Our package as users run it (config/filter_odom.yaml = the dataclass defaults), then peers.
# The registration defaults before the map was re-anchored (a 60-keyframe map whose voxels
# keep the newest keyframe's point, no retry of a failed match), spelled out so the row means
# the same after the change. The defaults before issue 15 (15 keyframes) are in the study.
# Session 6 made anchors the default (a keyframe leaving the window leaves its points in the
# map); the rows of the studies before spell out that they had none.
NO_ANCHORS = (('registration.map_anchors', False),)
# Session 7 added turned guesses to re-acquisition (the last resort); the rows before had none.
NO_TURN_GUESSES = (('registration.recovery_yaw_guesses', 0),)
# Session 14 made rough anchors served from their own side the default; the rows before had
# smooth anchors only.
NO_VIEW_GATE = (('registration.map_anchor_rough_view_deg', 0.0),)
# Session 17 made a share (0.25) of the rough anchors served from any side the default; the
# rows with view-gated rough anchors before had none.
NO_ANY_SIDE = (('registration.map_anchor_rough_any_side_share', 0.0),)
# Session 18 made motion compensation (deskew, velocity window 2) the default; every row
# before had none (and the window of then, 5: no effect without deskew, but in the config).
NO_DESKEW = (('registration.deskew', False), ('registration.deskew_velocity_window', 5))


# Session 40 made every map point served only from the side it was seen from the default
# (the window's points as the anchors, smooth ones too); every row before served the window
# from any side and smooth anchors from any side.
NO_WINDOW_GATE = (('registration.map_window_rough_view_deg', 0.0),
                  ('registration.map_smooth_view_deg', 180.0))


def _pinned(entries: tuple[Entry, ...], pin: tuple) -> tuple[Entry, ...]:
    """Our rows with `pin` first (an entry's own override, later in the list, still wins);
    the peers' rows as they are."""
    return tuple(Entry(e.label, e.method, pin + tuple(e.overrides))
                 if e.method in ('default+gft', 'default') else e for e in entries)


def before_deskew(entries: tuple[Entry, ...]) -> tuple[Entry, ...]:
    """Rows measured before deskew was the default, pinned to none."""
    return _pinned(entries, NO_DESKEW)


def before_window_gate(entries: tuple[Entry, ...]) -> tuple[Entry, ...]:
    """Rows measured before the window's points were served from their side (session 40)."""
    return _pinned(entries, NO_WINDOW_GATE)


PREVIOUS_DEFAULTS = (('registration.map_keyframes', 60), ('registration.map_max_points', 80000),
                     ('registration.map_keyframe_eviction', 'oldest'),
                     ('registration.keyframe_rotation_rad', 0.2),
                     ('registration.map_voxel_keeps', 'newest'),
                     ('registration.retry_failed_match', False)) + NO_ANCHORS + NO_TURN_GUESSES
# Before issue 15: a 15-keyframe map.
ORIGINAL_DEFAULTS = PREVIOUS_DEFAULTS[2:] + (('registration.map_keyframes', 15),
                                             ('registration.map_max_points', 40000))
# The record: the package as users run it, then every LiDAR-only peer with its own defaults
# (GenZ-ICP with its deskew and as it ships, deskew off), each stamped where its pose holds.
ENTRIES = (
    Entry('gft_odom', 'default+gft'),
    Entry('kiss-icp', 'kiss-icp'),
    Entry('GenZ-ICP', 'genz-icp'),
    Entry('GenZ-ICP, no deskew (as shipped)', 'genz-icp-no-deskew'),
    Entry('CT-ICP', 'ct-icp'),
    Entry('MAD-ICP', 'mad-icp'),
    Entry('FORM', 'form'),
    Entry('LOAM', 'loam'),
)

# Issue 20's ablations. Session 6: the frequency deciding what the map keeps (anchors: a
# keyframe leaving the window leaves its smooth points, ground and trunks, behind), against the
# same registration without frequencies (--no-filter: nothing is anchored, the map is the
# keyframe window alone) and with each scan's frequencies shuffled among its points (random
# points anchored: the memory without the frequency's choice).
_ANCHORS = (('registration.map_anchors', True), ('registration.map_anchor_smoothness', 0.75)
            ) + NO_VIEW_GATE
ABLATION_ENTRIES = (
    Entry('anchors (frequency; the default)', 'default+gft', _ANCHORS),
    Entry('no frequency (--no-filter)', 'default', _ANCHORS),
    Entry('anchors, shuffled frequency', 'default+gft',
          _ANCHORS + (('pipeline.shuffle_frequencies', True),)),
    Entry('anchors, every point', 'default+gft',
          (('registration.map_anchor_smoothness', 0.0),) + NO_VIEW_GATE),
)
# Session 5: the Gauss-Newton solver with per-pair residuals: the frequency as a per-pair
# weight (rough_weight 0: canopy pairs down-weighted, the best of the 'frequency' variants on
# training drive every_other_row-113), the same registration without frequencies, shuffled,
# and the map neighbourhood's planarity in place of the frequency (GenZ-ICP-style
# point-to-point rows).
_GN = (('registration.solver', 'gauss_newton'), ('registration.convergence_m', 5e-4),
       ('registration.residual_model', 'frequency'), ('registration.rough_weight', 0.0)
       ) + NO_ANCHORS + NO_TURN_GUESSES
ABLATION_ENTRIES += (
    Entry('GN, frequency as weight', 'default+gft', _GN),
    Entry('GN, no frequency (--no-filter)', 'default', _GN),
    Entry('GN, shuffled frequency', 'default+gft',
          _GN + (('pipeline.shuffle_frequencies', True),)),
    Entry('GN, map planarity (GenZ-style)', 'default+gft',
          _GN[:2] + NO_ANCHORS + NO_TURN_GUESSES + (
              ('registration.residual_model', 'planarity'),
              ('registration.rough_residual', 'point'))),
)
# Session 14: rough anchors served only from the side they were seen from (session 9's
# map_anchor_rough_view_deg, 3-4 % better than the default on the training drives), with the
# frequency, shuffled, and without it (every anchor rough, so every one view-gated).
_VIEW_GATE = (('registration.map_anchor_rough_view_deg', 60.0),)
_VIEW = _VIEW_GATE + NO_ANY_SIDE
ABLATION_ENTRIES += (
    Entry('view-gated rough anchors (frequency)', 'default+gft', _VIEW),
    Entry('view-gated rough anchors, shuffled frequency', 'default+gft',
          _VIEW + (('pipeline.shuffle_frequencies', True),)),
    Entry('view-gated rough anchors, no frequency (--no-filter)', 'default', _VIEW),
)
# Session 15: the control's spread, two more permutations of each scan's frequencies.
ABLATION_ENTRIES += tuple(
    Entry(f'view-gated rough anchors, shuffled frequency (seed {seed})', 'default+gft',
          _VIEW + (('pipeline.shuffle_frequencies', True), ('pipeline.shuffle_seed', seed)))
    for seed in (1, 2))

# Session 16: a share of the rough anchors served from any side (session 15: 2 % on the
# training drives, 7 % on the held-out ones), its frequency ablation, on drives never seen.
_ANY_SIDE = _VIEW_GATE + (('registration.map_anchor_rough_any_side_share', 0.25),)
ABLATION_ENTRIES += (
    Entry('any-side share 0.25 (frequency)', 'default+gft', _ANY_SIDE),
    Entry('any-side share 0.25, shuffled frequency', 'default+gft',
          _ANY_SIDE + (('pipeline.shuffle_frequencies', True),)),
    Entry('any-side share 0.25, no frequency (--no-filter)', 'default', _ANY_SIDE),
    Entry('GenZ-ICP', 'genz-icp'),
)
# Session 18: deskew is the default; the frequency ablation of the new default.
ABLATION_ENTRIES = before_window_gate(before_deskew(ABLATION_ENTRIES) + (
    Entry('deskew (frequency; the default)', 'default+gft'),
    Entry('deskew, shuffled frequency', 'default+gft', (('pipeline.shuffle_frequencies', True),)),
    Entry('deskew, no frequency (--no-filter)', 'default'),
)) + (
    # Session 40: every map point served from its side (the default), its frequency ablation.
    Entry('served from its side (frequency; the default)', 'default+gft'),
    Entry('served from its side, shuffled frequency', 'default+gft',
          (('pipeline.shuffle_frequencies', True),)),
    Entry('served from its side, no frequency (--no-filter)', 'default'),
) + tuple(
    # Session 41: the control's spread at the session 40 default, two more permutations.
    Entry(f'served from its side, shuffled frequency (seed {seed})', 'default+gft',
          (('pipeline.shuffle_frequencies', True), ('pipeline.shuffle_seed', seed)))
    for seed in (1, 2))

# A row as it is and with each scan's frequencies shuffled among its points (the control).
_SHUFFLED = (('pipeline.shuffle_frequencies', True),)
_AND_SHUFFLED = (('', ()), (', shuffled frequency', _SHUFFLED))

# The drift study (docs/benchmarks.md): candidate changes to the default, run on the TRAINING
# drives only; the held-out record then reports the one chosen against the old default.
_DESKEW = ('registration.deskew', True)
_LONG_MAP = (('registration.map_keyframes', 60), ('registration.map_max_points', 80000))
STUDY_ENTRIES = before_window_gate(before_deskew((
    Entry('default', 'default+gft', ORIGINAL_DEFAULTS),
    Entry('deskew', 'default+gft', ORIGINAL_DEFAULTS + (_DESKEW,)),
    Entry('map 60 keyframes', 'default+gft', ORIGINAL_DEFAULTS + _LONG_MAP),
    Entry('deskew + map 60 keyframes', 'default+gft', ORIGINAL_DEFAULTS + (_DESKEW,) + _LONG_MAP),
    Entry('deskew + ldos B4 [1]', 'default+gft', ORIGINAL_DEFAULTS
          + (_DESKEW, ('spectral.n_bands', 4), ('spectral.band_mask', [1]))),
    # Round 2, after round 1 showed the map's length mattered most.
    Entry('map 60 kf, rotation kf 1 rad', 'default+gft',
          PREVIOUS_DEFAULTS + (('registration.keyframe_rotation_rad', 1.0),)),
    Entry('deskew + map 60 kf, rotation kf 1 rad', 'default+gft',
          PREVIOUS_DEFAULTS + (_DESKEW, ('registration.keyframe_rotation_rad', 1.0))),
    Entry('map 120 kf', 'default+gft', PREVIOUS_DEFAULTS + (
        ('registration.map_keyframes', 120), ('registration.map_max_points', 120000))),
    Entry('map 60 kf, map voxel 0.5 m', 'default+gft',
          PREVIOUS_DEFAULTS + (('registration.map_voxel_size_m', 0.5),)),
    Entry('map 60 kf, farthest eviction', 'default+gft',
          PREVIOUS_DEFAULTS + (('registration.map_keyframe_eviction', 'farthest'),)),
    Entry('map 60 kf, farthest eviction, rotation kf 1 rad', 'default+gft',
          PREVIOUS_DEFAULTS + (('registration.map_keyframe_eviction', 'farthest'),
                               ('registration.keyframe_rotation_rad', 1.0))),
    # Round 3, on seven training drives (three with fast pivots), from the round-2 default.
    Entry('previous default (60 kf)', 'default+gft', PREVIOUS_DEFAULTS),
    Entry('previous default + deskew', 'default+gft', PREVIOUS_DEFAULTS + (_DESKEW,)),
    Entry('voxels keep oldest', 'default+gft',
          PREVIOUS_DEFAULTS + (('registration.map_voxel_keeps', 'oldest'),)),
    Entry('retry failed match', 'default+gft',
          PREVIOUS_DEFAULTS + (('registration.retry_failed_match', True),)),
    Entry('voxels keep oldest + retry (new default)', 'default+gft'),
    Entry('new default + map points from the scan', 'default+gft',
          (('registration.map_points_from', 'scan'),)),
    # Session 14: a map voxel keeps the mean of every view in the window, not the first view
    # (the bias study: the map is always seen from behind).
    Entry('default (session 13)', 'default+gft', NO_VIEW_GATE),
    Entry('map voxels keep the mean of all views', 'default+gft',
          (('registration.map_voxel_keeps', 'mean'),) + NO_VIEW_GATE),
    Entry('rough map voxels keep the mean of all views', 'default+gft',
          (('registration.map_voxel_keeps', 'mean_rough'),) + NO_VIEW_GATE),
    Entry('rough map voxels keep the mean, shuffled frequency', 'default+gft',
          (('registration.map_voxel_keeps', 'mean_rough'),
           ('pipeline.shuffle_frequencies', True)) + NO_VIEW_GATE),
    # Session 15: a keyframe on rotation alone. A VLP-16 sees all around, so turning on the
    # spot shows little new, while a keyframe's map work (~150 ms) overruns the scan period.
    Entry('default (session 14)', 'default+gft'),
    Entry('rotation keyframes 0.5 rad', 'default+gft',
          (('registration.keyframe_rotation_rad', 0.5),)),
    Entry('no rotation keyframes', 'default+gft',
          (('registration.keyframe_rotation_rad', 3.2),)),
    # Session 15: a map point's normal estimated once, when it enters the map, and kept (the
    # rebuild's normals of every point are most of a keyframe's map work).
    Entry('map normals kept', 'default+gft', (('registration.map_normals', 'kept'),)),
    # Session 15: the shuffled control beat the frequency where rows are met again from the
    # other side; serve a share of the rough anchors (drawn by voxel) from any side as well.
    Entry('rough anchors from any side, share 0.25', 'default+gft',
          (('registration.map_anchor_rough_any_side_share', 0.25),)),
    Entry('rough anchors from any side, share 0.5', 'default+gft',
          (('registration.map_anchor_rough_any_side_share', 0.5),)),
    # Session 16: a keyframe's map rebuild on a thread while the next scan is matched
    # against the map before it (the at-rate p95: the rebuild no longer holds up that scan).
    Entry('map update in the background', 'default+gft',
          (('registration.map_update', 'background'),)),
    # Session 17: the frequency choosing which rough anchors are served from any side (a
    # lower smoothness threshold, no random share) against the random share of the default.
    Entry('anchor smoothness 0.6, no any-side share', 'default+gft',
          (('registration.map_anchor_smoothness', 0.6),) + NO_ANY_SIDE),
    Entry('anchor smoothness 0.5, no any-side share', 'default+gft',
          (('registration.map_anchor_smoothness', 0.5),) + NO_ANY_SIDE),
    # Session 18: motion compensation on the session 17 default (session 5: it helped two of
    # three training drives a lot and hurt the third, under a map policy since replaced).
    Entry('deskew (session 17 default)', 'default+gft', (_DESKEW,)),
    # Session 18: the frequency sets each pair's robust kernel: a Tukey scale for smooth scan
    # points (ground, trunks) and another for rough ones (canopy), blended by smoothness; one
    # kernel for all between the two is its geometric control.
    Entry('canopy kernel 0.15 m, smooth 0.3 m', 'default+gft',
          (('registration.rough_kernel_scale_m', 0.15),)),
    Entry('smooth kernel 0.15 m, canopy 0.3 m', 'default+gft',
          (('registration.robust_kernel_scale_m', 0.15),
           ('registration.rough_kernel_scale_m', 0.3))),
    Entry('one kernel 0.2 m', 'default+gft', (('registration.robust_kernel_scale_m', 0.2),)),
)) + (
    # Session 18: with deskew (window 5) held-out lawnmower-205 lost 0.14 rad of heading at a
    # turn's onset (the mean twist of 5 scans lags a yaw rate that jumps to 1 rad/s); the
    # velocity window of deskew, chosen here on the training drives.
    Entry('deskew, velocity window 1', 'default+gft',
          (('registration.deskew', True), ('registration.deskew_velocity_window', 1))),
    Entry('deskew, velocity window 2', 'default+gft',
          (('registration.deskew', True), ('registration.deskew_velocity_window', 2))),
    # Session 19: the frequency choosing each source voxel's point (the smoothest) on the
    # deskewed default; without frequencies it is the default's first point, so a gain here
    # is the frequency's.
    Entry('source voxels keep the smoothest point', 'default+gft',
          (('registration.voxel_priority', 'smoothest'),)),
    # Session 20: a trusted match that fits poorly for the recent ones is matched again from
    # turned guesses (at a turn's onset in open ground ICP from the prediction turns too
    # little and is trusted: edge drive 221).
    Entry('turn check', 'default+gft', (('registration.turn_check', True),)),
)) + (
    # Session 42: on edge drive 221 the poses slid 0.7 m through a headland corner and three
    # good matches after it were refused for the bounds; the next match that agrees with a
    # refused one is trusted (on the default of session 40).
    Entry('a refused match vouches for the next', 'default+gft',
          (('registration.plausible_from_refused', True),)),
    # Session 42: two of the scan's own frequency roles (sessions 18-19, under the map of
    # then) screened again on the session 40 map, training drives first.
    Entry('source voxels keep the smoothest point (session 40 map)', 'default+gft',
          (('registration.voxel_priority', 'smoothest'),)),
    Entry('canopy kernel 0.15 m (session 40 map)', 'default+gft',
          (('registration.rough_kernel_scale_m', 0.15),)),
    # Session 43: the frequency thins the source's canopy (rough points one per coarser
    # voxel), so ground and trunks weigh more in the match; its shuffled control thins a
    # random share of the same size.
) + tuple(
    Entry(f'rough source voxel {size} m{label}', 'default+gft',
          (('registration.rough_voxel_size_m', size),) + extra)
    for size in (0.5, 0.6, 0.7, 0.8)
    for label, extra in _AND_SHUFFLED) + tuple(
    # ... with the smooth points denser than the default's 0.4 m source voxel; and the
    # source voxel alone, every point alike (the thinning's geometric control).
    Entry(f'source voxel 0.3 m, rough {size} m{label}', 'default+gft',
          (('registration.voxel_size_m', 0.3), ('registration.rough_voxel_size_m', size))
          + extra)
    for size in (0.4, 0.6)
    for label, extra in _AND_SHUFFLED) + tuple(
    Entry(f'source voxel {size} m', 'default+gft', (('registration.voxel_size_m', size),))
    for size in (0.25, 0.3, 0.35)) + tuple(
    # The noise floor of a screen: a source voxel 2.5 % off the default's moves every voxel
    # boundary and nothing else.
    Entry(f'source voxel {size} m (noise floor){label}', method,
          (('registration.voxel_size_m', size),) + extra)
    for size in (0.39, 0.41)
    for label, method, extra in (('', 'default+gft', ()),
                                 (', no frequency (--no-filter)', 'default', ()),
                                 (', shuffled frequency', 'default+gft', _SHUFFLED))) + tuple(
    # Session 44: the scan's range signal low-pass filtered on the scan-line graph before the
    # match (the paper's idea applied to the signal, not to the choice of points).
    Entry(f'range low-pass alpha {alpha}, sigma {sigma} m', 'default+gft',
          (('spectral.range_lowpass_alpha', alpha), ('spectral.range_lowpass_sigma_m', sigma)))
    for alpha, sigma in ((2.0, 0.1), (8.0, 0.1), (8.0, 0.3), (30.0, 0.05), (8.0, 1.0))) + tuple(
    # Session 44: the noise floor again, the default's voxel size on another grid (its origin
    # shifted half a voxel): the frequency, no frequency and the shuffled control.
    Entry(f'source grid offset {offset} m{label}', method,
          (('registration.voxel_grid_offset_m', offset),) + extra)
    for offset in (0.2, 0.1)
    for label, method, extra in (('', 'default+gft', ()),
                                 (', no frequency (--no-filter)', 'default', ()),
                                 (', shuffled frequency', 'default+gft', _SHUFFLED)))


def main(argv=None) -> int:
    """Simulate what is missing, run the record, write its results."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--drives', choices=tuple(DRIVE_SETS), default='held-out')
    p.add_argument('--cache', type=Path, default=None,
                   help=f'simulated drives (default {default_cache_dir()})')
    p.add_argument('--jobs', type=int, default=2, help='processes (simulation and methods)')
    p.add_argument('--only', nargs='*', default=None, help='entry labels to run')
    p.add_argument('--fresh', action='store_true',
                   help='measure every pair again (default: reuse results kept in the cache)')
    p.add_argument('--cached-only', action='store_true',
                   help='report the pairs already measured in the cache, measure nothing')
    p.add_argument('--study', action='store_true',
                   help='the drift-study candidates instead of the record entries')
    p.add_argument('--ablation', action='store_true',
                   help="issue 20's frequency ablation instead of the record entries")
    p.add_argument('--names', nargs='*', default=None,
                   help='only these drives of the set (e.g. lawnmower-111 spiral-112)')
    p.add_argument('--out', type=Path, default=RESULTS)
    args = p.parse_args(argv)
    drives = [d for d in DRIVE_SETS[args.drives] if args.names is None or d.name in args.names]
    if not drives:
        p.error(f'no drive of {args.drives} matches --names {args.names}')
    pool = STUDY_ENTRIES if args.study else ABLATION_ENTRIES if args.ablation else ENTRIES
    entries = [e for e in pool if args.only is None or e.label in args.only]
    if not entries:
        p.error(f'no entry matches --only {args.only}; labels: {[e.label for e in pool]}')
    t0 = time.perf_counter()
    sequences = ensure_drives(drives, args.cache, jobs=args.jobs,
                              progress=lambda name: print(f'simulated {name}', flush=True))
    t_sim = time.perf_counter() - t0
    record = run_record(entries, sequences, jobs=args.jobs,
                        progress=lambda label, drive: print(f'{label} on {drive}', flush=True),
                        cache_dir=None if args.fresh else
                        (args.cache or default_cache_dir()) / 'record_runs',
                        cached_only=args.cached_only)
    settings = {'drives': args.drives, 'jobs': args.jobs, 'simulate_s': t_sim,
                'methods_s': time.perf_counter() - t0 - t_sim, 'machine': machine_info()}
    kind = 'study' if args.study else 'ablation' if args.ablation else 'record'
    stem = f'{kind}_{args.drives}' + ('_' + '_'.join(args.names) if args.names else '')
    paths = write_record(record, args.out, settings, stem=stem)
    print(paths['markdown'].read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main())
