"""The paper's method read literally (IROS 2010, docs/paper-frontend.md): the benchmark baseline.

Deliberately straightforward and slow, as the paper describes it:
- thinning with a Python loop (keep a point when it is >= 0.05 m from the last kept one);
- heading: rotate by every angle in [0°, 180°) at 0.1°, project on x, 0.02 m histogram, hmax(θ);
- absolute heading: the first major wall is the standard direction; when the relative angle jumps
  by more than ±45°, the major wall switched to a perpendicular one;
- translation against the previous scan only: shift the current scan by 0.005 m steps over
  ±0.8 m, re-histogram it with 0.03 m bins for every shift, correlate, take the argmax (x and y
  independently); no prediction, no refinement, no ambiguity checks.

Same interface as the front ends (process / reset), so benchmarks can swap them.
"""

from __future__ import annotations

import math

import numpy as np

from clients.wire import PoseFlag
from service.core.types import FloatArray, LaserScan, Pose2D, PoseEstimate, wrap_angle

THINNING_M = 0.05
HEADING_STEP_DEG = 0.1
HEADING_BIN_M = 0.02
SWITCH_DEG = 45.0
TRANS_BIN_M = 0.03
TRANS_STEP_M = 0.005
TRANS_WINDOW_M = 0.8


def thin_loop(points: FloatArray) -> FloatArray:
    kept = [points[0]]
    for p in points[1:]:
        if math.hypot(p[0] - kept[-1][0], p[1] - kept[-1][1]) >= THINNING_M:
            kept.append(p)
    return np.array(kept)


def relative_wall_angle(points: FloatArray) -> float:
    """θ in [0, π) maximising hmax(θ) of the x projection of the points rotated by θ."""
    best_theta, best_h = 0.0, -1
    for k in range(round(180.0 / HEADING_STEP_DEG)):
        theta = math.radians(k * HEADING_STEP_DEG)
        c, s = math.cos(theta), math.sin(theta)
        proj = points[:, 0] * c - points[:, 1] * s
        idx = np.floor(proj / HEADING_BIN_M).astype(np.int64)
        h = int(np.bincount(idx - idx.min()).max())
        if h > best_h:
            best_theta, best_h = theta, h
    return best_theta


def correlate_literal(ref: FloatArray, cur: FloatArray) -> float:
    """argmax over shifts of Σ_i h_ref(i) h_cur(i, shift), re-histogramming every shift."""
    lo = min(float(ref.min()), float(cur.min())) - TRANS_WINDOW_M - TRANS_BIN_M
    hi = max(float(ref.max()), float(cur.max())) + TRANS_WINDOW_M + TRANS_BIN_M
    n = math.ceil((hi - lo) / TRANS_BIN_M) + 1
    h_ref = np.bincount(np.floor((ref - lo) / TRANS_BIN_M).astype(np.int64), minlength=n)
    best, best_e = 0.0, -1.0
    n_half = round(TRANS_WINDOW_M / TRANS_STEP_M)
    for k in range(-n_half, n_half + 1):
        shift = k * TRANS_STEP_M
        h_cur = np.bincount(
            np.floor((cur + shift - lo) / TRANS_BIN_M).astype(np.int64), minlength=n
        )
        e = float(h_ref @ h_cur[:n])
        if e > best_e:
            best, best_e = shift, e
    return best


class PaperBaseline:
    """Scan-to-previous-scan matching exactly as the paper describes it."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._pose: Pose2D | None = None
        self._rel: float | None = None  # relative angle of the major wall at the last scan
        self._offset = 0.0  # heading = relative angle + offset (k·90° after switches)
        self._prev_map: FloatArray | None = None

    def process(self, scan: LaserScan) -> PoseEstimate:
        pts = scan.points_xy_m()
        if pts.shape[0] < 10:
            pose = self._pose or Pose2D(0.0, 0.0, 0.0)
            return PoseEstimate(scan.stamp_ns, pose, 0.0, PoseFlag.DEGENERATE)
        pts = thin_loop(pts)
        rel = relative_wall_angle(pts)
        flags = PoseFlag.NONE
        if self._rel is None:
            # The first major wall is the standard direction (the map y axis, as in the paper):
            # rotating the scan by `rel` puts it along y, so the first heading is `rel`.
            self._offset = 0.0
        else:
            jump = math.degrees(rel - self._rel)
            # The ±45° rule (and wrapping of the 180° range).
            while jump > SWITCH_DEG:
                self._offset -= math.pi / 2.0
                jump -= 90.0
                flags |= PoseFlag.HEADING_SWITCH
            while jump < -SWITCH_DEG:
                self._offset += math.pi / 2.0
                jump += 90.0
                flags |= PoseFlag.HEADING_SWITCH
        self._rel = rel
        theta = wrap_angle(rel + self._offset)
        c, s = math.cos(theta), math.sin(theta)
        cur = np.column_stack((c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]))
        if self._pose is None or self._prev_map is None:
            x, y = 0.0, 0.0
        else:
            ref = self._prev_map
            x = self._pose.x_m + correlate_literal(ref[:, 0], cur[:, 0] + self._pose.x_m)
            y = self._pose.y_m + correlate_literal(ref[:, 1], cur[:, 1] + self._pose.y_m)
        self._pose = Pose2D(x, y, theta)
        self._prev_map = cur + np.array([x, y])
        return PoseEstimate(scan.stamp_ns, self._pose, 1.0, flags)
