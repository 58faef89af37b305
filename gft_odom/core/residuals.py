"""Residual-and-weight models: which residual each correspondence contributes, and how much.

A scan point matched to a map point can constrain the pose in three ways:
- point-to-plane, `r = n . (p - q)`: one row along the map normal n. Right for smooth
  structure (ground, trunks, posts, walls) whose normal is real;
- beam-perpendicular point-to-point, `r = P (p - q)` with `P = I - b b^T` and b the unit beam
  direction: porous canopy is a volume whose returns sit at random depths along the beam, so
  it can say where the foliage is across the beam but not along it;
- point-to-point, `r = p - q`: GenZ-ICP's residual where the map is not planar;
- beam covariance, `r = p - q` weighed by `Omega = 2 (2 I + (k^2 - 1)(b b^T + c c^T))^-1`,
  with b the scan point's beam and c the beam the map point was measured along: each canopy
  return is uncertain k times more along its own beam (its depth in the foliage) than across
  it. Seen from behind (the map), canopy beside and ahead of the robot is displaced along a
  beam with a forward component; the scan sees it from beside. Point-to-point or the scan's
  beam alone read that displacement as motion (docs/registration.md, the bias study).

A model says, per correspondence, which residual types apply and with what weight (`terms`:
a list of `Term`s); `normal_equations` turns a term into its Gauss-Newton contribution over
the perturbation (translation, rotation about the sensor), the robust kernel weighing each
residual by its norm. A new weighting is one model class; a new residual type is one more
branch of `normal_equations`. `linearise` spells the same terms out as explicit rows.

Smoothness s in [0, 1] (1 = a surface with a real normal) comes from the scan point's graph
frequency (`frequency`), or from the map neighbourhood's covariance (`planarity`, the
GenZ-ICP-style control); without either every correspondence is a plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gft_odom.errors import ConfigError

RESIDUAL_MODELS = ('plane', 'frequency', 'planarity')
ROUGH_RESIDUALS = ('beam_perpendicular', 'point', 'beam_covariance')


@dataclass
class Correspondences:
    """Matched pairs at the current pose estimate (world frame)."""

    source_world: np.ndarray  # (m, 3) scan points moved by the current estimate
    lever: np.ndarray  # (m, 3) source_world - sensor position (the rotation's lever arm)
    target: np.ndarray  # (m, 3) nearest map points
    normal: np.ndarray  # (m, 3) map normals at the targets (unit)
    smoothness: np.ndarray | None  # (m,) in [0, 1], None when the model has no source of it
    # (m, 3) unit direction each map point was measured along (None: unknown, the scan's
    # beam stands in for it).
    target_beam: np.ndarray | None = None


def skew_rows(a: np.ndarray) -> np.ndarray:
    """(m, 3, 3) cross-product matrices [a]x of the rows of `a`."""
    out = np.zeros((a.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -a[:, 2], a[:, 1]
    out[:, 1, 0], out[:, 1, 2] = a[:, 2], -a[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -a[:, 1], a[:, 0]
    return out


def plane_rows(c: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-plane: J = [n, a x n], r = n . (p - q)."""
    return _plane_rows(c.lever, c.normal, c.source_world - c.target)


def _plane_rows(a: np.ndarray, n: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.hstack([n, np.cross(a, n)]), np.einsum('ij,ij->i', n, e)


def point_rows(c: Correspondences, beam_perpendicular: bool) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-point rows, 3 per pair (flattened): J = P [I, -[a]x], r = P (p - q), with P the
    projection across the beam (or the identity)."""
    m = c.lever.shape[0]
    J = np.concatenate([np.broadcast_to(np.eye(3), (m, 3, 3)), -skew_rows(c.lever)], axis=2)
    r = c.source_world - c.target
    if beam_perpendicular:
        b = c.lever / np.maximum(np.linalg.norm(c.lever, axis=1, keepdims=True), 1e-9)
        P = np.eye(3)[None] - b[:, :, None] * b[:, None, :]
        J = P @ J
        r = np.einsum('nij,nj->ni', P, r)
    return J.reshape(3 * m, 6), r.reshape(3 * m)


@dataclass
class Term:
    """One residual type over a subset of the pairs: `kind` from RESIDUAL_KINDS, `index` (k,)
    the pairs it covers, `weight` (k,) the model's weight of each."""

    kind: str
    index: np.ndarray
    weight: np.ndarray
    # 'beam_covariance': the along-beam standard deviation over the across-beam one.
    depth_ratio: float = 1.0


# The residual types a model can assign; `normal_equations` has each one's closed form.
RESIDUAL_KINDS = ('plane', 'beam_perpendicular', 'point', 'beam_covariance')


def unit_rows(v: np.ndarray) -> np.ndarray:
    """Rows of `v` scaled to unit length (a zero row stays zero)."""
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)


