"""One ICP call for scan registration, whichever solver runs it.

open3d's ICP (point-to-point, point-to-plane or GICP; one residual type for every pair)
serves paper mode and default mode with solver 'open3d'; solver 'map_tree'
(core/map_tree_icp.py) is the same point-to-plane ICP over a KD-tree the map keeps between
rebuilds; the Gauss-Newton solver
(core/gauss_newton.py: a residual type and weight per pair, core/residuals.py) serves default
mode with solver 'gauss_newton'. The backend also tells the local map what its target must
carry (normals, covariances, planarity) so that a rebuild computes it once (or, with
map_normals 'on_demand', the numpy solvers' normals as pairs use them).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d

from gft_odom.core.deferred import Deferred, resolved
from gft_odom.core.gauss_newton import GaussNewtonICP
from gft_odom.core.geometry import transform_points
from gft_odom.core.local_map import LocalMap
from gft_odom.core.map_tree_icp import MapTreeICP
from gft_odom.core.residuals import make_residual_model

if TYPE_CHECKING:
    from gft_odom.core.registration_config import RegistrationConfig

o3d_reg = o3d.pipelines.registration

# Re-acquisition's fine ICP may iterate this many times longer than a normal match.
RECOVERY_ITERATIONS_FACTOR = 4


def robust_kernel(name: str, scale_m: float):
    """open3d's robust loss of that name ('none': plain least squares)."""
    if name == 'tukey':
        return o3d_reg.TukeyLoss(scale_m)
    if name == 'huber':
        return o3d_reg.HuberLoss(scale_m)
    if name == 'cauchy':
        return o3d_reg.CauchyLoss(scale_m)
    return o3d_reg.L2Loss()


