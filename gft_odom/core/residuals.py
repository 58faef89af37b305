"""Residual-and-weight models: which residual each correspondence contributes, and how much.

A scan point matched to a map point can constrain the pose in three ways:
- point-to-plane, `r = n . (p - q)`: one row along the map normal n. Right for smooth
  structure (ground, trunks, posts, walls) whose normal is real;
- beam-perpendicular point-to-point, `r = P (p - q)` with `P = I - b b^T` and b the unit beam
  direction: porous canopy is a volume whose returns sit at random depths along the beam, so
  it can say where the foliage is across the beam but not along it;
- point-to-point, `r = p - q`: GenZ-ICP's residual where the map is not planar.

A model turns the m correspondences into Gauss-Newton rows `(J, r, w, group)` with `J` (k, 6)
over the perturbation (translation, rotation about the sensor), `w` the model's weight of each
row and `group` the residual a row belongs to: i for pair i's plane row, m + i for its rough
rows (the robust kernel weighs each residual by its norm, not each row). Each model is one
class; `make_residual_model` picks one by name.

Smoothness s in [0, 1] (1 = a surface with a real normal) comes from the scan point's graph
frequency (`frequency`), or from the map neighbourhood's covariance (`planarity`, the
GenZ-ICP-style control); without either every correspondence is a plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gft_odom.errors import ConfigError

RESIDUAL_MODELS = ('plane', 'frequency', 'planarity')
ROUGH_RESIDUALS = ('beam_perpendicular', 'point')


@dataclass
class Correspondences:
    """Matched pairs at the current pose estimate (world frame)."""

    source_world: np.ndarray  # (m, 3) scan points moved by the current estimate
    lever: np.ndarray  # (m, 3) source_world - sensor position (the rotation's lever arm)
    target: np.ndarray  # (m, 3) nearest map points
    normal: np.ndarray  # (m, 3) map normals at the targets (unit)
    smoothness: np.ndarray | None  # (m,) in [0, 1], None when the model has no source of it


def skew_rows(a: np.ndarray) -> np.ndarray:
    """(m, 3, 3) cross-product matrices [a]x of the rows of `a`."""
    out = np.zeros((a.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -a[:, 2], a[:, 1]
    out[:, 1, 0], out[:, 1, 2] = a[:, 2], -a[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -a[:, 1], a[:, 0]
    return out


def plane_rows(c: Correspondences) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-plane: J = [n, a x n], r = n . (p - q)."""
    J = np.hstack([c.normal, np.cross(c.lever, c.normal)])
    r = np.einsum('ij,ij->i', c.normal, c.source_world - c.target)
    return J, r


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


class PlaneResidual:
    """Every correspondence a point-to-plane row of weight 1 (kiss-icp-like, open3d's)."""

    name = 'plane'

    def linearise(self, c: Correspondences):
        """(J, r, w, group) of every correspondence."""
        J, r = plane_rows(c)
        m = r.shape[0]
        return J, r, np.ones(m), np.arange(m)


class SmoothnessResidual:
    """Plane rows weighted by the smoothness s, rough rows by `rough_weight * (1 - s)`.

    With no smoothness (the frequency switched off) it is `PlaneResidual`: the ablation
    '--no-filter' is the same registration with every point weighted alike.
    """

    def __init__(self, name: str, rough_residual: str = 'beam_perpendicular',
                 rough_weight: float = 1.0) -> None:
        if rough_residual not in ROUGH_RESIDUALS:
            raise ConfigError(f'rough residual must be one of {ROUGH_RESIDUALS}, '
                              f'got {rough_residual!r}')
        self.name = name
        self.beam_perpendicular = rough_residual == 'beam_perpendicular'
        self.rough_weight = float(rough_weight)

    def linearise(self, c: Correspondences):
        """(J, r, w, group): one plane row per pair, three rough rows where s < 1."""
        Jp, rp = plane_rows(c)
        m = rp.shape[0]
        if c.smoothness is None:
            return Jp, rp, np.ones(m), np.arange(m)
        s = np.clip(np.nan_to_num(c.smoothness, nan=0.0), 0.0, 1.0)
        rough = np.flatnonzero(s < 1.0)
        if rough.size == 0 or self.rough_weight == 0.0:
            return Jp, rp, s, np.arange(m)
        sub = Correspondences(c.source_world[rough], c.lever[rough], c.target[rough],
                              c.normal[rough], None)
        Jr, rr = point_rows(sub, self.beam_perpendicular)
        wr = np.repeat(self.rough_weight * (1.0 - s[rough]), 3)
        return (np.vstack([Jp, Jr]), np.concatenate([rp, rr]), np.concatenate([s, wr]),
                np.concatenate([np.arange(m), m + np.repeat(rough, 3)]))


def make_residual_model(name: str, rough_residual: str = 'beam_perpendicular',
                        rough_weight: float = 1.0):
    """The model named by `registration.residual_model`."""
    if name == 'plane':
        return PlaneResidual()
    if name in ('frequency', 'planarity'):
        return SmoothnessResidual(name, rough_residual, rough_weight)
    raise ConfigError(f'residual model must be one of {RESIDUAL_MODELS}, got {name!r}')


def smoothness_from_nu(nu: np.ndarray, nu_smooth: float) -> np.ndarray:
    """Smoothness of scan points from their graph frequency: nu / nu_smooth, clipped to
    [0, 1]; no spectrum (isolated, NaN) is rough (0).

    On the scan-line graph `ldos_mean` is the weighted degree over lambda_max: a point whose
    two ring neighbours continue its surface has nu near 0.5, a canopy return ~0."""
    nu = np.asarray(nu, dtype=np.float64)
    return np.clip(np.nan_to_num(nu / nu_smooth, nan=0.0), 0.0, 1.0)


def smoothness_from_covariances(covariances: np.ndarray, variation_rough: float) -> np.ndarray:
    """Smoothness of map points from their neighbourhood covariance (GenZ-ICP-style): the
    surface variation `l_min / (l_1 + l_2 + l_3)` is 0 on a plane and 1/3 in an isotropic
    blob; s = 1 - variation / variation_rough, clipped to [0, 1]."""
    if covariances.shape[0] == 0:
        return np.zeros(0)
    eig = np.linalg.eigvalsh(covariances)
    variation = eig[:, 0] / np.maximum(eig.sum(axis=1), 1e-12)
    return np.clip(1.0 - variation / variation_rough, 0.0, 1.0)
