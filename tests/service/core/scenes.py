"""Simulated rooms, scans and submaps for the core's tests (imported as `scenes`: pytest puts
this folder on the path for the tests in it)."""

from __future__ import annotations

import math

import numpy as np

from sensor_agent.sim.world import LaserModel, World, simulate_scan
from service.core.frontend.likelihood import LikelihoodGrid
from service.core.frontend.scan_matcher import MatcherParams, ScanMatcherFrontEnd, surface_in_map
from service.core.types import LaserScan, Pose2D

MODEL = LaserModel.utm30lx()
PARAMS = MatcherParams()


def world_of(segments: list[list[float]], width_m: float, height_m: float) -> World:
    """A world of these wall segments ([x0, y0, x1, y1], metres) and nothing else."""
    return World(
        seed=0,
        size="test",
        width_m=width_m,
        height_m=height_m,
        corridor_width_m=2.0,
        segments_m=np.array(segments, dtype=np.float64),
        loop_xy_m=np.zeros((0, 2)),
        free_raster=np.ones((1, 1), dtype=bool),
    )


# An 8 × 6 m room with a box and a stub wall.
ROOM = world_of(
    [
        [0, 0, 8, 0], [8, 0, 8, 6], [8, 6, 0, 6], [0, 6, 0, 0],
        [5, 4, 5.6, 4], [5.6, 4, 5.6, 4.8], [5.6, 4.8, 5, 4.8], [5, 4.8, 5, 4],
        [2, 0, 2, 1.5],
    ],
    60.0,
    60.0,
)  # fmt: skip
# 180 m long, 2 m wide: no end in range
CORRIDOR = world_of([[-90, 0, 90, 0], [-90, 2, 90, 2]], 60.0, 60.0)


def scan_of(world: World, pose: Pose2D, rng: np.random.Generator, stamp_ns: int = 0) -> LaserScan:
    """One UTM-30LX scan of `world` from `pose`."""
    sample = simulate_scan(world, pose, MODEL, rng)
    return LaserScan(
        stamp_ns, MODEL.angle_min_rad, MODEL.angle_increment_rad, sample.ranges_m,
        MODEL.range_min_m, MODEL.range_max_m,
    )  # fmt: skip


def grid_of(scans: list[tuple[LaserScan, Pose2D]]) -> LikelihoodGrid:
    """A submap built as the front end builds one (surfaces), at known poses."""
    grid = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m)
    for scan, pose in scans:
        grid.insert(surface_in_map(scan.points_xy_m(), pose, PARAMS))
    return grid


def matched_points(scan: LaserScan) -> np.ndarray:
    """The points of `scan` the front end matches (within reach, one per voxel)."""
    return ScanMatcherFrontEnd()._points(scan, scan.points_xy_m())


def bad_scan(kind: str, stamp_ns: int, n: int) -> LaserScan:
    """A scan no front end can match, of this kind, with `n` beams where the kind has any."""
    ranges = {
        "empty": np.zeros(0),
        "max_range": np.full(n, MODEL.range_max_m),
        "nan": np.full(n, np.nan),
        "one_beam": np.array([2.0]),
        "inf": np.full(n, np.inf),
        "huge": np.full(n, 1e300),
    }[kind]
    range_max_m = math.inf if kind == "huge" else MODEL.range_max_m  # (1e300 is then valid)
    return LaserScan(
        stamp_ns, MODEL.angle_min_rad, MODEL.angle_increment_rad, ranges, 0.1, range_max_m
    )
