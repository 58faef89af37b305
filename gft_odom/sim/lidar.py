"""Velodyne VLP-16 model and vectorised ray casting against the orchard.

Rays are cast in batches (no Python loop per ray or per point). Primitives are culled first by
range, then per ray by azimuth (rays sorted by world azimuth, each primitive's bounding sphere
gives an azimuth window found with `searchsorted`) and by elevation; only the surviving
(ray, primitive) pairs are intersected exactly. The ground heightfield is intersected by
marching each downward-enough ray over geometrically spaced samples, then bisection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gft_odom.sim.orchard import CANOPY, GROUND, Orchard

# Laser firing order of the VLP-16 (laser id -> elevation); ring = elevation order, ring 0 at
# -15 deg. Lasers fire 2.304 us apart within a 55.296 us firing cycle.
VLP16_FIRING_ELEVATIONS_DEG = (-15.0, 1.0, -13.0, 3.0, -11.0, 5.0, -9.0, 7.0,
                               -7.0, 9.0, -5.0, 11.0, -3.0, 13.0, -1.0, 15.0)
VLP16_LASER_SPACING_S = 2.304e-6

# Reflectivity (0..255, the VLP-16's calibrated intensity scale) per surface code: dry soil,
# bark, leaves, galvanised steel post, black PE drip line, painted shed wall, car paint.
SURFACE_REFLECTIVITY = np.array([22.0, 35.0, 60.0, 120.0, 8.0, 90.0, 150.0])


@dataclass(frozen=True)
class Vlp16Model:
    """Geometry and timing of one VLP-16 sweep.

    The head spins clockwise seen from above (azimuth in the ROS sensor frame decreases with
    time); a sweep starts facing backwards (azimuth pi), so the cut lies behind the robot.
    `azimuth_step_deg` 0.2 at 10 Hz is the real sensor; a coarser step makes test scans cheap.
    """

    azimuth_step_deg: float = 0.2
    rate_hz: float = 10.0
    min_range_m: float = 0.4
    max_range_m: float = 100.0

    @property
    def n_columns(self) -> int:
        """Firing columns in one sweep (360 deg / azimuth step)."""
        return int(round(360.0 / self.azimuth_step_deg))

    @property
    def period_s(self) -> float:
        """Duration of one sweep."""
        return 1.0 / self.rate_hz

    def ray_table(self) -> dict[str, np.ndarray]:
        """All rays of one sweep in firing order (column by column, lasers in firing order).

        Returns `direction` (R, 3) unit vectors in the sensor frame, `ring` (R,) uint16,
        `column` (R,) int, `time_offset_s` (R,) from the sweep start.
        """
        n_col = self.n_columns
        elev_fire = np.deg2rad(np.array(VLP16_FIRING_ELEVATIONS_DEG))
        ring_fire = np.round((np.array(VLP16_FIRING_ELEVATIONS_DEG) + 15.0) / 2.0)
        column = np.repeat(np.arange(n_col), 16)
        laser = np.tile(np.arange(16), n_col)
        azimuth = np.pi - 2.0 * np.pi * column / n_col
        elev = elev_fire[laser]
        direction = np.column_stack([np.cos(elev) * np.cos(azimuth),
                                     np.cos(elev) * np.sin(azimuth), np.sin(elev)])
        time_offset = column * (self.period_s / n_col) + laser * VLP16_LASER_SPACING_S
        return {'direction': direction, 'ring': ring_fire[laser].astype(np.uint16),
                'column': column, 'time_offset_s': time_offset}


@dataclass
class RayHits:
    """First hit per ray: distance along the ray (inf = no return), surface code, primitive
    index within its kind (-1 for ground / no hit), |cos| of the incidence angle."""

    range_m: np.ndarray
    surface: np.ndarray
    primitive: np.ndarray
    cos_incidence: np.ndarray


def _pairs_by_azimuth(directions: np.ndarray, centre: np.ndarray, radius: np.ndarray,
                      ref_origin: np.ndarray, max_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (ray, primitive) pairs whose azimuth/elevation windows overlap the primitive's
    bounding sphere as seen from `ref_origin` (`radius` already includes origin motion)."""
    rel = centre - ref_origin
    dist = np.linalg.norm(rel, axis=1)
    keep = np.nonzero(dist - radius <= max_range_m)[0]
    if keep.size == 0 or directions.shape[0] == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    rel, dist, radius = rel[keep], dist[keep], radius[keep]
    horiz = np.hypot(rel[:, 0], rel[:, 1])
    inside = horiz <= radius
    half = np.where(inside, np.pi, np.arcsin(np.clip(radius / np.maximum(horiz, 1e-9), 0, 1)))
    centre_az = np.arctan2(rel[:, 1], rel[:, 0])

    ray_az = np.arctan2(directions[:, 1], directions[:, 0])
    order = np.argsort(ray_az, kind='stable')
    az_sorted = ray_az[order]
    n = order.size
    az_ext = np.concatenate([az_sorted, az_sorted + 2.0 * np.pi])
    order_ext = np.concatenate([order, order])
    lo_az = np.mod(centre_az - half + np.pi, 2.0 * np.pi) - np.pi
    lo = np.searchsorted(az_ext, lo_az, side='left')
    hi = np.searchsorted(az_ext, lo_az + 2.0 * half, side='right')
    lo = np.where(inside, 0, lo)
    hi = np.where(inside, n, np.minimum(hi, lo + n))
    counts = hi - lo
    total = int(counts.sum())
    prim = np.repeat(np.arange(keep.size), counts)
    start = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    ray = order_ext[start + np.arange(total)]

    # Elevation window of the sphere, per pair.
    el_c = np.arctan2(rel[:, 2], horiz)
    el_half = np.where(dist <= radius, np.pi,
                       np.arcsin(np.clip(radius / np.maximum(dist, 1e-9), 0, 1)))
    ray_el = np.arcsin(np.clip(directions[:, 2], -1.0, 1.0))
    ok = np.abs(ray_el[ray] - el_c[prim]) <= el_half[prim]
    return ray[ok], keep[prim[ok]]


