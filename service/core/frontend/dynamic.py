"""Points on things that moved in: where the previous scan's beams passed through.

A person walking beside the robot moves with it. In a corridor whose own walls say nothing
about the motion along it, that person's few points are the only along-axis evidence, and
they vote for standing still: each such scan cut the measured step and the carried speed
(a 120 m plain corridor mapped 34 m short). Static geometry cannot appear in space the
previous scan saw through, so a point there is a moving object and takes no part in the
match or the map.

The previous scan, and a keyframe about a metre back (a person who walks beside the robot
is in the previous scan too), are tested. The test is one-sided: a point is rejected only
when every beam of that scan passing within a margin of it reached clearly beyond it. The
margin covers the prediction's error along the beam and a share of the range (grazing
surfaces, the heading's error far out); a beam without a return counts as free only up to a
few metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.types import FloatArray, Pose2D, rotate_points


@dataclass(frozen=True, slots=True)
class SeenThroughParams:
    margin_m: float = 0.3  # + this along the beam (the prediction's error) ...
    margin_ratio: float = 0.05  # ... and this share of the range
    neighbour_beams: int = 1  # every beam within ± this many must reach beyond the point ...
    lateral_margin_m: float = 0.1  # ... and every beam passing within this of it ...
    max_window_beams: int = 16  # ... up to ± this many (near points: ±4°, 4 cm at 0.6 m)
    keyframes: int = 3  # the oldest of this many newest keyframes is tested too
    # A beam without a return passed freely this far: anything nearer returns the laser
    # (a plain corridor's beams along it end beyond the range, and a person in front of the
    # robot is seen only against them). Glass returns nothing either way.
    no_return_reach_m: float = 5.0


@dataclass(frozen=True, slots=True)
class FreeSpace:
    """What one scan saw free: per beam, how far (`free_reach_m`), from `pose`, with the
    windowed minima precomputed (a keyframe's serve many later scans)."""

    pose: Pose2D
    angle_min_rad: float
    increment_rad: float
    # levels[j, i] = min(reach[i : i + 2**j]) (a sparse table; unknown reads 0, no evidence).
    levels: FloatArray

    # Checkpoints keep the reach (level 0) and rebuild the rest: 11 levels are 95 KB a scan.
    def __getstate__(self) -> dict[str, object]:
        return {
            "pose": self.pose,
            "angle_min_rad": self.angle_min_rad,
            "increment_rad": self.increment_rad,
            "reach": self.levels[0],
            "widest": 1 << (self.levels.shape[0] - 1),
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        object.__setattr__(self, "pose", state["pose"])
        object.__setattr__(self, "angle_min_rad", state["angle_min_rad"])
        object.__setattr__(self, "increment_rad", state["increment_rad"])
        object.__setattr__(
            self, "levels", _sparse_table(np.asarray(state["reach"]), state["widest"])
        )

    @classmethod
    def of(  # noqa: PLR0917 - the scan's pose, ranges and geometry
        cls,
        pose: Pose2D,
        ranges_m: FloatArray,
        range_min_m: float,
        range_max_m: float,
        angle_min_rad: float,
        increment_rad: float,
        params: SeenThroughParams,
    ) -> FreeSpace:
        reach = np.nan_to_num(free_reach_m(ranges_m, range_min_m, range_max_m, params), nan=0.0)
        return cls(
            pose,
            angle_min_rad,
            increment_rad,
            _sparse_table(reach, 2 * params.max_window_beams + 1),
        )

    def matches(self, angle_min_rad: float, increment_rad: float, beams: int) -> bool:
        return (self.angle_min_rad, self.increment_rad) == (angle_min_rad, increment_rad) and (
            self.levels.shape[1] == beams
        )


_FLOOR_LOG2 = np.floor(np.log2(np.maximum(np.arange(4097), 1))).astype(np.int64)  # windows


def _sparse_table(values: FloatArray, widest: int) -> FloatArray:
    """(L, n): row j holds min(values[i : i + 2**j]) (as far as the array goes), for windows
    up to `widest`."""
    n = values.shape[0]
    levels = [values]
    step = 1
    while 2 * step <= min(n, widest):
        prev = levels[-1]
        nxt = prev.copy()
        nxt[: n - step] = np.minimum(prev[: n - step], prev[step:])
        levels.append(nxt)
        step *= 2
    return np.stack(levels)


def free_reach_m(
    ranges_m: FloatArray, range_min_m: float, range_max_m: float, params: SeenThroughParams
) -> FloatArray:
    """How far each beam of a scan saw free space (NaN: unknown, a beam blocked at the
    sensor). Without a return (NaN, or at or beyond `range_max_m`): `no_return_reach_m`."""
    r = np.asarray(ranges_m, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        no_return = ~np.isfinite(r) | (r >= range_max_m)
        reach = np.where(no_return, params.no_return_reach_m, r)
        reach[~no_return & (r < max(range_min_m, 1e-6))] = np.nan
    return reach


def seen_through(
    points_laser_m: FloatArray, pose: Pose2D, free: FreeSpace, params: SeenThroughParams
) -> npt.NDArray[np.bool_]:
    """Which of the current scan's points (laser frame, at `pose`) lie where the scan of
    `free` saw free space."""
    n_pts = points_laser_m.shape[0]
    n_beams = free.levels.shape[1]
    out = np.zeros(n_pts, dtype=bool)
    if n_pts == 0 or n_beams < 3 or free.increment_rad <= 0.0:
        return out
    # Into that scan's laser frame.
    rel = free.pose.between(pose)
    xy = rotate_points(points_laser_m, rel.theta_rad)
    x, y = xy[:, 0] + rel.x_m, xy[:, 1] + rel.y_m
    r = np.hypot(x, y)
    beam = np.rint((np.arctan2(y, x) - free.angle_min_rad) / free.increment_rad).astype(np.int64)
    # The beams within `lateral_margin_m` of the point (at least ± `neighbour_beams`): an edge,
    # or a point the pose's error moves sideways, has a beam of that scan that hit it.
    with np.errstate(divide="ignore"):
        half = np.ceil(params.lateral_margin_m / (np.maximum(r, 1e-3) * free.increment_rad))
    widest = 1 << (free.levels.shape[0] - 1)  # the table's widest window serves up to ±this
    cap = min(params.max_window_beams, widest, (_FLOOR_LOG2.shape[0] - 2) // 2)
    half = np.clip(half, params.neighbour_beams, cap).astype(np.int64)
    lo, hi = beam - half, beam + half
    inside = (lo >= 0) & (hi < n_beams)
    if not inside.any():
        return out
    idx = np.flatnonzero(inside)
    lo, hi = lo[idx], hi[idx]
    # min over [lo, hi]: two overlapping power-of-two windows of the sparse table.
    level = _FLOOR_LOG2[hi - lo + 1]
    flat = free.levels.ravel()
    row = level * n_beams
    reach = np.minimum(flat[row + lo], flat[row + hi - (1 << level) + 1])
    out[idx] = reach > r[idx] * (1.0 + params.margin_ratio) + params.margin_m
    return out