def beam_information(scan_beam: np.ndarray, map_beam: np.ndarray | None,
                     depth_ratio: float) -> np.ndarray:
    """(m, 3, 3) information of p - q when both points are `depth_ratio` times less certain
    along their beams than across (1 across both beams)."""
    b = unit_rows(scan_beam)
    c = b if map_beam is None else unit_rows(map_beam)
    outer = b[:, :, None] * b[:, None, :] + c[:, :, None] * c[:, None, :]
    C = 2.0 * np.eye(3)[None] + (depth_ratio ** 2 - 1.0) * outer
    return 2.0 * np.linalg.inv(C)


def _beam_covariance_equations(a, e, Omega, w, kernel):
    """(H, g) of point rows J = [I, -[a]x] weighed by Omega and w * kernel(Mahalanobis)."""
    w = w * kernel(np.sqrt(np.maximum(np.einsum('ni,nij,nj->n', e, Omega, e), 0.0)))
    J = np.concatenate([np.broadcast_to(np.eye(3), (a.shape[0], 3, 3)), -skew_rows(a)], axis=2)
    JtO = np.einsum('nki,nkl->nil', J, Omega) * w[:, None, None]
    return np.einsum('nil,nlj->ij', JtO, J), np.einsum('nil,nl->i', JtO, e)


def normal_equations(c: Correspondences, term: Term, kernel) -> tuple[np.ndarray, np.ndarray]:
    """(H, g) = sum of w J^T J, w J^T r over the term's pairs, with w = the model's weight
    times `kernel(residual norm)`; in closed form for the point types (no 3-row blocks).

    Beam-perpendicular rows are `[P, -[a]x]`: the lever a is the beam, so P [a]x = [a]x."""
    i, w = term.index, term.weight
    a = c.lever[i]
    e = c.source_world[i] - c.target[i]
    if term.kind == 'plane':
        J, r = _plane_rows(a, c.normal[i], e)
        w = w * kernel(np.abs(r))
        Jw = J * w[:, None]
        return Jw.T @ J, Jw.T @ r
    if term.kind == 'beam_covariance':
        map_beam = None if c.target_beam is None else c.target_beam[i]
        return _beam_covariance_equations(a, e, beam_information(a, map_beam,
                                                                 term.depth_ratio), w, kernel)
    if term.kind not in ('beam_perpendicular', 'point'):
        raise ConfigError(f'residual kind must be one of {RESIDUAL_KINDS}, got {term.kind!r}')
    H = np.zeros((6, 6))
    if term.kind == 'beam_perpendicular':
        b = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-9)
        r = e - b * np.einsum('ij,ij->i', b, e)[:, None]
        w = w * kernel(np.linalg.norm(r, axis=1))
        H[:3, :3] = w.sum() * np.eye(3) - (b * w[:, None]).T @ b
    else:
        r = e
        w = w * kernel(np.linalg.norm(r, axis=1))
        H[:3, :3] = w.sum() * np.eye(3)
    wa = a * w[:, None]
    sa = wa.sum(axis=0)
    H[:3, 3:] = -skew_rows(sa[None])[0]
    H[3:, :3] = H[:3, 3:].T
    H[3:, 3:] = np.einsum('ij,ij->', wa, a) * np.eye(3) - wa.T @ a
    g = np.r_[(r * w[:, None]).sum(axis=0), np.cross(wa, r).sum(axis=0)]
    return H, g


class PlaneResidual:
    """Every correspondence a point-to-plane row of weight 1 (kiss-icp-like, open3d's)."""

    name = 'plane'

    def terms(self, c: Correspondences) -> list[Term]:
        """One plane term over every pair."""
        m = c.lever.shape[0]
        return [Term('plane', np.arange(m), np.ones(m))]