def _hit_cylinders(o, d, base, axis, length, radius):
    """Entry distance into finite uncapped cylinders (inf if missed) and |cos incidence|."""
    w = o - base
    da = np.einsum('ij,ij->i', d, axis)
    wa = np.einsum('ij,ij->i', w, axis)
    dp = d - da[:, None] * axis
    wp = w - wa[:, None] * axis
    a = np.einsum('ij,ij->i', dp, dp)
    b = 2.0 * np.einsum('ij,ij->i', wp, dp)
    c = np.einsum('ij,ij->i', wp, wp) - radius ** 2
    disc = b * b - 4.0 * a * c
    ok = (disc > 0.0) & (a > 1e-12)
    sq = np.sqrt(np.where(ok, disc, 0.0))
    t = (-b - sq) / (2.0 * np.where(ok, a, 1.0))
    h = wa + t * da
    ok &= (t > 0.0) & (h >= 0.0) & (h <= length)
    normal = (wp + t[:, None] * dp) / radius[:, None]
    cos = np.abs(np.einsum('ij,ij->i', normal, d))
    return np.where(ok, t, np.inf), cos


def _hit_boxes(o, d, centre, half, yaw):
    """Entry distance into yawed boxes (inf if missed) and |cos incidence|."""
    c, s = np.cos(yaw), np.sin(yaw)
    rel = o - centre
    ol = np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                          rel[:, 2]])
    dl = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = 1.0 / dl
        t1 = (-half - ol) * inv
        t2 = (half - ol) * inv
    tmin = np.fmin(t1, t2)
    tmax = np.fmax(t1, t2)
    t_in = np.nanmax(tmin, axis=1)
    t_out = np.nanmin(tmax, axis=1)
    ok = (t_in <= t_out) & (t_in > 0.0)
    face = np.nanargmax(tmin, axis=1)
    cos = np.abs(dl[np.arange(dl.shape[0]), face])
    return np.where(ok, t_in, np.inf), cos


