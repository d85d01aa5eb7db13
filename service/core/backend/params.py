"""The pose graph's parameters and covariance helper, without gtsam (`graph` imports it: only a
session with loop closure needs it)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.core.types import FloatArray, matmul_exact

_COV_FLOOR = (1e-6, 1e-6, 1e-8)  # keeps a constraint's information matrix finite


@dataclass(frozen=True, slots=True)
class GraphParams:
    prior_sigma_m: float = 1e-3  # the first node pins the map frame
    prior_sigma_rad: float = 1e-4
    heading_huber_k: float = 3.0  # whitened residual where a heading prior stops being L2
    loop_huber_k: float = 3.0  # whitened residual where a closure stops being L2 (iSAM2)
    loop_cauchy_k: float = 3.0  # whitened residual scale of the closures' Cauchy kernel (batch)
    relinearize_threshold: float = 0.01  # iSAM2
    batch_max_iterations: int = 100  # Levenberg-Marquardt, offline


def rotate_covariance(cov_map: FloatArray, theta_rad: float) -> FloatArray:
    """A 3×3 (x, y, θ) covariance on the map axes, expressed in a frame at heading θ."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    out = matmul_exact(matmul_exact(rot, cov_map), rot.T)
    out[np.diag_indices(3)] += _COV_FLOOR
    return out
