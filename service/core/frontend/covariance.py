"""The front end's covariance: how well each match pins the pose, as a number the graph can weigh.

Every scan is matched against the local map, whose anchor is the latest keyframe. So the error
of a pose relative to that keyframe is the error of its own match where the match constrains an
axis. Where it does not (an ambiguous axis, a degenerate scan) the pose is the motion model's,
carried at the last measured speed, and its error is what that speed's error integrates to:
each axis keeps a position-and-speed covariance under white-noise acceleration (a Kalman
filter's prediction), so the error grows with time, and faster the longer the speed has gone
unmeasured. From a standing start the speed is unknown until a match measures it: a featureless
corridor driven from rest is reported as metres of uncertainty, not as millimetres of standing
still. `CovarianceTracker` keeps that per axis of the wall family's frame (x, y, θ) and restarts
the positions, not the speeds, at each keyframe.

The per-match figures come from the correlation itself: a sharp, well supported peak is a few
millimetres, a flat one centimetres, an ambiguous one no measurement at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from service.core.frontend.translation import AxisMatch
from service.core.types import Covariance3, fields_by_name, restore_fields


@dataclass(frozen=True, slots=True)
class CovarianceParams:
    """How a match's shape maps onto standard deviations, and how an unmeasured axis grows."""

    match_sigma_floor_m: float = 0.006  # a sharp, well supported peak
    match_sigma_flat_m: float = 0.04  # added as the peak's contrast goes to zero
    match_support_full: float = 60.0  # weighted points at which support stops helping
    accel_psd_m2_s3: float = 0.05  # white-noise acceleration: speed σ grows √(q·t)
    unknown_speed_sigma_m_s: float = 1.0  # before any match measured it, and at most
    anchored_heading_sigma_deg: float = 0.15  # a heading measured on the building's walls
    relative_heading_sigma_deg: float = 0.5  # per scan, a heading from directions / prediction

    # Pickled by name (a session checkpoint keeps it): a later version may add fields.
    def __getstate__(self) -> dict[str, object]:
        return fields_by_name(self)

    def __setstate__(self, state: object) -> None:
        restore_fields(self, state if isinstance(state, dict) else {}, CovarianceParams())


def axis_sigma_m(match: AxisMatch, params: CovarianceParams) -> float | None:
    """σ of one measured axis, or None where the match does not constrain it."""
    if match.ambiguous:
        return None
    support = min(max(match.support / params.match_support_full, 1e-3), 1.0)
    flat = params.match_sigma_flat_m * (1.0 - min(max(match.sharpness, 0.0), 1.0))
    return (params.match_sigma_floor_m + flat) / math.sqrt(support)


@dataclass(slots=True)
class AxisCovariance:
    """Position (relative to the latest keyframe) and speed covariance along one axis."""

    pos_var_m2: float = 0.0
    pos_speed_cov_m2_s: float = 0.0
    speed_var_m2_s2: float = 1.0

    def predict(self, dt_s: float, accel_psd_m2_s3: float, max_speed_var_m2_s2: float) -> None:
        """Carried over `dt_s` at the current speed, the speed's error integrating."""
        q, t = accel_psd_m2_s3, dt_s
        self.pos_var_m2 += (
            2.0 * t * self.pos_speed_cov_m2_s + t * t * self.speed_var_m2_s2 + q * t**3 / 3.0
        )
        self.pos_speed_cov_m2_s += t * self.speed_var_m2_s2 + q * t * t / 2.0
        self.speed_var_m2_s2 += q * t
        if self.speed_var_m2_s2 > max_speed_var_m2_s2:
            # A robot's speed is no more unknown than its range: scaled down, still PSD.
            scale = math.sqrt(max_speed_var_m2_s2 / self.speed_var_m2_s2)
            self.pos_speed_cov_m2_s *= scale
            self.speed_var_m2_s2 = max_speed_var_m2_s2

    def measure(self, sigma_m: float) -> None:
        """A match measured the position with σ `sigma_m`.

        The speed learns from it as in a Kalman update. The position keeps the match's own
        variance, not the fused one: consecutive matches share the local map's errors, so
        fusing them as independent would claim a precision no single match has.
        """
        r = sigma_m * sigma_m
        s = self.pos_var_m2 + r
        if s > 0.0:
            self.speed_var_m2_s2 -= self.pos_speed_cov_m2_s**2 / s
            self.pos_speed_cov_m2_s *= r / s
        self.pos_var_m2 = r

    def measure_speed(self, sigma_m_s: float) -> None:
        """A match measured the motion since the previous scan, i.e. the speed, with σ
        `sigma_m_s`: the speed learns from it, the position relative to the keyframe does not
        (what the estimate missed before is still missed: no state correction goes with it)."""
        r = sigma_m_s * sigma_m_s
        s = self.speed_var_m2_s2 + r
        if s > 0.0:
            self.pos_speed_cov_m2_s *= r / s
            self.speed_var_m2_s2 *= r / s

    def restart(self) -> None:
        """A new keyframe: the position is measured from here; the speed stays as known."""
        self.pos_var_m2 = 0.0
        self.pos_speed_cov_m2_s = 0.0


