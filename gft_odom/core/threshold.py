"""The robust kernel's scale from how far the motion model's predictions have been off.

kiss-icp's adaptive threshold (Vizzo et al., RA-L 2023), as an idea: a match starts at the
prediction, so the residuals it should expect are about as large as the displacement the
prediction's error causes at the far edge of what is matched. After each trusted match the
deviation between prediction and estimate is turned into that displacement (its translation
plus its rotation's chord at `range_m`); the scale is the root mean square of those
displacements so far. Deviations below `min_motion_m` are not counted, so that standing still
does not shrink the scale to nothing. Until one is counted the scale is `initial_m`. With a
`window` only the last that many counted errors make the mean (0: all of them, as kiss-icp),
so the scale widens soon after the motion turns erratic.

The fixed Tukey scale (`robust_kernel_scale_m`) was chosen on simulated drives; a real
platform, driven more gently or more roughly, predicts better or worse, and this follows it.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from gft_odom.core.geometry import invert_transform
from gft_odom.core.motion_model import transform_magnitude


def prediction_error_m(T_pred: np.ndarray, T_est: np.ndarray, range_m: float) -> float:
    """How far the prediction `T_pred` moved a point at `range_m` from where the estimate
    `T_est` puts it, at most: |t| + 2 r sin(theta / 2) of the deviation T_pred^-1 T_est."""
    translation_m, angle_rad = transform_magnitude(invert_transform(T_pred) @ T_est)
    return translation_m + 2.0 * range_m * math.sin(angle_rad / 2.0)


class AdaptiveThreshold:
    """The root mean square of the prediction errors of the trusted matches so far (or of the
    last `window` of them)."""

    def __init__(self, initial_m: float, min_motion_m: float, range_m: float,
                 window: int = 0) -> None:
        self.initial_m = initial_m
        self.min_motion_m = min_motion_m
        self.range_m = range_m
        self.window = window
        self.reset()

    def reset(self) -> None:
        """No error counted: the scale is `initial_m` again."""
        self._sum_sq_m2 = 0.0
        self.n_samples = 0
        self._recent_sq_m2: deque[float] = deque(maxlen=self.window or None)

    def observe(self, T_pred: np.ndarray, T_est: np.ndarray) -> None:
        """A trusted match `T_est` that started from the prediction `T_pred`."""
        error_m = prediction_error_m(T_pred, T_est, self.range_m)
        if math.isfinite(error_m) and error_m > self.min_motion_m:
            self._sum_sq_m2 += error_m * error_m
            self.n_samples += 1
            if self.window:
                self._recent_sq_m2.append(error_m * error_m)

    @property
    def sigma_m(self) -> float:
        """The root mean square of the counted errors (`initial_m` before one)."""
        if self.n_samples == 0:
            return self.initial_m
        if self.window:
            return math.sqrt(sum(self._recent_sq_m2) / len(self._recent_sq_m2))
        return math.sqrt(self._sum_sq_m2 / self.n_samples)
