"""A synthetic citrus orchard as arrays of primitives, generated from a seed.

The scene is what the VLP-16 model casts rays against: a ground heightfield, finite cylinders
(trunks, posts, irrigation pipes), porous ellipsoid canopies that sway in the wind, and boxes
(a building, parked vehicles) at the row ends. Rows are laid out in a row frame (u along the
rows, v across them) and placed in the world (the "orchard" frame) with a seed-dependent
heading and offset, so the world axes are not aligned with the rows.

Ranges follow the project issue: rows 5.5-7 m apart, trees 3-5 m apart in a row with jitter and
~10 % missing, trunks r 0.06-0.15 m and 0.4-0.9 m tall with a slight lean, canopies with
horizontal radii 1.2-2.2 m and vertical radii 1.0-2.0 m skirting low over the trunks.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.ndimage import gaussian_filter

from gft_odom.errors import SimulationError
from gft_odom.sim.variation import OrchardVariation

# Surface codes, one per kind of primitive (also the `label` of simulated points).
GROUND = 0
TRUNK = 1
CANOPY = 2
POST = 3
PIPE = 4
BUILDING = 5
VEHICLE = 6
SURFACE_NAMES = ('ground', 'trunk', 'canopy', 'post', 'pipe', 'building', 'vehicle')

# Headland from the outermost trees to the row-end objects: room for the robot to turn.
HEADLAND_M = 9.0
# Wheel ruts along the lanes (varied simulator only): offset from the lane centre, width.
RUT_OFFSET_M = 0.19
RUT_WIDTH_M = 0.12


@dataclass(frozen=True)
class Heightfield:
    """Ground height z(x, y) on a regular world grid, bilinear in between, clamped outside."""

    origin_xy_m: np.ndarray  # (2,) world x, y of cell (0, 0)
    resolution_m: float
    z_m: np.ndarray  # (nx, ny) float64

    def _corners(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """Cell fractions fx, fy and the heights z00, z01, z10, z11 of the cell's corners."""
        fx, fy, flat = self._cell(x, y)
        z = self.z_m.reshape(-1)
        ny = self.z_m.shape[1]
        return fx, fy, z[flat], z[flat + 1], z[flat + ny], z[flat + ny + 1]

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height at world points (any matching shapes)."""
        fx, fy, z00, z01, z10, z11 = self._corners(x, y)
        return z00 + fx * (z10 - z00) + fy * (z01 - z00 + fx * (z11 - z10 - z01 + z00))

    def gradient(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """dz/dx and dz/dy of the bilinear surface at world points."""
        fx, fy, z00, z01, z10, z11 = self._corners(x, y)
        dzdx = ((z10 - z00) * (1.0 - fy) + (z11 - z01) * fy) / self.resolution_m
        dzdy = ((z01 - z00) * (1.0 - fx) + (z11 - z10) * fx) / self.resolution_m
        return dzdx, dzdy

    @cached_property
    def max_slope(self) -> float:
        """Lipschitz bound of the bilinear surface: |grad z| never exceeds this."""
        dx = np.abs(np.diff(self.z_m, axis=0))
        dy = np.abs(np.diff(self.z_m, axis=1))
        if dx.shape[0] == 0 or dy.shape[1] == 0:
            return 0.0
        # Inside a cell |dz/dx| is at most its larger x-edge difference, likewise for y.
        cell_dx = np.maximum(dx[:, :-1], dx[:, 1:])
        cell_dy = np.maximum(dy[:-1, :], dy[1:, :])
        return float(np.hypot(cell_dx, cell_dy).max() / self.resolution_m)

    @cached_property
    def blocks(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(block size m, max z, min z) over blocks of 16 x 16 cells: cheap local bounds."""
        k = 16
        nx, ny = self.z_m.shape
        px, py = (-nx) % k, (-ny) % k
        z = np.pad(self.z_m, ((0, px), (0, py)), mode='edge')
        z = z.reshape(z.shape[0] // k, k, z.shape[1] // k, k)
        return k * self.resolution_m, z.max(axis=(1, 3)), z.min(axis=(1, 3))

    def _cell(self, x, y):
        nx, ny = self.z_m.shape
        gx = np.clip((np.asarray(x, dtype=float) - self.origin_xy_m[0]) / self.resolution_m,
                     0.0, nx - 1.000001)
        gy = np.clip((np.asarray(y, dtype=float) - self.origin_xy_m[1]) / self.resolution_m,
                     0.0, ny - 1.000001)
        ix = gx.astype(np.intp)
        iy = gy.astype(np.intp)
        return gx - ix, gy - iy, ix * ny + iy


@dataclass(frozen=True)
class Cylinders:
    """Finite cylinders without caps: base point, unit axis, length along the axis, radius."""

    base_m: np.ndarray  # (M, 3)
    axis: np.ndarray  # (M, 3) unit
    length_m: np.ndarray  # (M,)
    radius_m: np.ndarray  # (M,)
    surface: np.ndarray  # (M,) int8: TRUNK, POST or PIPE

    def __len__(self) -> int:
        return int(self.radius_m.shape[0])


@dataclass(frozen=True)
class Canopies:
    """Porous ellipsoids, axes aligned with the rows; centres sway with the wind over time.

    offset(t) = amplitude * (sin(2 pi f_u t + phase_u) along the rows, sin(2 pi f_v t + phase_v)
    across them), horizontal only: a crown bends as a whole in a light wind.
    """

    centre_m: np.ndarray  # (K, 3) at rest
    radii_m: np.ndarray  # (K, 3) along the rows, across the rows, vertical
    sway_amplitude: np.ndarray  # (K,) fraction of the configured wind amplitude, 0.5..1
    sway_frequency_hz: np.ndarray  # (K, 2)
    sway_phase_rad: np.ndarray  # (K, 2)

    def __len__(self) -> int:
        return int(self.radii_m.shape[0])


@dataclass(frozen=True)
class Boxes:
    """Boxes standing on the ground, rotated about z: centre, half extents, yaw, surface code."""

    centre_m: np.ndarray  # (B, 3)
    half_extent_m: np.ndarray  # (B, 3)
    yaw_rad: np.ndarray  # (B,)
    surface: np.ndarray  # (B,) int8: BUILDING or VEHICLE

    def __len__(self) -> int:
        return int(self.yaw_rad.shape[0])


@dataclass(frozen=True)
class Orchard:
    """The scene plus the row layout the motion scenarios drive along.

    Row-frame coordinates (u, v) map to the world as xy = origin + R(heading) (u, v).
    Row i has its trunk line at v = row_v_m[i]; trees span u in [row_start_u_m, row_end_u_m].
    """

    seed: int
    heading_rad: float
    origin_xy_m: np.ndarray  # (2,)
    row_v_m: np.ndarray  # (n_rows,)
    row_start_u_m: float
    row_end_u_m: float
    row_spacing_m: float
    tree_spacing_m: float
    ground: Heightfield
    cylinders: Cylinders
    canopies: Canopies
    boxes: Boxes
    trunk_index_of_tree: np.ndarray  # (n_trees,) index into `cylinders`
    canopy_index_of_tree: np.ndarray  # (n_trees,) index into `canopies`

    @property
    def rotation_2d(self) -> np.ndarray:
        """2-D rotation from row-aligned axes to world x, y."""
        c, s = np.cos(self.heading_rad), np.sin(self.heading_rad)
        return np.array([[c, -s], [s, c]])

    def to_world_xy(self, uv: np.ndarray) -> np.ndarray:
        """Row-frame (..., 2) -> world (..., 2)."""
        return np.asarray(uv, dtype=float) @ self.rotation_2d.T + self.origin_xy_m

    @property
    def edge_lane_v_m(self) -> float:
        """v of the track along the outside of row 0, the block's edge: trees on one side,
        open ground on the other (nothing is placed at v < row_v_m[0])."""
        return float(self.row_v_m[0] - 0.5 * self.row_spacing_m)

    def lane_v_m(self, lane: int) -> float:
        """v of the lane between rows `lane` and `lane + 1`."""
        if not 0 <= lane < len(self.row_v_m) - 1:
            raise SimulationError(f'lane {lane} does not exist with {len(self.row_v_m)} rows')
        return float(0.5 * (self.row_v_m[lane] + self.row_v_m[lane + 1]))


def _smooth_noise(rng: np.random.Generator, shape, sigma_cells: float) -> np.ndarray:
    """Zero-mean, unit-std Gaussian random field with correlation length ~sigma_cells."""
    field = gaussian_filter(rng.standard_normal(shape), sigma_cells, mode='wrap')
    return (field - field.mean()) / max(field.std(), 1e-12)


def _make_ground(rng: np.random.Generator, lo_xy: np.ndarray, hi_xy: np.ndarray,
                 resolution_m: float, variation: OrchardVariation | None = None) -> Heightfield:
    """Gentle slope + slow undulation (tens of cm over tens of m) + bumps (a few cm) +
    roughness (about a centimetre); `variation` sets the slope and the three amplitudes."""
    n = np.ceil((hi_xy - lo_xy) / resolution_m).astype(int) + 2
    xs = lo_xy[0] + resolution_m * np.arange(n[0])
    ys = lo_xy[1] + resolution_m * np.arange(n[1])
    slope_dir = rng.uniform(0.0, 2.0 * np.pi)
    slope = rng.uniform(0.005, 0.025)  # 0.5-2.5 %
    undulation_m, bump_m, roughness_m = 0.25, 0.04, 0.01
    if variation is not None:
        slope = variation.slope
        undulation_m, bump_m = variation.undulation_std_m, variation.bump_std_m
        roughness_m = variation.roughness_std_m
    gx, gy = slope * np.cos(slope_dir), slope * np.sin(slope_dir)
    xc, yc = 0.5 * (lo_xy + hi_xy)
    z = gx * (xs[:, None] - xc) + gy * (ys[None, :] - yc)
    # Smooth components on coarse grids (cheap), upsampled bilinearly: undulation (0.25 m std
    # over ~12 m) and bumps (4 cm std over ~1.5 m).
    for cell_m, sigma_cells, std_m in ((4.0, 3.0, undulation_m), (0.5, 3.0, bump_m)):
        cn = np.ceil((hi_xy - lo_xy) / cell_m).astype(int) + 2
        coarse = Heightfield(lo_xy.copy(), cell_m,
                             std_m * _smooth_noise(rng, tuple(cn), sigma_cells))
        z = z + coarse.height(xs[:, None], ys[None, :])
    z = z + roughness_m * _smooth_noise(rng, tuple(n), 1.0)  # roughness, ~1 cm
    return Heightfield(np.array([xs[0], ys[0]]), resolution_m, z)


def _add_ruts(ground: Heightfield, rot: np.ndarray, origin: np.ndarray, lane_v: np.ndarray,
              u_lo: float, u_hi: float, depth_m: float) -> Heightfield:
    """Wheel ruts pressed `depth_m` into every lane: two tracks RUT_OFFSET_M either side of
    the lane centre (where the robot's own wheels run), Gaussian profile RUT_WIDTH_M wide.
    The 0.25 m heightfield samples them coarsely: a rut is a shallow trough in the grid."""
    nx, ny = ground.z_m.shape
    xs = ground.origin_xy_m[0] + ground.resolution_m * np.arange(nx)
    ys = ground.origin_xy_m[1] + ground.resolution_m * np.arange(ny)
    gx, gy = np.meshgrid(xs, ys, indexing='ij')
    uv = np.stack([gx - origin[0], gy - origin[1]], axis=-1) @ rot  # world -> row frame
    u, v = uv[..., 0], uv[..., 1]
    # Distance across the lane to the nearest rut (at +-RUT_OFFSET_M of each lane centre).
    nearest_lane = lane_v[np.clip(np.searchsorted(lane_v, v), 0, lane_v.size - 1)]
    other_lane = lane_v[np.clip(np.searchsorted(lane_v, v) - 1, 0, lane_v.size - 1)]
    d_lane = np.minimum(np.abs(v - nearest_lane), np.abs(v - other_lane))
    d_track = np.abs(d_lane - RUT_OFFSET_M)
    along = (u >= u_lo) & (u <= u_hi)
    rut = depth_m * np.exp(-0.5 * (d_track / RUT_WIDTH_M) ** 2) * along
    return Heightfield(ground.origin_xy_m, ground.resolution_m, ground.z_m - rut)


def generate_orchard(seed: int, n_rows: int = 8, row_length_m: float = 60.0,
                     ground_resolution_m: float = 0.25, margin_m: float = 60.0,
                     variation: OrchardVariation | None = None,
                     headland_m: float = HEADLAND_M) -> Orchard:
    """Build an orchard from `seed`: `n_rows` rows of trees about `row_length_m` long.

    `margin_m` is how far the ground extends beyond the row-end objects (the heightfield is
    clamped beyond that, i.e. flat-ish far away). `variation` (see sim/variation.py) replaces
    the fixed ranges with one drawn orchard; without it the orchard is what it always was for
    this seed (the random stream is the same either way). `headland_m` moves the row-end
    objects (shed, vehicles) that far past the outermost trees, to leave an open headland;
    nothing else changes with it (the ground, trees and ruts are those of the same seed).
    """
    if n_rows < 2:
        raise SimulationError(f'n_rows must be >= 2 (a lane needs two rows), got {n_rows}')
    if not row_length_m >= 5.0:
        raise SimulationError(f'row_length_m must be >= 5 m, got {row_length_m}')
    if not ground_resolution_m > 0.0:
        raise SimulationError(f'ground_resolution_m must be > 0, got {ground_resolution_m}')
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x0C17]))

    row_spacing = rng.uniform(5.5, 7.0)
    tree_spacing = rng.uniform(3.0, 5.0)
    missing_fraction = rng.uniform(0.06, 0.14)
    if variation is not None:
        row_spacing, tree_spacing = variation.row_spacing_m, variation.tree_spacing_m
        missing_fraction = variation.missing_fraction
    heading = rng.uniform(-np.pi, np.pi)
    origin = rng.uniform(-40.0, 40.0, size=2)
    rot = np.array([[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]])

    n_per_row = max(2, int(round(row_length_m / tree_spacing)) + 1)
    row_v = row_spacing * np.arange(n_rows)
    u_nominal = tree_spacing * np.arange(n_per_row)
    row_start_u, row_end_u = float(u_nominal[0]), float(u_nominal[-1])

    # Ground covers rows + headlands + margin, in world coordinates.
    corners_uv = np.array([[row_start_u - HEADLAND_M - 12.0, -row_spacing - 12.0],
                           [row_end_u + HEADLAND_M + 12.0, -row_spacing - 12.0],
                           [row_start_u - HEADLAND_M - 12.0, row_v[-1] + row_spacing + 12.0],
                           [row_end_u + HEADLAND_M + 12.0, row_v[-1] + row_spacing + 12.0]])
    corners = corners_uv @ rot.T + origin
    ground = _make_ground(rng, corners.min(axis=0) - margin_m, corners.max(axis=0) + margin_m,
                          ground_resolution_m, variation)
    if variation is not None and variation.rut_depth_m > 0.0:
        ground = _add_ruts(ground, rot, origin, 0.5 * (row_v[1:] + row_v[:-1]),
                           row_start_u - HEADLAND_M, row_end_u + HEADLAND_M,
                           variation.rut_depth_m)

    def world_xy(u, v):
        return np.stack([u, v], axis=-1) @ rot.T + origin

    # Trees: a full grid, jittered, some missing.
    uu, vv = np.meshgrid(u_nominal, row_v, indexing='xy')
    uu = uu.ravel() + rng.normal(0.0, 0.15, uu.size)
    vv = vv.ravel() + rng.normal(0.0, 0.10, vv.size)
    present = rng.random(uu.size) >= missing_fraction
    uu, vv = uu[present], vv[present]
    n_trees = uu.size
    trunk_xy = world_xy(uu, vv)
    trunk_z = ground.height(trunk_xy[:, 0], trunk_xy[:, 1]) - 0.05  # rooted slightly below
    trunk_r = rng.uniform(0.06, 0.15, n_trees)
    trunk_len = rng.uniform(0.4, 0.9, n_trees)
    # Young trees (replanted gaps): a thin, short trunk under a small crown.
    tree_scale = np.ones(n_trees)
    if variation is not None:
        young = rng.random(n_trees) < variation.young_fraction
        tree_scale = np.where(young, rng.uniform(0.3, 0.6, n_trees), 1.0) * \
            variation.canopy_scale
        trunk_r = trunk_r * variation.trunk_radius_scale * np.where(young, 0.5, 1.0)
        trunk_len = trunk_len * np.where(young, 0.7, 1.0)
    lean = np.abs(rng.normal(0.0, np.deg2rad(4.0), n_trees))
    lean_dir = rng.uniform(0.0, 2.0 * np.pi, n_trees)
    trunk_axis = np.stack([np.sin(lean) * np.cos(lean_dir), np.sin(lean) * np.sin(lean_dir),
                           np.cos(lean)], axis=1)
    trunk_base = np.column_stack([trunk_xy, trunk_z])
    trunk_top = trunk_base + trunk_axis * trunk_len[:, None]

    # Canopies skirt low: their bottom sits 0-0.35 m below the trunk top, at least 0.2 m above
    # the ground, so the lower trunk shows and the upper trunk hides inside the crown.
    along = rng.uniform(1.2, 2.2, n_trees) * tree_scale
    across = np.minimum(rng.uniform(1.2, 2.2, n_trees) * tree_scale, 0.5 * row_spacing - 1.0)
    vertical = rng.uniform(1.0, 2.0, n_trees) * tree_scale
    ground_at_tree = trunk_z + 0.05
    bottom = np.maximum(trunk_top[:, 2] - rng.uniform(0.0, 0.35, n_trees), ground_at_tree + 0.2)
    canopy_centre = np.column_stack([trunk_top[:, :2] + rng.normal(0.0, 0.1, (n_trees, 2)),
                                     bottom + vertical])
    canopies = Canopies(
        centre_m=canopy_centre,
        radii_m=np.column_stack([along, across, vertical]),
        sway_amplitude=rng.uniform(0.5, 1.0, n_trees),
        sway_frequency_hz=rng.uniform(0.3, 0.9, (n_trees, 2)),
        sway_phase_rad=rng.uniform(0.0, 2.0 * np.pi, (n_trees, 2)))
    canopy_index_of_tree = np.arange(n_trees)
    if variation is not None and variation.canopy_model != 'ellipsoid':
        # Its own random stream: the rest of the orchard is that of the same seed.
        shape_rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xC4A0]))
        canopies, canopy_index_of_tree = _shaped_canopies(
            canopies, variation.canopy_model, tree_spacing, shape_rng)

    # Row-end posts (both ends of every row), vertical, slightly leaning.
    post_u = np.concatenate([np.full(n_rows, row_start_u - 2.0), np.full(n_rows, row_end_u + 2.0)])
    post_v = np.concatenate([row_v, row_v]) + rng.normal(0.0, 0.05, 2 * n_rows)
    post_xy = world_xy(post_u, post_v)
    n_posts = post_u.size
    post_base = np.column_stack([post_xy, ground.height(post_xy[:, 0], post_xy[:, 1]) - 0.1])
    post_tilt = rng.normal(0.0, np.deg2rad(1.5), (n_posts, 2))
    post_axis = np.column_stack([post_tilt, np.ones(n_posts)])
    post_axis /= np.linalg.norm(post_axis, axis=1, keepdims=True)

    # Irrigation pipes: one drip line per row, 0.35 m beside the trunks, resting on the ground,
    # in straight pieces between stakes every ~2 m (so they follow the ground).
    n_seg = max(1, int(np.ceil((row_end_u - row_start_u + 4.0) / 2.0)))
    knots_u = np.linspace(row_start_u - 2.0, row_end_u + 2.0, n_seg + 1)
    ku, kv = np.meshgrid(knots_u, row_v + 0.35, indexing='xy')
    knots_xy = world_xy(ku, kv)  # (n_rows, n_seg + 1, 2)
    knots_z = ground.height(knots_xy[..., 0], knots_xy[..., 1]) + 0.02
    knots = np.concatenate([knots_xy, knots_z[..., None]], axis=-1)
    seg_a = knots[:, :-1].reshape(-1, 3)
    seg_vec = (knots[:, 1:] - knots[:, :-1]).reshape(-1, 3)
    seg_len = np.linalg.norm(seg_vec, axis=1)

    cylinders = Cylinders(
        base_m=np.concatenate([trunk_base, post_base, seg_a]),
        axis=np.concatenate([trunk_axis, post_axis, seg_vec / seg_len[:, None]]),
        length_m=np.concatenate([trunk_len, rng.uniform(1.5, 2.2, n_posts), seg_len]),
        radius_m=np.concatenate([trunk_r, np.full(n_posts, 0.05), np.full(seg_len.size, 0.02)]),
        surface=np.concatenate([np.full(n_trees, TRUNK), np.full(n_posts, POST),
                                np.full(seg_len.size, PIPE)]).astype(np.int8))

    # Row-end objects beyond the headlands (clear of the turning robot): a packing shed at one
    # end, one or two parked vehicles at the other.
    mid_v = 0.5 * row_v[-1]
    shed_end = rng.integers(2)
    shed_u = (row_start_u - headland_m - 7.0) if shed_end == 0 else (row_end_u + headland_m + 7.0)
    box_uv = [(shed_u, mid_v + rng.uniform(-0.25, 0.25) * row_v[-1])]
    box_half = [(rng.uniform(2.0, 3.0), rng.uniform(3.0, 5.0), rng.uniform(1.5, 2.2))]
    box_yaw = [heading + rng.normal(0.0, 0.05)]
    box_surface = [BUILDING]
    vehicle_u = (row_end_u + headland_m + 6.5) if shed_end == 0 else (row_start_u - headland_m
                                                                         - 6.5)
    for _ in range(int(rng.integers(1, 3))):
        box_uv.append((vehicle_u + rng.normal(0.0, 0.5), rng.uniform(0.0, row_v[-1])))
        box_half.append((rng.uniform(0.9, 1.1), rng.uniform(2.0, 2.5), rng.uniform(0.7, 0.9)))
        box_yaw.append(heading + rng.normal(0.0, 0.2))
        box_surface.append(VEHICLE)
    box_uv = np.array(box_uv)
    box_xy = world_xy(box_uv[:, 0], box_uv[:, 1])
    box_half = np.array(box_half)
    box_z = ground.height(box_xy[:, 0], box_xy[:, 1]) - 0.1 + box_half[:, 2]
    boxes = Boxes(np.column_stack([box_xy, box_z]), box_half, np.array(box_yaw),
                  np.array(box_surface, dtype=np.int8))

    return Orchard(
        seed=int(seed), heading_rad=float(heading), origin_xy_m=origin, row_v_m=row_v,
        row_start_u_m=row_start_u, row_end_u_m=row_end_u, row_spacing_m=float(row_spacing),
        tree_spacing_m=float(tree_spacing), ground=ground, cylinders=cylinders,
        canopies=canopies, boxes=boxes, trunk_index_of_tree=np.arange(n_trees),
        canopy_index_of_tree=canopy_index_of_tree)