class SmoothnessResidual:
    """Plane rows weighted by the smoothness s, rough rows by `rough_weight * (1 - s)`.

    With no smoothness (the frequency switched off) it is `PlaneResidual`: the ablation
    '--no-filter' is the same registration with every point weighted alike.
    """

    def __init__(self, name: str, rough_residual: str = 'beam_perpendicular',
                 rough_weight: float = 1.0, depth_ratio: float = 1.0) -> None:
        if rough_residual not in ROUGH_RESIDUALS:
            raise ConfigError(f'rough residual must be one of {ROUGH_RESIDUALS}, '
                              f'got {rough_residual!r}')
        self.name = name
        self.rough_residual = rough_residual
        self.rough_weight = float(rough_weight)
        self.depth_ratio = float(depth_ratio)

    def terms(self, c: Correspondences) -> list[Term]:
        """A plane term weighted s over every pair, a rough term weighted 1 - s where s < 1."""
        m = c.lever.shape[0]
        if c.smoothness is None:
            return [Term('plane', np.arange(m), np.ones(m))]
        s = np.clip(np.nan_to_num(c.smoothness, nan=0.0), 0.0, 1.0)
        out = [Term('plane', np.arange(m), s)]
        rough = np.flatnonzero(s < 1.0)
        if rough.size and self.rough_weight > 0.0:
            out.append(Term(self.rough_residual, rough, self.rough_weight * (1.0 - s[rough]),
                            self.depth_ratio))
        return out


def linearise(model, c: Correspondences):
    """The model's terms as explicit Gauss-Newton rows (J, r, w, group): for tests and
    inspection; the solver uses `normal_equations`. Group i is pair i's plane row, m + i its
    rough rows."""
    m = c.lever.shape[0]
    Js, rs, ws, groups = [], [], [], []
    for term in model.terms(c):
        sub = Correspondences(c.source_world[term.index], c.lever[term.index],
                              c.target[term.index], c.normal[term.index], None,
                              None if c.target_beam is None else c.target_beam[term.index])
        if term.kind == 'plane':
            J, r = plane_rows(sub)
            w, group = term.weight, term.index
        elif term.kind == 'beam_covariance':
            # Whitened point rows: L^T J, L^T r with Omega = L L^T.
            J, r = point_rows(sub, False)
            L = np.linalg.cholesky(beam_information(sub.lever, sub.target_beam,
                                                    term.depth_ratio))
            Lt = np.swapaxes(L, 1, 2)
            J = np.einsum('nij,njk->nik', Lt, J.reshape(-1, 3, 6)).reshape(-1, 6)
            r = np.einsum('nij,nj->ni', Lt, r.reshape(-1, 3)).reshape(-1)
            w, group = np.repeat(term.weight, 3), m + np.repeat(term.index, 3)
        else:
            J, r = point_rows(sub, term.kind == 'beam_perpendicular')
            w, group = np.repeat(term.weight, 3), m + np.repeat(term.index, 3)
        Js.append(J)
        rs.append(r)
        ws.append(w)
        groups.append(group)
    return np.vstack(Js), np.concatenate(rs), np.concatenate(ws), np.concatenate(groups)


def make_residual_model(name: str, rough_residual: str = 'beam_perpendicular',
                        rough_weight: float = 1.0, depth_ratio: float = 1.0):
    """The model named by `registration.residual_model`."""
    if name == 'plane':
        return PlaneResidual()
    if name in ('frequency', 'planarity'):
        return SmoothnessResidual(name, rough_residual, rough_weight, depth_ratio)
    raise ConfigError(f'residual model must be one of {RESIDUAL_MODELS}, got {name!r}')


def smoothness_from_nu(nu: np.ndarray, nu_smooth: float, unknown: float = 0.0) -> np.ndarray:
    """Smoothness of scan points from their graph frequency: nu / nu_smooth, clipped to
    [0, 1]; no spectrum (isolated, NaN) is `unknown` (rough, 0, by default).

    On the scan-line graph `ldos_mean` is the weighted degree over lambda_max: a point whose
    two ring neighbours continue its surface has nu near 0.5, a canopy return ~0."""
    nu = np.asarray(nu, dtype=np.float64)
    return np.clip(np.nan_to_num(nu / nu_smooth, nan=unknown), 0.0, 1.0)


def smoothness_from_covariances(covariances: np.ndarray, variation_rough: float) -> np.ndarray:
    """Smoothness of map points from their neighbourhood covariance (GenZ-ICP-style): the
    surface variation `l_min / (l_1 + l_2 + l_3)` is 0 on a plane and 1/3 in an isotropic
    blob; s = 1 - variation / variation_rough, clipped to [0, 1]."""
    if covariances.shape[0] == 0:
        return np.zeros(0)
    eig = np.linalg.eigvalsh(covariances)
    variation = eig[:, 0] / np.maximum(eig.sum(axis=1), 1e-12)
    return np.clip(1.0 - variation / variation_rough, 0.0, 1.0)
