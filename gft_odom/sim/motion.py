"""Robot trajectories through the orchard: where base_link is at any time.

A scenario is a planar path in the row frame (straight lanes, arcs at the row ends), driven at
about 1 m/s (slower in turns), with a small lateral and yaw wobble of a skid-steer robot. Height,
roll and pitch come from the terrain under the four wheels, so the pose is a smooth function of
time that the LiDAR model can evaluate per firing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from gft_odom.errors import SimulationError
from gft_odom.sim.orchard import HEADLAND_M, Orchard
from gft_odom.sim.variation import MAX_SPEED_MPS, MIN_CRUISE_MPS, OrchardVariation

SCENARIOS = ('row', 'uturn', 'loop')

# Clearpath Jackal: wheelbase 0.262 m, track 0.375 m; base_link above the ground.
WHEELBASE_M = 0.262
TRACK_M = 0.375
BASE_LINK_HEIGHT_M = 0.07
# uturn: the turn circles the row end, centred this far past the last trunk.
TURN_CLEARANCE_M = 3.5
# loop: lanes `LOOP_LANE_GAP` apart, joined by semicircles in the headlands.
LOOP_LANE_GAP = 2


def _arc(centre, radius, a0, a1, step):
    n = max(2, int(np.ceil(abs(a1 - a0) * radius / step)) + 1)
    a = np.linspace(a0, a1, n)
    return np.column_stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)])


def _line(p0, p1, step):
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(2, int(np.ceil(np.linalg.norm(p1 - p0) / step)) + 1)
    return p0 + np.linspace(0.0, 1.0, n)[:, None] * (p1 - p0)


def _join(*pieces):
    out = [pieces[0]]
    for p in pieces[1:]:
        out.append(p[1:] if np.allclose(p[0], out[-1][-1]) else p)
    return np.concatenate(out)


def required_row_length_m(scenario: str, distance_m: float) -> float:
    """Row length an orchard needs so that `scenario` fits `distance_m` of driving.

    Assumes the widest row spacing (7 m).
    """
    if scenario == 'row':
        need = distance_m + 8.0
    elif scenario == 'uturn':
        need = 0.5 * (distance_m - np.pi * 3.5) + 4.0
    elif scenario == 'loop':
        radius = 0.5 * LOOP_LANE_GAP * 7.0
        # One lap a little shorter than the drive (turns are slower), so the loop closes.
        need = 0.5 * (0.85 * distance_m - 2.0 * np.pi * radius) - 2.0 * TURN_CLEARANCE_M
    else:
        raise SimulationError(f'unknown scenario {scenario!r}; choose one of {SCENARIOS}')
    # Rows of at least 40 m (20 m for a loop, so ~95 m of driving closes one).
    return float(np.clip(need, 20.0 if scenario == 'loop' else 40.0, 200.0))


def _scenario_path_uv(orchard: Orchard, scenario: str, distance_m: float,
                      step_m: float) -> tuple[np.ndarray, bool]:
    """Planar path in the row frame and whether it is a closed loop."""
    n_rows = len(orchard.row_v_m)
    u0, u1 = orchard.row_start_u_m, orchard.row_end_u_m
    if scenario == 'row':
        v = orchard.lane_v_m(n_rows // 2 - 1)
        start = u0 + 2.0
        return _line((start, v), (start + max(distance_m, 1.0) + 20.0, v), step_m), False
    if scenario == 'uturn':
        lane = n_rows // 2 - 1
        va, vb = orchard.lane_v_m(lane), orchard.lane_v_m(lane + 1)
        radius = 0.5 * (vb - va)
        turn_u = u1 + TURN_CLEARANCE_M
        leg = float(np.clip(0.5 * (distance_m - np.pi * radius), 3.0, turn_u - u0 - 1.0))
        path = _join(_line((turn_u - leg, va), (turn_u, va), step_m),
                     _arc((turn_u, 0.5 * (va + vb)), radius, -0.5 * np.pi, 0.5 * np.pi, step_m),
                     _line((turn_u, vb), (turn_u - leg - 30.0, vb), step_m))
        return path, False
    if scenario == 'loop':
        lane = max(0, n_rows // 2 - 1 - LOOP_LANE_GAP // 2)
        lane_b = min(lane + LOOP_LANE_GAP, n_rows - 2)
        if lane_b == lane:
            raise SimulationError(f'a loop needs at least 3 rows, the orchard has {n_rows}')
        va, vb = orchard.lane_v_m(lane), orchard.lane_v_m(lane_b)
        radius = 0.5 * (vb - va)
        if radius + 1.0 > HEADLAND_M + TURN_CLEARANCE_M:
            raise SimulationError(f'loop turn radius {radius:.1f} m does not fit the headland')
        ua, ub = u0 - TURN_CLEARANCE_M, u1 + TURN_CLEARANCE_M
        start = u0 + 1.0
        vm = 0.5 * (va + vb)
        path = _join(_line((start, va), (ub, va), step_m),
                     _arc((ub, vm), radius, -0.5 * np.pi, 0.5 * np.pi, step_m),
                     _line((ub, vb), (ua, vb), step_m),
                     _arc((ua, vm), radius, 0.5 * np.pi, 1.5 * np.pi, step_m),
                     _line((ua, va), (start, va), step_m))
        return path, True
    raise SimulationError(f'unknown scenario {scenario!r}; choose one of {SCENARIOS}')


@dataclass(frozen=True)
class RobotMotion:
    """Pose of base_link in the world as a function of time since the start of the run.

    The path is tabulated densely in arc length s; `t_of_s` comes from the speed profile.
    """

    orchard: Orchard
    s_m: np.ndarray  # (P,) arc length at the path samples
    uv_m: np.ndarray  # (P, 2) row-frame path
    heading_rad: np.ndarray  # (P,) unwrapped path tangent direction in the row frame
    t_s: np.ndarray  # (P,) time at which s is reached
    closed: bool
    lateral_wobble_m: float
    lateral_wobble_wavelength_m: float
    lateral_wobble_phase_rad: float
    yaw_wobble_rad: float
    yaw_wobble_hz: float
    yaw_wobble_phase_rad: float

    @property
    def duration_s(self) -> float:
        """Time to drive the tabulated path once."""
        return float(self.t_s[-1])

    def _s_at(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        if self.closed:
            laps, t_in = np.divmod(t, self.t_s[-1])
            return np.interp(t_in, self.t_s, self.s_m) + laps * self.s_m[-1]
        return np.interp(t, self.t_s, self.s_m)

    def planar_pose(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) (T, 2) and yaw (T,) of base_link at times `t_s` (seconds from start)."""
        s = self._s_at(t_s)
        s_tab = np.mod(s, self.s_m[-1]) if self.closed else s
        u = np.interp(s_tab, self.s_m, self.uv_m[:, 0])
        v = np.interp(s_tab, self.s_m, self.uv_m[:, 1])
        heading = np.interp(s_tab, self.s_m, self.heading_rad)
        wobble = self.lateral_wobble_m * np.sin(
            2.0 * np.pi * s / self.lateral_wobble_wavelength_m + self.lateral_wobble_phase_rad)
        uv = np.column_stack([u - np.sin(heading) * wobble, v + np.cos(heading) * wobble])
        yaw = heading + self.orchard.heading_rad + self.yaw_wobble_rad * np.sin(
            2.0 * np.pi * self.yaw_wobble_hz * np.asarray(t_s, float) + self.yaw_wobble_phase_rad)
        return self.orchard.to_world_xy(uv), yaw

    def poses(self, t_s: np.ndarray) -> np.ndarray:
        """T_world_base (T, 4, 4) at times `t_s`: planar pose + height, roll, pitch from the
        ground under the four wheels."""
        t_s = np.atleast_1d(np.asarray(t_s, dtype=float))
        xy, yaw = self.planar_pose(t_s)
        c, s = np.cos(yaw), np.sin(yaw)
        fwd = np.column_stack([c, s])
        left = np.column_stack([-s, c])
        hx, hy = 0.5 * WHEELBASE_M, 0.5 * TRACK_M
        ground = self.orchard.ground
        z = {}
        for name, (a, b) in {'fl': (hx, hy), 'fr': (hx, -hy), 'rl': (-hx, hy),
                             'rr': (-hx, -hy)}.items():
            p = xy + a * fwd + b * left
            z[name] = ground.height(p[:, 0], p[:, 1])
        front, rear = 0.5 * (z['fl'] + z['fr']), 0.5 * (z['rl'] + z['rr'])
        lft, rgt = 0.5 * (z['fl'] + z['rl']), 0.5 * (z['fr'] + z['rr'])
        pitch = np.arctan2(rear - front, WHEELBASE_M)
        roll = np.arctan2(lft - rgt, TRACK_M)
        height = 0.5 * (front + rear) + BASE_LINK_HEIGHT_M
        poses = np.tile(np.eye(4), (t_s.size, 1, 1))
        poses[:, :3, :3] = Rotation.from_euler('xyz', np.column_stack([roll, pitch, yaw])
                                               ).as_matrix()
        poses[:, :3, 3] = np.column_stack([xy, height])
        return poses