class IcpBackend:
    """ICP from an initial guess against the local map (or, in paper mode, the last scan)."""

    def __init__(self, config: RegistrationConfig, local_map: LocalMap):
        self.config = config
        self.local_map = local_map
        self.estimation = config.resolved_estimation
        self.criteria = o3d_reg.ICPConvergenceCriteria(
            relative_fitness=config.convergence_relative,
            relative_rmse=config.convergence_relative, max_iteration=config.max_iterations)
        # Re-acquisition starts further away: more iterations to converge.
        self.recovery_criteria = o3d_reg.ICPConvergenceCriteria(
            relative_fitness=config.convergence_relative,
            relative_rmse=config.convergence_relative,
            max_iteration=RECOVERY_ITERATIONS_FACTOR * config.max_iterations)
        # The paper's ICP is plain least squares; ours is robust.
        kernel_name = 'none' if config.mode == 'paper' else config.robust_kernel
        self._kernel_name = kernel_name
        self.kernel_scale_m = config.robust_kernel_scale_m  # adaptive_kernel_ratio: per scan
        self.kernel = robust_kernel(kernel_name, config.robust_kernel_scale_m)
        local_map.with_normals = self.estimation == 'point_to_plane'
        local_map.with_covariances = self.estimation == 'gicp'
        # Gauss-Newton (default mode): per-pair residual types and weights.
        self.solver = None
        if config.solver == 'gauss_newton' and config.mode == 'default':
            self.solver = GaussNewtonICP(
                make_residual_model(config.residual_model, config.rough_residual,
                                    config.rough_weight, config.rough_depth_ratio),
                config.robust_kernel, config.robust_kernel_scale_m, config.max_iterations,
                config.convergence_m, config.frequency_affinity_m)
            if config.residual_model == 'planarity':
                local_map.smoothness_variation = config.rough_surface_variation
                local_map.with_covariances = True  # computed once per map rebuild
        # 'map_tree' (default mode, against the map): open3d's point-to-plane ICP over the
        # map's KD-tree (gicp and point_to_point: open3d's own ICP).
        self.map_tree = None
        if (config.solver == 'map_tree' and config.mode == 'default'
                and self.estimation == 'point_to_plane'):
            self.map_tree = MapTreeICP(kernel_name, config.robust_kernel_scale_m,
                                       config.convergence_relative, config.convergence_relative,
                                       config.max_iterations,
                                       anderson_memory=config.anderson_memory,
                                       anneal_from_m=config.kernel_anneal_from_m,
                                       anneal_factor=config.kernel_anneal_factor)
        if self.solves_on_map_target:
            # 'on_demand': the map's target estimates the normals its pairs use.
            # 'in_time': a rebuild's when they fit before the next scan, else on demand.
            local_map.with_normals = config.map_normals in ('rebuild', 'in_time')
            local_map.normals_in_time = config.map_normals == 'in_time'
            local_map.normals_slack_s = config.map_normals_slack_s
            local_map.keep_normals = config.map_normals == 'kept'
        # This scan's downsampled points: their smoothness (residual_model 'frequency'), and
        # the same with unknown kept NaN (frequency_affinity_m, rough_kernel_scale_m; a
        # Deferred is computed only when one of them reads it); set per scan.
        self.source_smoothness: np.ndarray | None = None
        self.point_smoothness: np.ndarray | Deferred | None = None

    def use_kernel_scale(self, scale_m: float) -> None:
        """The robust kernel's scale for the matches that follow, in every solver."""
        self.kernel_scale_m = scale_m
        self.kernel = robust_kernel(self._kernel_name, scale_m)
        if self.map_tree is not None:
            self.map_tree.kernel_scale_m = scale_m
        if self.solver is not None:
            self.solver.kernel_scale_m = scale_m

    def use_smoothness(self, source_smoothness: np.ndarray | None,
                       point_smoothness: np.ndarray | Deferred | None) -> None:
        """The smoothness of the scan about to be matched (None: not used)."""
        self.source_smoothness = source_smoothness
        self.point_smoothness = point_smoothness

    def _match_smoothness(self) -> np.ndarray | None:
        """The scan points' smoothness for the Gauss-Newton candidate choice: only read
        with frequency_affinity_m > 0, so only computed then."""
        if self.point_smoothness is None or not self.config.frequency_affinity_m > 0.0:
            return None
        return resolved(self.point_smoothness)

    def _point_kernel_scale_m(self) -> np.ndarray | None:
        """Each scan point's kernel scale, from the kernel's scale where it is smooth to
        rough_kernel_scale_m where it is rough (None: one scale for all; so without
        frequencies)."""
        rough_m = self.config.rough_kernel_scale_m
        if rough_m <= 0.0 or self.point_smoothness is None:
            return None
        return rough_m + (self.kernel_scale_m - rough_m) * self._blend_smoothness()

    def _point_gate_m(self, distance_m: float) -> float | np.ndarray:
        """Each scan point's correspondence gate, from `rough_gate_ratio` x `distance_m` where
        it is rough (or unknown) to `distance_m` where it is smooth; `distance_m` for all when
        the option is off or the scan has no frequencies."""
        ratio = self.config.rough_gate_ratio
        if ratio <= 0.0 or self.point_smoothness is None:
            return distance_m
        return distance_m * (ratio + (1.0 - ratio) * self._blend_smoothness())

    def _blend_smoothness(self) -> np.ndarray:
        """The scan points' smoothness as the per-point settings blend by it: in [0, 1],
        unknown counted rough (0)."""
        return np.clip(np.nan_to_num(resolved(self.point_smoothness), nan=0.0), 0.0, 1.0)

    @property
    def solves_on_map_target(self) -> bool:
        """A numpy solver ('gauss_newton' or 'map_tree') matches against the map's
        `MapTarget` rather than open3d's cloud."""
        return self.solver is not None or self.map_tree is not None

    def matched(self, target: o3d.geometry.PointCloud):
        """What a match against `target` was solved on: the map's `MapTarget` when a numpy
        solver matched against the map (its normals are there), else `target` itself."""
        if self.solves_on_map_target and target is self.local_map.cloud:
            return self.local_map.target()
        return target

    def match_rmse_m(self, result, source_xyz: np.ndarray, target) -> float:
        """The RMSE a match's covariance is scaled by: ICP's own, or (`noise_gate_m`, against
        the local map) the RMS distance of the points within that gate at its pose. Within a
        narrow correspondence gate the distances are cut short and the covariance would claim
        more than the match knows. Only for the matches kept (a KD-tree query each)."""
        gate_m = self.config.noise_gate_m
        if not gate_m > 0.0 or target is not self.local_map.cloud:
            return float(result.inlier_rmse)
        distance_m = self.local_map.distances_within(
            transform_points(np.asarray(result.transformation), source_xyz), gate_m)
        near = distance_m[np.isfinite(distance_m)]
        return float(np.sqrt(np.mean(near ** 2))) if near.size else 0.0

    def register(self, source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud,
                 init: np.ndarray, distance_m: float, recovery: bool = False,
                 prior: bool = False, max_iterations: int | None = None):
        """ICP of `source` onto `target` from `init` with pairs up to `distance_m` apart
        (`recovery`: the longer iteration budget of re-acquisition; `max_iterations`: another
        budget; `prior`: `init` is the motion model's prediction, a soft prior with
        motion_prior_weight). Returns open3d's result or the solver's IcpResult
        (transformation, fitness, inlier_rmse)."""
        criteria = self.recovery_criteria if recovery else self.criteria
        if max_iterations is not None:
            criteria = o3d_reg.ICPConvergenceCriteria(
                relative_fitness=criteria.relative_fitness,
                relative_rmse=criteria.relative_rmse, max_iteration=max_iterations)
        if self.solver is not None and target is self.local_map.cloud:
            return self.solver.register(np.asarray(source.points), self.local_map.target(),
                                        init, distance_m, self.source_smoothness,
                                        criteria.max_iteration, self._match_smoothness(),
                                        (init, self.config.motion_prior_weight)
                                        if prior and self.config.motion_prior_weight > 0.0
                                        else None)
        if self.map_tree is not None and target is self.local_map.cloud:
            return self.map_tree.register(np.asarray(source.points), self.local_map.target(),
                                          init, self._point_gate_m(distance_m),
                                          criteria.max_iteration,
                                          self._point_kernel_scale_m())
        if self.estimation == 'gicp':
            estimation = o3d_reg.TransformationEstimationForGeneralizedICP(
                self.config.gicp_epsilon, self.kernel)
            return o3d_reg.registration_generalized_icp(source, target, distance_m, init,
                                                        estimation, criteria)
        if self.estimation == 'point_to_plane':
            if not target.has_normals():
                target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(
                    self.local_map.normal_neighbours))
            estimation = o3d_reg.TransformationEstimationPointToPlane(self.kernel)
        else:
            estimation = o3d_reg.TransformationEstimationPointToPoint()
        return o3d_reg.registration_icp(source, target, distance_m, init, estimation, criteria)
