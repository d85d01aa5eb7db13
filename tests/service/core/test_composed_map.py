"""The map composed from chunks at given corrections (service/core/maps/composed.py)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from service.core.maps.composed import ChunkedMap
from service.core.maps.grid import OccupancyGrid
from service.core.slam import SlamSession
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
        chunks.draw(scan, pose, node)
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
    assert [c.anchor_node for c in chunks.chunks] == [0, 3]
    assert [c.frozen for c in chunks.chunks] == [True, False]
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


def test_scans_go_to_their_nodes_chunk_and_a_frozen_chunk_is_compact() -> None:
    """A scan goes to the chunk of its latest node's stretch (before the first node: a chunk
    never moved); the chunk before a new stretch is frozen: read-only, its tiles in int8 steps,
    and composes as it did while filling (within a step)."""
    chunks = ChunkedMap(0.05, nodes_per_chunk=2)
    nodes = [-1, 0, 0, 1, 2, 3, 3, 4]
    for k, node in enumerate(nodes):
        chunks.draw(_room_scan(2.0 + 0.3 * k, 3.0), Pose2D(2.0 + 0.3 * k, 3.0, 0.0), node)
    assert [(c.anchor_node, c.scans) for c in chunks.chunks] == [(-1, 1), (0, 3), (2, 3), (4, 1)]
    assert chunks.scans == len(nodes)
    first = chunks.chunks[1].grid
    assert first.memory_bytes() == (first.tile_count + 1) * 64 * 64 + first._index.nbytes
    with pytest.raises(ValueError, match="read-only"):
        first.integrate(_room_scan(5.0, 3.0), Pose2D(5.0, 3.0, 0.0))
    filling = OccupancyGrid(0.05)
    for k in (1, 2, 3):
        filling.integrate(_room_scan(2.0 + 0.3 * k, 3.0), Pose2D(2.0 + 0.3 * k, 3.0, 0.0))
    (was, i0, j0), (now, fi0, fj0) = filling.log_odds(), first.log_odds()
    assert (i0, j0) == (fi0, fj0)
    np.testing.assert_array_equal(now != 0, was != 0)  # the same cells known
    assert np.abs(now - was).max() <= 3.5 / 127 / 2 + 1e-6
    # Corrections for nodes 0..4: the first chunk (-1) never moves; chunk 2's anchor moves.
    still = chunks.compose(IDENTITY)
    moved = chunks.compose([Pose2D(0.0, 0.0, 0.0)] * 2 + [Pose2D(1.0, 0.0, 0.0)] * 3)
    assert moved.width == still.width + 20


def test_a_session_standing_still_holds_no_more_map() -> None:
    """Scans drawn without travel (no new node) go into the same chunk: the map's memory stays
    (no per-scan store), and drawing it costs the same."""
    session = SlamSession(map_resolution_m=0.05)
    scan = _room_scan(4.0, 3.0)
    for _ in range(20):
        session.process(scan)
    held = session.map_bytes
    for _ in range(200):
        session.process(scan)
    assert session.backend.node_count == 1
    assert session.map_bytes == held
    assert session.map_image().occupancy.size > 0


def test_a_session_without_loop_closure_never_imports_gtsam() -> None:
    code = (
        "import sys\n"
        "from service.app.mapper import Engine, LocalMapper\n"
        "LocalMapper(Engine(loop_closure=False), False, 0.05)\n"
        "assert 'gtsam' not in sys.modules, 'gtsam imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