def make_motion(orchard: Orchard, scenario: str, duration_s: float, speed_mps: float = 1.0,
                seed: int = 0, lateral_wobble_m: float = 0.05,
                yaw_wobble_rad: float = 0.02) -> RobotMotion:
    """Plan `scenario` in `orchard` for at least `duration_s` of driving at ~`speed_mps`.

    Turns are driven at 60-100 % of the speed depending on curvature.
    """
    if not speed_mps > 0.0:
        raise SimulationError(f'speed_mps must be > 0, got {speed_mps}')
    if not duration_s >= 0.0:
        raise SimulationError(f'duration_s must be >= 0, got {duration_s}')
    step = 0.02
    uv, closed = _scenario_path_uv(orchard, scenario, duration_s * speed_mps, step)
    seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    d = np.gradient(uv, s, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    curvature = np.abs(np.gradient(heading, s))
    # Smooth the curvature over ~1 m so the speed changes gently into and out of turns.
    kernel = np.ones(max(1, int(1.0 / step)))
    curvature = np.convolve(curvature, kernel / kernel.size, mode='same')
    speed = speed_mps * np.clip(1.0 / (1.0 + 1.2 * curvature), 0.6, 1.0)
    t = np.concatenate([[0.0], np.cumsum(seg / (0.5 * (speed[1:] + speed[:-1])))])
    if not closed and t[-1] < duration_s:
        raise SimulationError(f'scenario {scenario!r} path lasts {t[-1]:.1f} s, '
                              f'{duration_s:.1f} s requested')
    return _with_wobble(orchard, s, uv, heading, t, closed, seed, lateral_wobble_m,
                        yaw_wobble_rad)


def _with_wobble(orchard: Orchard, s: np.ndarray, uv: np.ndarray, heading: np.ndarray,
                 t: np.ndarray, closed: bool, seed: int, lateral_wobble_m: float,
                 yaw_wobble_rad: float) -> RobotMotion:
    """The motion along a tabulated path, with the skid-steer wobble drawn from `seed`."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x40710]))
    return RobotMotion(
        orchard=orchard, s_m=s, uv_m=uv, heading_rad=heading, t_s=t, closed=closed,
        lateral_wobble_m=float(lateral_wobble_m),
        lateral_wobble_wavelength_m=float(rng.uniform(6.0, 12.0)),
        lateral_wobble_phase_rad=float(rng.uniform(0.0, 2.0 * np.pi)),
        yaw_wobble_rad=float(yaw_wobble_rad), yaw_wobble_hz=float(rng.uniform(0.2, 0.5)),
        yaw_wobble_phase_rad=float(rng.uniform(0.0, 2.0 * np.pi)))


# --- CitrusFarm-like routes over many lanes, driven with a varied speed profile ---------------

ROUTES = ('lawnmower', 'every_other_row', 'spiral', 'out_and_back', 'edge_lawnmower')
# edge_lawnmower leaves the block at its edge: a fast lawn-mower that starts on the track
# outside the outermost row (trees on one side, open ground on the other; lane EDGE_LANE) and
# turns square, on tight corners, far out past the row ends into an open headland (the shed
# and vehicles stand OPEN_HEADLAND_M past the trees instead of HEADLAND_M).
EDGE_ROUTE = 'edge_lawnmower'
EDGE_LANE = -1
EDGE_TURN_CLEARANCE_M = 8.0
OPEN_HEADLAND_M = 30.0
# Its driving replaces the seed's draw: ~1.8 m/s everywhere (headlands too), 0.8 m corners
# taken at up to 2 rad/s. The rest of the draw (acceleration, stops, orchard) is the seed's.
EDGE_DRIVING = {'cruise_speed_mps': 1.8, 'lane_speed_jitter': 0.05, 'max_yaw_rate_rps': 2.0,
                'turn_radius_m': 0.8}
# Headlands of the other routes are driven at most this fast.
HEADLAND_SPEED_MPS = 0.8
# A pivot (turn on the spot) is an arc this tight: the yaw-rate limit then sets a crawl.
PIVOT_RADIUS_M = 0.05
# Sampling of the route path and the slowest the integration of ds / v lets the robot go.
ROUTE_STEP_M = 0.02
_CRAWL_MPS = 0.02


def _straight(p, heading, length_m, step):
    """Samples (uv, heading) of a straight piece of `length_m` from `p` along `heading`."""
    n = max(2, int(np.ceil(length_m / step)) + 1)
    d = np.linspace(0.0, length_m, n)
    uv = np.asarray(p, float) + d[:, None] * np.array([np.cos(heading), np.sin(heading)])
    return uv, np.full(n, heading)


def _turn(p, heading, angle_rad, radius_m, step):
    """Samples of an arc of `radius_m` turning by `angle_rad` (> 0 left) from pose (p, heading)."""
    side = np.sign(angle_rad)
    centre = np.asarray(p, float) + side * radius_m * np.array([-np.sin(heading),
                                                                np.cos(heading)])
    n = max(3, int(np.ceil(abs(angle_rad) * max(radius_m, 0.2) / step)) + 1)
    h = heading + np.linspace(0.0, angle_rad, n)
    # Position on the circle: centre - side r (-sin h, cos h).
    uv = centre - side * radius_m * np.column_stack([-np.sin(h), np.cos(h)])
    return uv, h


def route_lanes(route: str, n_lanes: int) -> list[int]:
    """The order in which `route` drives lanes 0..n_lanes-1 (CitrusFarm's route shapes);
    the edge route's first lane is the edge track, EDGE_LANE, then lanes 0..n_lanes-2."""
    if route == 'lawnmower':
        return list(range(n_lanes))
    if route == EDGE_ROUTE:
        return [EDGE_LANE] + list(range(n_lanes - 1))
    if route == 'every_other_row':
        # Out every other lane, back along the ones skipped.
        out = list(range(0, n_lanes, 2))
        back = [lane for lane in range(n_lanes - 1, -1, -1) if lane % 2 == 1]
        return out + back
    if route == 'spiral':
        # Square spiral: outermost lanes first, closing in on the middle.
        order, lo, hi = [], 0, n_lanes - 1
        while lo <= hi:
            order.append(lo)
            if hi != lo:
                order.append(hi)
            lo, hi = lo + 1, hi - 1
        return order
    if route == 'out_and_back':
        # Each lane out and back again (a pivot at the far end), then the next lane.
        return [lane for lane in range(n_lanes) for _ in (0, 1)]
    raise SimulationError(f'unknown route {route!r}; choose one of {ROUTES}')


def route_turn_clearance_m(route: str) -> float:
    """How far past the last trunk `route` drives into the headland before it turns."""
    return EDGE_TURN_CLEARANCE_M if route == EDGE_ROUTE else TURN_CLEARANCE_M


def route_headland_m(route: str) -> float:
    """Distance from the outermost trees to the row-end objects in the orchard of `route`."""
    return OPEN_HEADLAND_M if route == EDGE_ROUTE else HEADLAND_M


def route_driving(route: str, variation: OrchardVariation) -> OrchardVariation:
    """The driving `route` is simulated with: the seed's draw, the edge route's fast tight
    turns in place of its speeds and turns."""
    return replace(variation, **EDGE_DRIVING) if route == EDGE_ROUTE else variation


def route_lane_count(route: str, distance_m: float, row_length_m: float) -> int:
    """Lanes a route needs for about `distance_m` with rows `row_length_m` long (>= 2)."""
    per_lane = row_length_m + 2.0 * route_turn_clearance_m(route) + 4.0
    passes = max(2, int(np.ceil(distance_m / per_lane)))
    return int(np.ceil(passes / 2)) if route == 'out_and_back' else passes


def _route_path(orchard: Orchard, lanes: list[int], turn_radius_m: float,
                turn_clearance_m: float, step: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Route path in the row frame: (uv, heading, lane index per sample, -1 in headlands)."""
    u0, u1 = orchard.row_start_u_m, orchard.row_end_u_m
    v = [orchard.edge_lane_v_m if lane == EDGE_LANE else orchard.lane_v_m(lane)
         for lane in lanes]
    pieces_uv, pieces_h, pieces_lane = [], [], []

    def add(piece, lane_index):
        uv, h = piece
        if pieces_uv:
            uv, h = uv[1:], h[1:]
        pieces_uv.append(uv)
        pieces_h.append(h)
        pieces_lane.append(np.full(len(h), lane_index))

    heading = 0.0
    add(_straight((u0 - 1.0, v[0]), heading, u1 - u0 + 1.0, step), 0)
    for i in range(1, len(lanes)):
        p = pieces_uv[-1][-1]
        dv = v[i] - v[i - 1]
        # Turn towards the next lane: left when it lies to the left of the heading.
        side = np.sign(np.cos(heading) * dv) if abs(dv) > 1e-9 else 1.0
        radius = PIVOT_RADIUS_M if abs(dv) < 1e-9 else float(
            np.clip(turn_radius_m, PIVOT_RADIUS_M, 0.5 * abs(dv)))
        over = turn_clearance_m - radius
        if abs(dv) < 1e-9:
            # Out and back: drive into the headland, pivot half a turn, come back.
            add(_straight(p, heading, turn_clearance_m, step), -1)
            p = pieces_uv[-1][-1]
            add(_turn(p, heading, side * np.pi, radius, step), -1)
            heading += side * np.pi
            p = pieces_uv[-1][-1]
            add(_straight(p, heading, turn_clearance_m, step), -1)
        else:
            add(_straight(p, heading, over, step), -1)
            for _ in range(2):
                p = pieces_uv[-1][-1]
                add(_turn(p, heading, side * 0.5 * np.pi, radius, step), -1)
                heading += side * 0.5 * np.pi
                if _ == 0:
                    p = pieces_uv[-1][-1]
                    add(_straight(p, heading, abs(dv) - 2.0 * radius, step), -1)
            p = pieces_uv[-1][-1]
            add(_straight(p, heading, over, step), -1)
        p = pieces_uv[-1][-1]
        add(_straight(p, heading, u1 - u0, step), i)
    uv = np.concatenate(pieces_uv)
    return uv, np.unwrap(np.concatenate(pieces_h)), np.concatenate(pieces_lane)


def _speed_profile(s: np.ndarray, curvature: np.ndarray, lane_of_sample: np.ndarray,
                   variation: OrchardVariation, headland_mps: float, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Speed at every path sample: per-lane cruise, `headland_mps` in the headlands, yaw-rate
    and acceleration limits, stops from rest to rest. Returns (speed, stop sample indices,
    stop durations)."""
    n_lanes = int(lane_of_sample.max()) + 1
    jitter = 1.0 + variation.lane_speed_jitter * rng.uniform(-1.0, 1.0, n_lanes)
    # A stress drive's robot is faster than the Jackal: its own cruise speed is its cap.
    cruise = np.clip(variation.cruise_speed_mps * jitter, MIN_CRUISE_MPS,
                     max(MAX_SPEED_MPS, variation.cruise_speed_mps))
    speed = np.where(lane_of_sample >= 0, cruise[np.maximum(lane_of_sample, 0)], headland_mps)
    speed = np.minimum(speed, variation.max_yaw_rate_rps / np.maximum(curvature, 1e-9))
    n_stops = rng.poisson(variation.stops_per_100m * s[-1] / 100.0)
    stops = np.sort(np.searchsorted(s, rng.uniform(0.05, 0.95, n_stops) * s[-1]))
    durations = rng.uniform(1.0, variation.stop_duration_s, stops.size)
    speed[stops] = 0.0
    speed[0] = speed[-1] = 0.0
    ds = np.diff(s)
    two_a = 2.0 * variation.max_accel_mps2
    for i in range(1, s.size):  # accelerate no faster than max_accel (forward pass)
        speed[i] = min(speed[i], np.sqrt(speed[i - 1] ** 2 + two_a * ds[i - 1]))
    for i in range(s.size - 2, -1, -1):  # and brake no harder (backward pass)
        speed[i] = min(speed[i], np.sqrt(speed[i + 1] ** 2 + two_a * ds[i]))
    return speed, stops, durations


def make_route_motion(orchard: Orchard, route: str, n_lanes: int,
                      variation: OrchardVariation, seed: int = 0,
                      lateral_wobble_m: float = 0.05,
                      yaw_wobble_rad: float = 0.02) -> RobotMotion:
    """Drive `route` over `n_lanes` lanes of `orchard` with the speeds of `variation`
    (`route_driving` gives the edge route's).

    The drive starts and ends at rest; stops hold the robot still for a few seconds.
    """
    lanes = route_lanes(route, n_lanes)
    if max(lanes) > len(orchard.row_v_m) - 2:
        raise SimulationError(f'route {route!r} needs {max(lanes) + 2} rows, the orchard has '
                              f'{len(orchard.row_v_m)}')
    uv, heading, lane_of_sample = _route_path(orchard, lanes, variation.turn_radius_m,
                                              route_turn_clearance_m(route), ROUTE_STEP_M)
    seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
    # A pivot arc is shorter than its samples' spacing suggests; keep s strictly increasing.
    seg = np.maximum(seg, 1e-4)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    curvature = np.abs(np.gradient(heading, s))
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x40711]))
    # The edge route keeps its speed through the open headland; the others slow down there.
    headland_mps = variation.cruise_speed_mps if route == EDGE_ROUTE else min(
        variation.cruise_speed_mps, HEADLAND_SPEED_MPS)
    speed, stops, durations = _speed_profile(s, curvature, lane_of_sample, variation,
                                             headland_mps, rng)
    v_mid = np.maximum(0.5 * (speed[1:] + speed[:-1]), _CRAWL_MPS)
    t = np.concatenate([[0.0], np.cumsum(seg / v_mid)])
    # A stop: the same sample twice, `duration` apart (t stays strictly increasing).
    if stops.size:
        keep_order = np.argsort(np.concatenate([np.arange(s.size), stops]), kind='stable')
        dwell = np.zeros(s.size + stops.size)
        position = np.empty_like(keep_order)
        position[keep_order] = np.arange(keep_order.size)
        dwell[position[s.size + np.arange(stops.size)]] = durations
        s = np.concatenate([s, s[stops]])[keep_order]
        uv = np.concatenate([uv, uv[stops]])[keep_order]
        heading = np.concatenate([heading, heading[stops]])[keep_order]
        t = np.concatenate([t, t[stops]])[keep_order] + np.cumsum(dwell)
    return _with_wobble(orchard, s, uv, heading, t, False, seed, lateral_wobble_m,
                        yaw_wobble_rad)
