"""The map composed from chunks at given corrections (service/core/maps/composed.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.maps.composed import ChunkedMap
from service.core.maps.grid import OccupancyGrid
from service.core.types import LaserScan, Pose2D


def _room_scan(x_m: float, y_m: float) -> LaserScan:
    """A 1,081-beam scan from (x, y), heading 0, inside a 10 m x 6 m room."""
    angles = np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, 1081)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (10.0 - x_m) / c, np.where(c < 0, -x_m / c, np.inf))
        ty = np.where(s > 0, (6.0 - y_m) / s, np.where(s < 0, -y_m / s, np.inf))
    return LaserScan(
        stamp_ns=0,
        angle_min_rad=float(angles[0]),
        angle_increment_rad=float(angles[1] - angles[0]),
        range_min_m=0.02,
        range_max_m=30.0,
        ranges_m=np.minimum(tx, ty),
    )


def _chunked(poses: list[Pose2D], per_chunk: int) -> tuple[ChunkedMap, OccupancyGrid]:
    chunks = ChunkedMap(0.05, nodes_per_chunk=per_chunk)
    grid = OccupancyGrid(0.05)
    for node, pose in enumerate(poses):
        scan = _room_scan(pose.x_m, pose.y_m)
        chunks.add_node(node, pose, scan)
        grid.integrate(scan, pose)
    return chunks, grid


POSES = [Pose2D(2.0 + 0.3 * k, 3.0, 0.0) for k in range(6)]
IDENTITY = [Pose2D(0.0, 0.0, 0.0)] * len(POSES)


def test_one_chunk_at_no_correction_is_the_grid() -> None:
    chunks, grid = _chunked(POSES, per_chunk=10)
    image, expected = chunks.compose(IDENTITY), grid.snapshot()
    np.testing.assert_array_equal(image.occupancy, expected.occupancy)
    assert (image.origin_x_m, image.origin_y_m) == (expected.origin_x_m, expected.origin_y_m)


def test_a_correction_moves_its_chunk_only() -> None:
    chunks, _ = _chunked(POSES, per_chunk=3)  # nodes 0-2 and 3-5
    assert len(chunks.chunks) == 2
    still = chunks.compose(IDENTITY)
    # Both chunks moved by the same whole-cell shift: the same map, shifted.
    shift = [Pose2D(0.5, -0.25, 0.0)] * len(POSES)
    moved = chunks.compose(shift)
    np.testing.assert_array_equal(moved.occupancy, still.occupancy)
    assert moved.origin_x_m - still.origin_x_m == pytest.approx(0.5)
    assert moved.origin_y_m - still.origin_y_m == pytest.approx(-0.25)
    # The second chunk alone moved 1 m: the walls it saw are doubled, the map grows.
    second = [Pose2D(0.0, 0.0, 0.0)] * 3 + [Pose2D(1.0, 0.0, 0.0)] * 3
    split = chunks.compose(second)
    assert split.width == still.width + 20
    # A small rotation keeps the map whole (inverse warp: no holes), nearly unchanged.
    turned = chunks.compose([Pose2D(0.0, 0.0, math.radians(0.5))] * len(POSES))
    known_still = int(np.count_nonzero(still.occupancy >= 0))
    known_turned = int(np.count_nonzero(turned.occupancy >= 0))
    assert abs(known_turned - known_still) < 0.02 * known_still
    # A quarter turn: the map turned, every known cell kept (nearest cell, no holes).
    quarter = chunks.compose([Pose2D(0.0, 0.0, math.pi / 2)] * len(POSES))
    assert abs(quarter.width - still.height) <= 2
    assert abs(quarter.height - still.width) <= 2
    known_quarter = int(np.count_nonzero(quarter.occupancy >= 0))
    assert abs(known_quarter - known_still) < 0.02 * known_still