@dataclass(slots=True)
class CovarianceTracker:
    """Covariance of the current pose relative to the latest keyframe, per frame axis (x, y, θ)."""

    params: CovarianceParams = field(default_factory=CovarianceParams)
    along_x: AxisCovariance = field(default_factory=AxisCovariance)  # the wall family's axes
    along_y: AxisCovariance = field(default_factory=AxisCovariance)
    var_theta: float = 0.0
    frame_rad: float = 0.0  # the axes the matches measure along (the map's, or a wing's)
    # The heading's variance gathered since the walls last measured it (0 when they did), now
    # and at the latest keyframe: a heading anchored again on walls measures the keyframe's
    # drift too, so the motion since that keyframe carries it.
    drift_var_theta: float = 0.0
    keyframe_drift_var_theta: float = 0.0

    def __post_init__(self) -> None:
        start = self.params.unknown_speed_sigma_m_s**2
        self.along_x.speed_var_m2_s2 = self.along_y.speed_var_m2_s2 = start

    # Pickled by name: a checkpoint of an older version (a σ per axis, no speeds) restarts.
    def __getstate__(self) -> dict[str, object]:
        return fields_by_name(self)

    def __setstate__(self, state: object) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # slots pickled by `object` (older)
            state = state[1]
        values = state if isinstance(state, dict) else {}
        params = values.get("params")
        self.params = params if isinstance(params, CovarianceParams) else CovarianceParams()
        fresh = CovarianceTracker(self.params)
        for name in (
            "along_x",
            "along_y",
            "var_theta",
            "frame_rad",
            "drift_var_theta",
            "keyframe_drift_var_theta",
        ):
            value = values.get(name)
            expected = type(getattr(fresh, name))
            setattr(self, name, value if isinstance(value, expected) else getattr(fresh, name))

    def predicted_sigmas_m(self, dt_s: float, frame_rad: float) -> tuple[float, float]:
        """σ of the pose predicted `dt_s` ahead, relative to the latest keyframe, along the axes
        of the wall family at `frame_rad` (isotropic, the larger, if those are not the
        tracker's). Nothing is changed: this is what the search window and prior read."""
        q, t = self.params.accel_psd_m2_s3, max(dt_s, 0.0)
        # `AxisCovariance.predict`'s variance, summed in this order: the prior it sets is a
        # decision input, and another order moves its last bits (a tuning ring's map with it).
        x, y = (
            math.sqrt(
                a.pos_var_m2
                + 2.0 * t * a.pos_speed_cov_m2_s
                + t * t * a.speed_var_m2_s2
                + q * t**3 / 3.0
            )
            for a in (self.along_x, self.along_y)
        )
        return (x, y) if frame_rad == self.frame_rad else (max(x, y), max(x, y))

    def restart(self) -> None:
        """A new keyframe: the following poses are measured against it."""
        self.along_x.restart()
        self.along_y.restart()
        self.var_theta = 0.0
        self.keyframe_drift_var_theta = self.drift_var_theta

    def update(
        self,
        sigma_x_m: float | None,
        sigma_y_m: float | None,
        heading_anchored: bool,
        *,
        dt_s: float,
        frame_rad: float = 0.0,
        steps: tuple[bool, bool] = (False, False),
    ) -> Covariance3:
        """One scan `dt_s` after the previous: each axis is carried, then a measured one
        (σ not None) takes its match's variance; one measured against the previous scan
        (`steps`) measured the motion since it, which teaches the speed only.

        The σ are along the axes of the wall family at `frame_rad`. When those axes change,
        what was carried is kept as the larger of the two (isotropic: no axis is trusted more).
        """
        p = self.params
        if frame_rad != self.frame_rad:
            larger = max(self.along_x, self.along_y, key=lambda a: a.pos_var_m2)
            self.along_x, self.along_y = replace(larger), replace(larger)
            self.frame_rad = frame_rad
        max_speed_var = p.unknown_speed_sigma_m_s**2
        dt = max(dt_s, 0.0)
        for axis, sigma, step in zip(
            (self.along_x, self.along_y), (sigma_x_m, sigma_y_m), steps, strict=True
        ):
            axis.predict(dt, p.accel_psd_m2_s3, max_speed_var)
            if sigma is not None and step:
                if dt > 0.0:
                    axis.measure_speed(math.sqrt(2.0) * sigma / dt)  # two scans' errors
            elif sigma is not None:
                axis.measure(sigma)
        if heading_anchored:
            anchored_var = math.radians(p.anchored_heading_sigma_deg) ** 2
            self.var_theta = anchored_var + self.keyframe_drift_var_theta
            self.drift_var_theta = 0.0
        else:
            relative_var = math.radians(p.relative_heading_sigma_deg) ** 2
            self.var_theta += relative_var
            self.drift_var_theta += relative_var
        return self.covariance()

    def covariance(self) -> Covariance3:
        """Row-major 3×3 (x, y, θ), map axes."""
        var_x, var_y, phi = self.along_x.pos_var_m2, self.along_y.pos_var_m2, self.frame_rad
        if phi == 0.0:
            return (var_x, 0.0, 0.0, 0.0, var_y, 0.0, 0.0, 0.0, self.var_theta)
        c, s = math.cos(phi), math.sin(phi)  # R diag(var_x, var_y) Rᵀ
        xx = c * c * var_x + s * s * var_y
        yy = s * s * var_x + c * c * var_y
        xy = c * s * (var_x - var_y)
        return (xx, xy, 0.0, xy, yy, 0.0, 0.0, 0.0, self.var_theta)