# Lumpy crowns: each crown a cluster of this many lobes, each this share of its radii.
LUMP_LOBES = 4
LUMP_RADIUS_SHARE = (0.5, 0.75)
# Hedgerow: a crown reaches this share of the tree spacing along the row either way, so
# neighbouring crowns overlap into one wall.
HEDGE_REACH = 0.65


def _shaped_canopies(canopies: Canopies, model: str, tree_spacing_m: float,
                     rng: np.random.Generator) -> tuple[Canopies, np.ndarray]:
    """The crowns reshaped by `model` ('lumpy' or 'hedgerow'; sim/variation.CANOPY_MODELS),
    and the first canopy of each tree. A lobe sways with its crown."""
    n = len(canopies)
    if model == 'hedgerow':
        radii = canopies.radii_m.copy()
        radii[:, 0] = np.maximum(radii[:, 0], HEDGE_REACH * tree_spacing_m)
        return Canopies(canopies.centre_m, radii, canopies.sway_amplitude,
                        canopies.sway_frequency_hz, canopies.sway_phase_rad), np.arange(n)
    if model != 'lumpy':
        raise SimulationError(f'unknown canopy model {model!r}')
    parent = np.repeat(np.arange(n), LUMP_LOBES)
    radii = canopies.radii_m[parent]
    # Lobes scattered inside the crown: the cluster spans about the crown it replaces.
    offset = rng.uniform(-0.45, 0.45, (parent.size, 3)) * radii
    offset[:, 2] = np.abs(offset[:, 2])  # no lobe hangs below the crown's skirt
    shares = rng.uniform(*LUMP_RADIUS_SHARE, (parent.size, 3))
    return Canopies(canopies.centre_m[parent] + offset, radii * shares,
                    canopies.sway_amplitude[parent], canopies.sway_frequency_hz[parent],
                    canopies.sway_phase_rad[parent]), np.arange(n) * LUMP_LOBES
