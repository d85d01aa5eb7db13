"""The walls' angle of a scan (`service.core.frontend.heading`), the matcher's heading prior's
measurement (`walls.measure`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.frontend.heading import heading_scores, measure_heading, wrap_quarter
from service.core.types import FloatArray, LaserScan, Pose2D

Segments = np.ndarray  # (S, 4): x0, y0, x1, y1


def box(x0: float, y0: float, x1: float, y1: float) -> list[tuple[float, float, float, float]]:
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def room() -> Segments:
    """A 10 m × 6 m room with a pillar and a cupboard."""
    segs = box(-5.0, -3.0, 5.0, 3.0) + box(1.0, 0.8, 1.4, 1.2) + box(-3.5, -3.0, -2.0, -2.4)
    segs += [(2.5, -3.0, 2.5, -1.8)]  # a partition stub
    return np.array(segs, dtype=np.float64)


def cast(segs: Segments, pose: Pose2D, *, fov_deg: float = 270.0, beams: int = 1081) -> LaserScan:
    """Ray-cast `segs` from `pose` without noise (laser frame = robot frame)."""
    range_max_m = 30.0
    inc = math.radians(fov_deg) / (beams - 1)
    a_min = -math.radians(fov_deg) / 2.0
    ang = pose.theta_rad + a_min + inc * np.arange(beams)
    d = np.stack((np.cos(ang), np.sin(ang)), axis=1)  # (B, 2)
    p0 = segs[:, :2]
    e = segs[:, 2:] - p0  # (S, 2)
    w = p0 - np.array([pose.x_m, pose.y_m])  # (S, 2)
    # Solve pose + t·d = p0 + u·e for every (beam, segment).
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / den
        u = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / den
    hit = (np.abs(den) > 1e-12) & (t > 0.0) & (u >= 0.0) & (u <= 1.0)
    r = np.where(hit, t, np.inf).min(axis=1)
    r = np.where(np.isfinite(r) & (r < range_max_m), r, range_max_m)
    return LaserScan(0, a_min, inc, r, 0.02, range_max_m)


@pytest.mark.parametrize("heading_deg", list(range(0, 360, 7)))
def test_the_walls_angle_every_7_degrees(heading_deg: int) -> None:
    truth = math.radians(heading_deg)
    scan = cast(room(), Pose2D(0.3, -0.4, truth))
    m = measure_heading(scan.points_xy_m(), math.radians(0.1), 0.02)
    # Rotating laser points by the heading aligns them with the map: angle ≡ heading mod 90°.
    err = math.degrees(float(wrap_quarter(m.angle_rad - truth)))
    assert abs(err) < 0.2
    assert m.peak_fraction > 0.15  # decisive enough for a prior (`WallOptions`)


def _naive_scores(pts: FloatArray, angles: FloatArray, bin_m: float, soft: bool) -> FloatArray:
    out = np.empty(angles.shape[0])
    for k, a in enumerate(angles):
        c, s = math.cos(a), math.sin(a)
        total = 0.0
        for coord in (c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]):
            u = coord / bin_m
            lo = math.floor(float(u.min())) - 1
            i0 = np.floor(u - lo).astype(np.int64)
            if soft:
                f = (u - lo) - i0
                h = np.bincount(i0, 1.0 - f, i0.max() + 2) + np.bincount(i0 + 1, f, i0.max() + 2)
            else:
                h = np.bincount(i0).astype(np.float64)
            total += float((h * h).sum())
        out[k] = total
    return out


@pytest.mark.parametrize("soft", [False, True])
def test_heading_scores_match_naive_histograms(soft: bool) -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        pts = rng.normal(0.0, rng.uniform(0.5, 10.0), (int(rng.integers(5, 300)), 2))
        angles = rng.uniform(-0.8, 0.8, int(rng.integers(1, 40)))
        got = heading_scores(pts, angles, 0.05, soft=soft)
        np.testing.assert_allclose(got, _naive_scores(pts, angles, 0.05, soft), rtol=1e-9)