def _hit_canopies(o, d, centre, radii, rotation_2d, mean_free_path_m, rng):
    """Porous ellipsoids: a ray that enters travels an exponential depth (mean free path) and
    stops there if that is before it leaves; otherwise it passes through."""
    rel = o - centre
    r2 = rotation_2d  # row frame -> world; its transpose maps world -> row frame
    ol = np.column_stack([r2[0, 0] * rel[:, 0] + r2[1, 0] * rel[:, 1],
                          r2[0, 1] * rel[:, 0] + r2[1, 1] * rel[:, 1], rel[:, 2]]) / radii
    dl = np.column_stack([r2[0, 0] * d[:, 0] + r2[1, 0] * d[:, 1],
                          r2[0, 1] * d[:, 0] + r2[1, 1] * d[:, 1], d[:, 2]]) / radii
    a = np.einsum('ij,ij->i', dl, dl)
    b = 2.0 * np.einsum('ij,ij->i', ol, dl)
    c = np.einsum('ij,ij->i', ol, ol) - 1.0
    disc = b * b - 4.0 * a * c
    ok = disc > 0.0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    t_in = np.maximum((-b - sq) / (2.0 * a), 0.0)
    t_out = (-b + sq) / (2.0 * a)
    ok &= t_out > 0.0
    depth = rng.exponential(mean_free_path_m, size=t_in.size)
    ok &= depth < (t_out - t_in)
    # Leaves face every way: the incidence cosine is that of a random orientation.
    cos = rng.uniform(0.0, 1.0, size=t_in.size)
    return np.where(ok, t_in + depth, np.inf), cos


# Annuli (horizontal distance from the scan centre) over which ground-height bounds are kept.
_ANNULI_M = np.array([3.0, 6.0, 10.0, 15.0, 22.0, 32.0, 45.0, 65.0, 90.0, 130.0, 1e9])


