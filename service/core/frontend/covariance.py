"""The front end's covariance: how well each match pins the pose, as a number the graph can weigh.

Every scan is matched against the local map, whose anchor is the latest keyframe. So the error
of a pose relative to that keyframe is the error of its own match where the match constrains an
axis, and grows with every scan where it does not (an ambiguous axis is the motion prediction,
an unanchored heading is the predicted turn). `CovarianceTracker` keeps that per axis of the map
frame (x, y, θ), and restarts at each keyframe.

The per-match figures come from the correlation itself: a sharp, well supported peak is a few
millimetres, a flat one centimetres, an ambiguous one no measurement at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from service.core.frontend.translation import AxisMatch
from service.core.types import Covariance3


@dataclass(frozen=True, slots=True)
class CovarianceParams:
    """How a match's shape maps onto standard deviations (calibrated on the tuning worlds)."""

    match_sigma_floor_m: float = 0.006  # a sharp, well supported peak
    match_sigma_flat_m: float = 0.04  # added as the peak's contrast goes to zero
    match_support_full: float = 60.0  # weighted points at which support stops helping
    predicted_sigma_m: float = 0.05  # per scan, an axis carried by the motion prediction
    degenerate_sigma_m: float = 0.3  # per scan, no usable points at all
    anchored_heading_sigma_deg: float = 0.15  # a heading measured on the building's walls
    relative_heading_sigma_deg: float = 0.5  # per scan, a heading from directions / prediction


def axis_sigma_m(match: AxisMatch, params: CovarianceParams) -> float | None:
    """σ of one measured axis, or None where the match does not constrain it."""
    if match.ambiguous:
        return None
    support = min(max(match.support / params.match_support_full, 1e-3), 1.0)
    flat = params.match_sigma_flat_m * (1.0 - min(max(match.sharpness, 0.0), 1.0))
    return (params.match_sigma_floor_m + flat) / math.sqrt(support)


@dataclass(slots=True)
class CovarianceTracker:
    """Variance of the current pose relative to the latest keyframe, per map axis (x, y, θ)."""

    params: CovarianceParams = field(default_factory=CovarianceParams)
    var_x: float = 0.0  # along the first axis of the wall family at `frame_rad`
    var_y: float = 0.0
    var_theta: float = 0.0
    frame_rad: float = 0.0  # the axes the matches measure along (the map's, or a wing's)

    def restart(self) -> None:
        """A new keyframe: the following poses are measured against it."""
        self.var_x = self.var_y = self.var_theta = 0.0

    def update(
        self,
        sigma_x_m: float | None,
        sigma_y_m: float | None,
        heading_anchored: bool,
        *,
        degenerate: bool = False,
        frame_rad: float = 0.0,
    ) -> Covariance3:
        """One scan: a measured axis takes its match's variance, an unmeasured one grows.

        The σ are along the axes of the wall family at `frame_rad`. When those axes change,
        what was carried is kept as the larger of the two (isotropic: no axis is trusted more).
        """
        p = self.params
        if frame_rad != getattr(self, "frame_rad", 0.0):
            self.var_x = self.var_y = max(self.var_x, self.var_y)
            self.frame_rad = frame_rad
        step = p.degenerate_sigma_m if degenerate else p.predicted_sigma_m
        self.var_x = sigma_x_m**2 if sigma_x_m is not None else self.var_x + step**2
        self.var_y = sigma_y_m**2 if sigma_y_m is not None else self.var_y + step**2
        if heading_anchored:
            self.var_theta = math.radians(p.anchored_heading_sigma_deg) ** 2
        else:
            self.var_theta += math.radians(p.relative_heading_sigma_deg) ** 2
        return self.covariance()

    def covariance(self) -> Covariance3:
        """Row-major 3×3 (x, y, θ), map axes."""
        phi = getattr(self, "frame_rad", 0.0)
        if phi == 0.0:
            return (self.var_x, 0.0, 0.0, 0.0, self.var_y, 0.0, 0.0, 0.0, self.var_theta)
        c, s = math.cos(phi), math.sin(phi)  # R diag(var_x, var_y) Rᵀ
        xx = c * c * self.var_x + s * s * self.var_y
        yy = s * s * self.var_x + c * c * self.var_y
        xy = c * s * (self.var_x - self.var_y)
        return (xx, xy, 0.0, xy, yy, 0.0, 0.0, 0.0, self.var_theta)
