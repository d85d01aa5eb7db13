"""Core data types of the estimator: plain numpy, no transport, no IO."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import lru_cache
from typing import Any, NamedTuple, TypeVar

import numpy as np
import numpy.typing as npt

from clients.wire import PoseFlag

FloatArray = npt.NDArray[np.float64]
# A row-major 3×3 covariance of (x_m, y_m, theta_rad).
Covariance3 = tuple[float, float, float, float, float, float, float, float, float]
ZERO_COVARIANCE: Covariance3 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


class Pose2D(NamedTuple):
    """A planar pose: position in metres and heading in radians (counter-clockwise)."""

    x_m: float
    y_m: float
    theta_rad: float

    def compose(self, other: Pose2D) -> Pose2D:
        """`self ∘ other`: `other` expressed in this pose's frame, mapped to the parent frame."""
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return Pose2D(
            self.x_m + c * other.x_m - s * other.y_m,
            self.y_m + s * other.x_m + c * other.y_m,
            wrap_angle(self.theta_rad + other.theta_rad),
        )

    def inverse(self) -> Pose2D:
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return Pose2D(
            -c * self.x_m - s * self.y_m,
            s * self.x_m - c * self.y_m,
            wrap_angle(-self.theta_rad),
        )

    def between(self, other: Pose2D) -> Pose2D:
        """`inverse(self) ∘ other`: where `other` is, seen from this pose."""
        return self.inverse().compose(other)


ArrayT = TypeVar("ArrayT", bound="np.ndarray[Any, Any]")


def frozen_array(values: ArrayT) -> ArrayT:
    """`values` as a read-only array that owns its data (a copy when it is a view).

    For data that never changes once made (finished submaps, frozen map chunks, a node's
    points): checkpoints write such arrays once and refer to them afterwards
    (`service.app.statecodec.ArrayPack`), and writing into one by mistake raises.
    """
    out = values if values.base is None and values.flags.c_contiguous else values.copy()
    out.flags.writeable = False
    return out


def rotate_points(points_xy_m: FloatArray, theta_rad: float) -> FloatArray:
    """(N, 2) points rotated counter-clockwise by theta about the origin."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    out = np.empty_like(points_xy_m)
    out[:, 0] = c * points_xy_m[:, 0] - s * points_xy_m[:, 1]
    out[:, 1] = s * points_xy_m[:, 0] + c * points_xy_m[:, 1]
    return out


# Small products and solves in closed form, not through BLAS or LAPACK: their kernels differ in
# the last bits (`OPENBLAS_CORETYPE`), and a gate or a tie downstream must not.


def matmul_exact(a: FloatArray, b: FloatArray) -> FloatArray:
    """`a @ b` for small matrices, as element-wise products summed in a fixed order."""
    return np.asarray((a[:, :, None] * b[None, :, :]).sum(axis=1), dtype=np.float64)


def largest_eigenvalue_2x2(m: FloatArray) -> float:
    """The larger eigenvalue of a symmetric 2×2 matrix."""
    a, b, d = float(m[0, 0]), float(m[0, 1]), float(m[1, 1])
    return 0.5 * (a + d) + math.hypot(0.5 * (a - d), b)


def mahalanobis_sq_2x2(d: FloatArray, cov: FloatArray) -> float:
    """dᵀ·cov⁻¹·d for a symmetric positive-definite 2×2 `cov`."""
    a, b, c = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    x, y = float(d[0]), float(d[1])
    return (c * x * x - 2.0 * b * x * y + a * y * y) / (a * c - b * b)


def fields_by_name(obj: Any) -> dict[str, object]:
    """A dataclass's fields by name: what it pickles as, so that a checkpoint keeps its values
    when a later version adds fields (the dataclass default pickles by position)."""
    return {f.name: getattr(obj, f.name) for f in fields(obj)}


def parabolic_offset(y_minus: float, y0: float, y_plus: float) -> float:
    """Vertex of the parabola through three equally spaced samples, in steps, within ±0.5."""
    denom = y_minus - 2.0 * y0 + y_plus
    if denom >= 0.0:
        return 0.0
    return min(max(0.5 * (y_minus - y_plus) / denom, -0.5), 0.5)


def wrap_angle(theta_rad: float) -> float:
    """Wrap to [-π, π)."""
    return (theta_rad + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True, slots=True, eq=False)
class LaserScan:
    """One scan as the estimator sees it, in the laser frame (x forward, y left).

    `ranges_m` is (N,) float64; NaN marks an invalid beam. `odom` is the robot's odometry pose
    at the scan time if the robot has odometry.
    """

    stamp_ns: int
    angle_min_rad: float
    angle_increment_rad: float
    ranges_m: FloatArray
    range_min_m: float
    range_max_m: float
    odom: Pose2D | None = None

    def angles_rad(self) -> FloatArray:
        return _beam_angles(self.angle_min_rad, self.angle_increment_rad, self.ranges_m.shape[0])

    def valid_mask(self) -> npt.NDArray[np.bool_]:
        r = self.ranges_m
        with np.errstate(invalid="ignore"):
            return np.isfinite(r) & (r > 0.0) & (r >= self.range_min_m) & (r < self.range_max_m)

    def points_xy_m(self) -> FloatArray:
        """(M, 2) float64 Cartesian points of the valid beams, laser frame."""
        mask = self.valid_mask()
        r = self.ranges_m[mask]
        cos, sin = _beam_directions(self.angle_min_rad, self.angle_increment_rad, mask.shape[0])
        return np.column_stack((r * cos[mask], r * sin[mask]))


def _beam_angles(angle_min_rad: float, angle_increment_rad: float, n: int) -> FloatArray:
    """Each of n beams' angle."""
    out: FloatArray = angle_min_rad + angle_increment_rad * np.arange(n, dtype=np.float64)
    return out


@lru_cache(maxsize=16)
def _beam_directions(
    angle_min_rad: float, angle_increment_rad: float, n: int
) -> tuple[FloatArray, FloatArray]:
    """cos and sin of each beam's angle (`_beam_angles`): a laser's beams are the same every
    scan, so they are computed once per laser (elementwise, the same bits)."""
    a = _beam_angles(angle_min_rad, angle_increment_rad, n)
    cos, sin = np.cos(a), np.sin(a)
    cos.flags.writeable = sin.flags.writeable = False
    return cos, sin


@dataclass(frozen=True, slots=True)
class PoseEstimate:
    """The estimator's answer for one scan: the pose in the map frame and how sure it is.

    `covariance` is that of the pose relative to the latest keyframe before it (for a keyframe:
    the previous one), on the map axes: what the back end weighs a sequential constraint by.
    """

    stamp_ns: int
    pose: Pose2D
    quality: float  # [0, 1]
    flags: PoseFlag = PoseFlag.NONE
    is_keyframe: bool = False
    covariance: Covariance3 = ZERO_COVARIANCE

    @property
    def x_m(self) -> float:
        return self.pose.x_m

    @property
    def y_m(self) -> float:
        return self.pose.y_m

    @property
    def theta_rad(self) -> float:
        return self.pose.theta_rad