def _hit_ground(o, d, ground, t_min, t_max, min_step_m=0.02, min_step_fraction=0.005):
    """Distance to the heightfield along each ray (inf if none within t_max).

    Around the scan the ground is a least-squares plane plus a residual whose bound r(rho)
    grows with the horizontal distance rho (per-block max/min heights); a ray can only meet
    the ground where it is within r(rho) of that plane, which gives each ray a window (most
    upward rays have none). Inside the window each ray is sphere-traced with the ground's
    slope bound, with steps of at least `min_step_m` and `min_step_fraction` of the distance
    (grazing rays creep otherwise; so they may skip a bump thinner than 0.5 % of the range),
    then the crossing is refined by bisection to well under a millimetre.
    """
    n = o.shape[0]
    t_hit = np.full(n, np.inf)
    if n == 0:
        return t_hit
    centre = o.mean(axis=0)
    spread = float(np.linalg.norm(o[:, :2] - centre[:2], axis=1).max())
    # Local plane z = c0 + c1 (x - cx) + c2 (y - cy), fitted within 30 m.
    fit_r = min(30.0, t_max)
    g = np.linspace(-fit_r, fit_r, 25)
    gx, gy = np.meshgrid(centre[0] + g, centre[1] + g, indexing='ij')
    inside = (gx - centre[0]) ** 2 + (gy - centre[1]) ** 2 <= fit_r ** 2
    gx, gy = gx[inside], gy[inside]
    gz = ground.height(gx, gy)
    A = np.column_stack([np.ones_like(gx), gx - centre[0], gy - centre[1]])
    coef = np.linalg.lstsq(A, gz, rcond=None)[0]

    # Residual bound per annulus, from the blocks (the plane's extremes over each block).
    block_m, zmax, zmin = ground.blocks
    bx = ground.origin_xy_m[0] + block_m * np.arange(zmax.shape[0]) - centre[0]
    by = ground.origin_xy_m[1] + block_m * np.arange(zmax.shape[1]) - centre[1]
    near_x = (bx >= -t_max - block_m) & (bx <= t_max)
    near_y = (by >= -t_max - block_m) & (by <= t_max)
    bx, by = bx[near_x], by[near_y]
    zmax, zmin = zmax[near_x][:, near_y], zmin[near_x][:, near_y]
    plane_lo = coef[0] + np.minimum(coef[1] * bx, coef[1] * (bx + block_m))[:, None] + \
        np.minimum(coef[2] * by, coef[2] * (by + block_m))[None, :]
    plane_hi = coef[0] + np.maximum(coef[1] * bx, coef[1] * (bx + block_m))[:, None] + \
        np.maximum(coef[2] * by, coef[2] * (by + block_m))[None, :]
    resid = np.maximum(zmax - plane_lo, plane_hi - zmin).reshape(-1) + 0.01
    # Nearest distance from the centre to each block.
    dx = np.maximum(np.maximum(bx, -(bx + block_m)), 0.0)
    dy = np.maximum(np.maximum(by, -(by + block_m)), 0.0)
    block_rho = np.hypot(dx[:, None], dy[None, :]).reshape(-1)
    level = np.searchsorted(_ANNULI_M, block_rho - spread)
    r_level = np.zeros(_ANNULI_M.size)
    if resid.size:
        np.maximum.at(r_level, level, resid)
    r_cum = np.maximum.accumulate(r_level)  # bound over the whole disc up to each annulus

    # Ray height above the plane: a + b t; horizontal distance ~ h t.
    a = o[:, 2] - (coef[0] + coef[1] * (o[:, 0] - centre[0]) + coef[2] * (o[:, 1] - centre[1]))
    b = d[:, 2] - coef[1] * d[:, 0] - coef[2] * d[:, 1]
    h = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-6)
    edges = np.concatenate([[0.0], _ANNULI_M])
    t0 = np.maximum(edges[None, :-1] / h[:, None], t_min)  # (R, J)
    t1 = np.minimum(edges[None, 1:] / h[:, None], t_max)
    z0 = a[:, None] + b[:, None] * t0
    z1 = a[:, None] + b[:, None] * t1
    possible = (t0 < t1) & (np.minimum(z0, z1) <= r_cum[None, :])
    with np.errstate(divide='ignore', invalid='ignore'):
        t_cross = np.where(b[:, None] < 0.0, (a[:, None] - r_cum[None, :]) / -b[:, None], t0)
    t_in = np.where(possible, np.clip(t_cross, t0, t1), np.inf).min(axis=1)
    t_end = np.where(possible, t1, -np.inf).max(axis=1)
    # Rays going down relative to the plane march on to t_max (the bound may not hold beyond
    # the heightfield); the others stop where their window ends.
    t_end = np.where(b < 0.0, t_max, t_end)
    cand = np.nonzero(np.isfinite(t_in))[0]
    if cand.size == 0:
        return t_hit
    oc, dc = o[cand], d[cand]
    t_end = t_end[cand]
    # Sphere tracing on a heightfield: with the ground's slope bounded by L, a ray delta above
    # the ground at horizontal speed h cannot reach it within delta / (max(-dz, 0) + L h).
    closing = np.maximum(-dc[:, 2], 0.0) + ground.max_slope * h[cand] + 1e-9
    t_cur = t_in[cand].copy()
    t_prev = t_cur.copy()
    found = np.zeros(cand.size, bool)
    t_lo = np.zeros(cand.size)
    t_hi = np.zeros(cand.size)
    active = np.arange(cand.size)
    while active.size:  # each round vectorised over the rays still marching
        t = t_cur[active]
        p = oc[active] + t[:, None] * dc[active]
        delta = p[:, 2] - ground.height(p[:, 0], p[:, 1])
        below = delta <= 0.0
        hit = active[below]
        found[hit] = True
        t_lo[hit] = t_prev[hit]
        t_hi[hit] = t[below]
        more = ~below & (t < t_end[active])
        go = active[more]
        t_prev[go] = t[more]
        step = np.maximum(delta[more] / closing[go],
                          np.maximum(min_step_m, min_step_fraction * t[more]))
        t_cur[go] = np.minimum(t[more] + step,
                               t_end[go])
        active = go
    idx = np.nonzero(found)[0]
    lo, hi = t_lo[idx], t_hi[idx]
    oa, da = oc[idx], dc[idx]
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        p = oa + mid[:, None] * da
        below = p[:, 2] <= ground.height(p[:, 0], p[:, 1])
        hi = np.where(below, mid, hi)
        lo = np.where(below, lo, mid)
    t_hit[cand[idx]] = 0.5 * (lo + hi)
    return t_hit


