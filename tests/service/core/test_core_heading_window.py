"""The windowed coarse heading search against the whole-range one, and the coarse-curve reuse."""

from __future__ import annotations

import math

import numpy as np

from service.core.frontend.heading import QUARTER, measure_heading
from service.core.types import FloatArray


def _room(rng: np.random.Generator, heading_rad: float) -> FloatArray:
    """Points on the walls of a 6 m × 4 m room with clutter, seen at `heading_rad`."""
    t = rng.uniform(0.0, 1.0, 400)
    walls = np.concatenate(
        [
            np.column_stack((-3.0 + 6.0 * t[:100], np.full(100, -2.0))),
            np.column_stack((-3.0 + 6.0 * t[100:200], np.full(100, 2.0))),
            np.column_stack((np.full(100, -3.0), -2.0 + 4.0 * t[200:300])),
            np.column_stack((np.full(100, 3.0), -2.0 + 4.0 * t[300:])),
        ]
    )
    walls += rng.normal(0.0, 0.01, walls.shape)
    clutter = rng.uniform(-2.5, 2.5, (60, 2))
    pts = np.concatenate((walls, clutter))
    c, s = math.cos(-heading_rad), math.sin(-heading_rad)  # map -> laser frame
    return np.column_stack((c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]))


def _measure(pts: FloatArray, pred: float | None, half_rad: float = QUARTER / 2.0) -> float:
    m = measure_heading(
        pts, pred, math.radians(2.0), math.radians(0.1), 0.02, coarse_half_rad=half_rad
    )
    return m.angle_rad


def test_windowed_coarse_search_finds_the_same_heading() -> None:
    rng = np.random.default_rng(3)
    for _ in range(10):
        heading = float(rng.uniform(-math.pi, math.pi))
        pts = _room(rng, heading)
        pred = heading + math.radians(float(rng.uniform(-3.0, 3.0)))
        full = _measure(pts, pred)
        windowed = _measure(pts, pred, math.radians(8.0))
        assert windowed == full  # same coarse angles and scores near the prediction
        err = (windowed - heading + QUARTER / 2.0) % QUARTER - QUARTER / 2.0
        assert abs(err) < math.radians(0.3)


def test_second_measurement_reuses_the_coarse_curve() -> None:
    rng = np.random.default_rng(4)
    pts = _room(rng, 0.4)
    args = (math.radians(2.0), math.radians(0.1), 0.02)
    first = measure_heading(pts, 0.45, *args)
    free = measure_heading(pts, None, *args)
    reused = measure_heading(pts, None, *args, same_points=first)
    assert reused.angle_rad == free.angle_rad
    assert reused.peak_fraction == free.peak_fraction
    assert reused.prior_offset_rad == free.prior_offset_rad == 0.0