def cast_rays(orchard: Orchard, origins: np.ndarray, directions: np.ndarray,
              times_s: np.ndarray, rng: np.random.Generator, *, max_range_m: float = 100.0,
              min_range_m: float = 0.4, canopy_mean_free_path_m: float = 0.35,
              wind_amplitude_m: float = 0.0) -> RayHits:
    """First surface hit by each ray `origins[i] + t directions[i]` (world frame, unit dirs).

    `times_s` (seconds from the start of the run) drive the canopy sway.
    """
    n = origins.shape[0]
    best_t = _hit_ground(origins, directions, orchard.ground, min_range_m, max_range_m)
    best_surface = np.full(n, GROUND, np.int8)
    best_prim = np.full(n, -1, np.int32)
    ref = origins.mean(axis=0) if n else np.zeros(3)
    spread = float(np.linalg.norm(origins - ref, axis=1).max()) if n else 0.0

    # Candidate hits per primitive kind: (ray, t, surface, primitive, cos incidence).
    candidates: list[tuple[np.ndarray, ...]] = []

    cyl = orchard.cylinders
    if len(cyl):
        half = 0.5 * cyl.length_m
        ray, prim = _pairs_by_azimuth(directions, cyl.base_m + cyl.axis * half[:, None],
                                      np.hypot(half, cyl.radius_m) + spread, ref, max_range_m)
        t, cos = _hit_cylinders(origins[ray], directions[ray], cyl.base_m[prim], cyl.axis[prim],
                                cyl.length_m[prim], cyl.radius_m[prim])
        candidates.append((ray, t, cyl.surface[prim], prim, cos))

    can = orchard.canopies
    if len(can):
        sway = wind_amplitude_m * can.sway_amplitude
        ray, prim = _pairs_by_azimuth(directions, can.centre_m,
                                      can.radii_m.max(axis=1) + sway + spread, ref, max_range_m)
        tt = times_s[ray]
        amp = sway[prim]
        off_u = amp * np.sin(2.0 * np.pi * can.sway_frequency_hz[prim, 0] * tt
                             + can.sway_phase_rad[prim, 0])
        off_v = amp * np.sin(2.0 * np.pi * can.sway_frequency_hz[prim, 1] * tt
                             + can.sway_phase_rad[prim, 1])
        r2 = orchard.rotation_2d
        centre = can.centre_m[prim].copy()
        centre[:, 0] += r2[0, 0] * off_u + r2[0, 1] * off_v
        centre[:, 1] += r2[1, 0] * off_u + r2[1, 1] * off_v
        t, cos = _hit_canopies(origins[ray], directions[ray], centre, can.radii_m[prim], r2,
                               canopy_mean_free_path_m, rng)
        candidates.append((ray, t, np.full(ray.size, CANOPY, np.int8), prim, cos))

    box = orchard.boxes
    if len(box):
        ray, prim = _pairs_by_azimuth(directions, box.centre_m,
                                      np.linalg.norm(box.half_extent_m, axis=1) + spread, ref,
                                      max_range_m)
        t, cos = _hit_boxes(origins[ray], directions[ray], box.centre_m[prim],
                            box.half_extent_m[prim], box.yaw_rad[prim])
        candidates.append((ray, t, box.surface[prim], prim, cos))

    if candidates:
        ray, t, surface, prim, cos = (np.concatenate(column) for column in zip(*candidates))
        hit = np.isfinite(t)
        ray, t, surface, prim, cos = ray[hit], t[hit], surface[hit], prim[hit], cos[hit]
        np.minimum.at(best_t, ray, t)
        win = t == best_t[ray]
        best_surface[ray[win]] = surface[win]
        best_prim[ray[win]] = prim[win]
        cos_best = np.zeros(n)
        cos_best[ray[win]] = cos[win]
    else:
        cos_best = np.zeros(n)

    ground_hit = (best_surface == GROUND) & np.isfinite(best_t)
    if ground_hit.any():
        p = origins[ground_hit] + best_t[ground_hit, None] * directions[ground_hit]
        gx, gy = orchard.ground.gradient(p[:, 0], p[:, 1])
        normal = np.column_stack([-gx, -gy, np.ones_like(gx)])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        cos_best[ground_hit] = np.abs(np.einsum('ij,ij->i', normal, directions[ground_hit]))
    best_t[best_t > max_range_m] = np.inf
    best_surface[~np.isfinite(best_t)] = -1
    best_prim[~np.isfinite(best_t)] = -1
    return RayHits(best_t, best_surface, best_prim, cos_best)

