"""Deterministic synthetic indoor worlds, a 2D ray caster, laser beam models and trajectories.

Everything here is pure numpy (no IO) and deterministic by seed; tests, the emulator, the demo and
the benchmarks all build their data from it.

Public API (other modules code against these names):

- ``generate_building(seed, size="paper" | "small") -> World``: a Manhattan building (corridors
  forming loops, rooms with open and closed doors, pillars, clutter boxes) with a few
  non-Manhattan walls (chamfered corridor corners, a slanted lobby wall, angled partitions).
  ``"paper"`` is about 190 m x 50 m like the paper's building; ``"small"`` is 48 m x 24 m.
- ``World.segments_m``: (N, 4) float64 wall segments ``x0, y0, x1, y1`` in metres.
- ``World.raycast(pose, angles_rad, max_range_m) -> (B,) float64`` ranges, ``inf`` where no wall
  is hit within ``max_range_m``. ``pose`` is ``(x_m, y_m, theta_rad)`` (a ``Pose2D`` works);
  angles are in the laser frame (x forward, y left, counter-clockwise).
- ``LaserModel`` with ``LaserModel.utm30lx()``, ``.sick_lms200()``, ``.urg04lx()``.
- ``simulate_scan(world, pose, model, rng) -> ScanSample``: ``ranges_mm`` (uint32, device error
  codes below the minimum range for invalid beams, PROTOCOLS.md A.5) and ``ranges_m`` (float64,
  NaN for invalid beams); ``apply_beam_model(true_m, model, rng)`` is its second half (noise and
  codes on given noise-free ranges).
- ``generate_trajectory(world, seed, spacing_m=0.3, ...) -> Trajectory``: ground-truth poses along
  the building's corridor loop (a loop of >= 400 m on the paper building), one pose every
  ``spacing_m`` of travel or 10 degrees of rotation, smooth turns; the last pose closes the loop.
- ``RobotMotion(world, seed).pose_at(t_s)``: the same kind of loop as a continuous-time motion
  (about 0.7 m/s), looping forever, for live simulation at 40 Hz.

Frames: world x/y in metres, theta counter-clockwise in radians; the laser frame is the robot frame.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Final, Literal

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
PoseLike = Sequence[float]  # (x_m, y_m, theta_rad); Pose2D is a NamedTuple and fits
BuildingSize = Literal["paper", "small"]

RASTER_RES_M: Final = 0.05  # floor-plan raster; every Manhattan coordinate is a multiple of it
_WALL_INSET_M: Final = 0.10  # rooms are carved this far inside their outline: 0.1-0.2 m walls
_EPS: Final = 1e-9


class SimError(Exception):
    """Base class of the simulator's errors (bad parameters)."""


# --------------------------------------------------------------------------------------------
# World
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class World:
    """A synthetic building: wall segments plus the corridor loop trajectories follow.

    ``segments_m`` is (N, 4) float64 ``x0, y0, x1, y1``. ``loop_xy_m`` is the (K, 2) closed
    corridor centre-line polygon (counter-clockwise, corners only). ``free_raster`` is the floor
    plan at ``RASTER_RES_M`` (row i = y in [i*res, (i+1)*res), True = free); it is approximate near
    the non-Manhattan walls and only meant for clearance checks and ground-truth pictures.
    """

    seed: int
    size: str
    width_m: float
    height_m: float
    corridor_width_m: float
    segments_m: FloatArray
    loop_xy_m: FloatArray
    free_raster: BoolArray = field(repr=False)
    _seg_a: FloatArray = field(init=False, repr=False)
    _seg_e: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        seg = np.ascontiguousarray(self.segments_m, dtype=np.float64)
        if seg.ndim != 2 or seg.shape[1] != 4:
            raise SimError(f"segments_m must be (N, 4), got {seg.shape}")
        object.__setattr__(self, "segments_m", seg)
        object.__setattr__(self, "_seg_a", np.ascontiguousarray(seg[:, :2]))
        object.__setattr__(self, "_seg_e", np.ascontiguousarray(seg[:, 2:] - seg[:, :2]))

    @property
    def bounds_m(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the building."""
        return (0.0, 0.0, self.width_m, self.height_m)

    def is_free(self, xy_m: FloatArray) -> BoolArray:
        """(M,) True where the (M, 2) points lie in free space of the floor-plan raster."""
        xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
        j = np.floor(xy[:, 0] / RASTER_RES_M).astype(np.int64)
        i = np.floor(xy[:, 1] / RASTER_RES_M).astype(np.int64)
        h, w = self.free_raster.shape
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        out = np.zeros(xy.shape[0], dtype=bool)
        out[inside] = self.free_raster[i[inside], j[inside]]
        return out

    def clearance_ok(self, xy_m: FloatArray, radius_m: float) -> BoolArray:
        """(M,) True where a disc of ``radius_m`` around each point is free in the raster."""
        xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
        n = math.ceil(radius_m / RASTER_RES_M)
        g = np.arange(-n, n + 1, dtype=np.float64) * RASTER_RES_M
        ox, oy = np.meshgrid(g, g)
        keep = ox**2 + oy**2 <= radius_m**2
        offsets = np.column_stack((ox[keep], oy[keep]))
        pts = (xy[:, None, :] + offsets[None, :, :]).reshape(-1, 2)
        return np.asarray(self.is_free(pts).reshape(xy.shape[0], -1).all(axis=1), dtype=bool)

    def raycast(
        self, pose: PoseLike, angles_rad: FloatArray, max_range_m: float = 30.0
    ) -> FloatArray:
        """Distance along each beam to the first wall; ``inf`` where none within ``max_range_m``.

        Only segments within ``max_range_m`` of the sensor are considered, and each segment is
        tested only against the beams inside the angular interval it subtends, so the work is
        proportional to the number of wall crossings along the beams, not segments x beams.
        """
        px, py, theta = float(pose[0]), float(pose[1]), float(pose[2])
        angles = np.asarray(angles_rad, dtype=np.float64).reshape(-1)
        n_beams = angles.shape[0]
        ranges = np.full(n_beams, np.inf)
        if n_beams == 0 or self.segments_m.shape[0] == 0:
            return ranges

        # 1. Segments close enough to matter (point-to-segment distance).
        a = self._seg_a - (px, py)
        e = self._seg_e
        ee = np.einsum("ij,ij->i", e, e)
        t = np.clip(-np.einsum("ij,ij->i", a, e) / np.maximum(ee, _EPS), 0.0, 1.0)
        closest = a + t[:, None] * e
        near = np.einsum("ij,ij->i", closest, closest) <= max_range_m * max_range_m
        a = a[near]
        e = e[near]
        if a.shape[0] == 0:
            return ranges
        b = a + e

        # 2. Angular interval of each segment, relative to the sensor heading, in [-pi, pi).
        ang_a = np.arctan2(a[:, 1], a[:, 0]) - theta
        ang_b = np.arctan2(b[:, 1], b[:, 0]) - theta
        d = _wrap(ang_b - ang_a)
        start = _wrap(np.where(d >= 0.0, ang_a, ang_b))
        end = start + np.abs(d)

        rel = _wrap(angles)
        order = np.argsort(rel, kind="stable")
        sorted_rel = rel[order]
        tol = 1e-9
        lo = np.searchsorted(sorted_rel, start - tol, side="left")
        hi = np.searchsorted(sorted_rel, end + tol, side="right")
        # Intervals running past +pi continue at -pi.
        wraps = np.nonzero(end + tol >= math.pi)[0]
        lo2 = np.zeros(wraps.shape[0], dtype=np.int64)
        hi2 = np.searchsorted(sorted_rel, end[wraps] - 2.0 * math.pi + tol, side="right")
        seg_of = np.concatenate((np.arange(a.shape[0]), wraps))
        lo_all = np.concatenate((lo, lo2))
        counts = np.maximum(np.concatenate((hi, hi2)) - lo_all, 0)
        total = int(counts.sum())
        if total == 0:
            return ranges

        # 3. One (segment, beam) pair per beam inside each interval, intersected in one go.
        pair_seg = np.repeat(seg_of, counts)
        offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        pair_beam = order[np.repeat(lo_all, counts) + offsets]
        world_ang = angles[pair_beam] + theta
        dx, dy = np.cos(world_ang), np.sin(world_ang)
        ax, ay = a[pair_seg, 0], a[pair_seg, 1]
        ex, ey = e[pair_seg, 0], e[pair_seg, 1]
        denom = dx * ey - dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = (ax * ey - ay * ex) / denom
            u = (ax * dy - ay * dx) / denom
        ok = (np.abs(denom) > 1e-12) & (dist > 1e-9) & (u >= -1e-9) & (u <= 1.0 + 1e-9)
        np.minimum.at(ranges, pair_beam[ok], dist[ok])
        ranges[ranges > max_range_m] = np.inf
        return ranges


def _wrap(a: FloatArray) -> FloatArray:
    """Wrap angles to [-pi, pi)."""
    return np.asarray((a + math.pi) % (2.0 * math.pi) - math.pi, dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Building generator
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Preset:
    width_m: float
    height_m: float
    margin_m: tuple[float, float]  # building edge to the corridor ring, drawn per side
    middle_corridors: int
    room_width_m: tuple[float, float]


_PRESETS: Final[dict[str, _Preset]] = {
    "paper": _Preset(190.0, 50.0, (6.0, 7.5), 2, (3.0, 7.0)),
    "small": _Preset(48.0, 24.0, (4.5, 5.5), 1, (3.0, 5.5)),
}


def _snap(v: float) -> float:
    return round(v / RASTER_RES_M) * RASTER_RES_M


class _Plan:
    """Floor-plan raster being carved (True = free) plus the explicit non-Manhattan segments."""

    def __init__(self, width_m: float, height_m: float) -> None:
        self.nx = round(width_m / RASTER_RES_M)
        self.ny = round(height_m / RASTER_RES_M)
        self.free = np.zeros((self.ny, self.nx), dtype=bool)
        self.extra_segments: list[tuple[float, float, float, float]] = []

    def rect(self, x0: float, y0: float, x1: float, y1: float, value: bool) -> None:
        j0, j1 = sorted((round(x0 / RASTER_RES_M), round(x1 / RASTER_RES_M)))
        i0, i1 = sorted((round(y0 / RASTER_RES_M), round(y1 / RASTER_RES_M)))
        j0, i0 = max(j0, 0), max(i0, 0)
        self.free[i0:i1, j0:j1] = value

    def seal_behind(
        self, p: tuple[float, float], q: tuple[float, float], keep: tuple[float, float]
    ) -> None:
        """Add the wall p-q and make solid the raster cells entirely on the far side of it.

        Only cells whose four corners are all behind the line are filled, so the raster
        staircase stays hidden behind the exact diagonal segment.
        """
        self.extra_segments.append((p[0], p[1], q[0], q[1]))
        nx_, ny_ = -(q[1] - p[1]), q[0] - p[0]
        keep_side = (keep[0] - p[0]) * nx_ + (keep[1] - p[1]) * ny_
        x_lo, x_hi = min(p[0], q[0]), max(p[0], q[0])
        y_lo, y_hi = min(p[1], q[1]), max(p[1], q[1])
        j0, j1 = int(x_lo / RASTER_RES_M), math.ceil(x_hi / RASTER_RES_M)
        i0, i1 = int(y_lo / RASTER_RES_M), math.ceil(y_hi / RASTER_RES_M)
        jj, ii = np.meshgrid(np.arange(j0, j1), np.arange(i0, i1))
        behind = np.ones(jj.shape, dtype=bool)
        for dj in (0, 1):
            for di in (0, 1):
                cx = (jj + dj) * RASTER_RES_M - p[0]
                cy = (ii + di) * RASTER_RES_M - p[1]
                behind &= (cx * nx_ + cy * ny_) * keep_side < -1e-12
        # Only the triangle spanned by the line and the box corner on the far side.
        self.free[ii[behind], jj[behind]] = False

    def segments(self) -> FloatArray:
        solid = np.pad(~self.free, 1, constant_values=True)
        res = RASTER_RES_M
        # Horizontal boundaries lie on grid line y = r * res between raster rows r-1 and r.
        hb = solid[:-1, 1:-1] != solid[1:, 1:-1]
        rows, c0, c1 = _runs(hb)
        horiz = np.column_stack((c0 * res, rows * res, c1 * res, rows * res))
        # Vertical boundaries lie on grid line x = c * res between raster columns c-1 and c.
        vb = (solid[1:-1, :-1] != solid[1:-1, 1:]).T
        cols, r0, r1 = _runs(vb)
        vert = np.column_stack((cols * res, r0 * res, cols * res, r1 * res))
        extra = np.asarray(self.extra_segments, dtype=np.float64).reshape(-1, 4)
        return np.vstack((horiz, vert, extra)).astype(np.float64)


def _runs(mask: BoolArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Runs of True along axis 1: (row, start, end-exclusive) as float arrays."""
    padded = np.zeros((mask.shape[0], mask.shape[1] + 2), dtype=np.int8)
    padded[:, 1:-1] = mask
    d = np.diff(padded, axis=1)
    rows, starts = np.nonzero(d == 1)
    _, ends = np.nonzero(d == -1)  # row-major order pairs each start with its end
    return rows.astype(np.float64), starts.astype(np.float64), ends.astype(np.float64)


def _partition(rng: np.random.Generator, a: float, b: float, w: tuple[float, float]) -> list[float]:
    """Cut [a, b] into pieces of width in ``w``; returns the cut points including a and b."""
    cuts = [a]
    while b - cuts[-1] > w[1]:
        cuts.append(_snap(cuts[-1] + rng.uniform(*w)))
    if b - cuts[-1] < w[0] and len(cuts) > 1:
        cuts.pop()
    cuts.append(b)
    return cuts


@dataclass
class _Room:
    x0: float
    y0: float
    x1: float
    y1: float
    door_side: str | None  # "N", "S", "E", "W" or None; the side facing a corridor
    door_span: tuple[float, float] | None = None  # usable wall interval for the door


def generate_building(seed: int, size: BuildingSize = "paper") -> World:
    """A deterministic Manhattan building with a few non-Manhattan walls; see the module doc."""
    if size not in _PRESETS:
        raise SimError(f"unknown building size {size!r}; use one of {sorted(_PRESETS)}")
    pre = _PRESETS[size]
    rng = np.random.default_rng([seed, 0x5EED])
    width, height = pre.width_m, pre.height_m
    plan = _Plan(width, height)
    w = _snap(rng.uniform(2.2, 2.8))  # corridor width
    xl = _snap(rng.uniform(*pre.margin_m))
    xr = _snap(width - rng.uniform(*pre.margin_m))
    yb = _snap(rng.uniform(*pre.margin_m))
    yt = _snap(height - rng.uniform(*pre.margin_m))

    # Corridor ring plus middle corridors joining the long sides (more loops).
    corridors = [
        (xl, yb, xr, yb + w),
        (xl, yt - w, xr, yt),
        (xl, yb, xl + w, yt),
        (xr - w, yb, xr, yt),
    ]
    span = xr - xl
    middles: list[float] = []
    for k in range(pre.middle_corridors):
        frac = (k + 1) / (pre.middle_corridors + 1)
        middles.append(_snap(xl + frac * span + rng.uniform(-0.08, 0.08) * span))
    corridors += [(xm, yb, xm + w, yt) for xm in middles]
    for c in corridors:
        plan.rect(*c, value=True)

    rooms: list[_Room] = []
    # South and north strips: rooms along the long corridors.
    for y0, y1, side in ((0.0, yb, "N"), (yt, height, "S")):
        cuts = _partition(rng, xl, xr, pre.room_width_m)
        for c0, c1 in itertools.pairwise(cuts):
            rooms.append(_Room(c0, y0, c1, y1, side, (c0, c1)))
    # West and east strips: rooms along the short corridors; corner rooms have no door.
    for x0, x1, side in ((0.0, xl, "E"), (xr, width, "W")):
        cuts = _partition(rng, 0.0, height, pre.room_width_m)
        for c0, c1 in itertools.pairwise(cuts):
            lo, hi = max(c0, yb), min(c1, yt)
            door = (side, (lo, hi)) if hi - lo > 1.8 else (None, None)
            rooms.append(_Room(x0, c0, x1, c1, door[0], door[1]))
    # Inner blocks between the vertical corridors: two rows back to back.
    edges = [xl + w, *[v for xm in middles for v in (xm, xm + w)], xr - w]
    blocks = list(zip(edges[0::2], edges[1::2], strict=True))
    y_mid = _snap((yb + w + yt - w) / 2.0)
    lobby_block = int(rng.integers(len(blocks)))
    lobby: tuple[float, float, float, float] | None = None
    for bi, (bx0, bx1) in enumerate(blocks):
        for y0, y1, side in ((yb + w, y_mid, "S"), (y_mid, yt - w, "N")):
            x_start = bx0
            if bi == lobby_block and side == "S":
                lobby_w = min(_snap(rng.uniform(12.0, 18.0)), _snap((bx1 - bx0) * 0.6))
                lx0 = _snap(bx0 + rng.uniform(0.0, max(bx1 - bx0 - lobby_w, 0.0)))
                lobby = (lx0, y0, lx0 + lobby_w, y1)
                if lx0 - bx0 >= pre.room_width_m[0]:
                    rooms.append(_Room(bx0, y0, lx0, y1, side, (bx0, lx0)))
                x_start = lx0 + lobby_w
                if bx1 - x_start < pre.room_width_m[0]:
                    continue
            cuts = _partition(rng, x_start, bx1, pre.room_width_m)
            for c0, c1 in itertools.pairwise(cuts):
                rooms.append(_Room(c0, y0, c1, y1, side, (c0, c1)))

    t = _WALL_INSET_M
    for room in rooms:
        plan.rect(room.x0 + t, room.y0 + t, room.x1 - t, room.y1 - t, value=True)
        if room.door_side is None or room.door_span is None or rng.random() < 0.2:
            continue  # closed door: just wall
        dw = _snap(rng.uniform(0.8, 1.2))
        lo, hi = room.door_span[0] + 0.3, room.door_span[1] - 0.3 - dw
        if hi < lo:
            continue
        d0 = _snap(rng.uniform(lo, hi))
        reach = 2.0 * t + RASTER_RES_M
        if room.door_side == "N":
            plan.rect(d0, room.y1 - reach, d0 + dw, room.y1 + RASTER_RES_M, True)
        elif room.door_side == "S":
            plan.rect(d0, room.y0 - RASTER_RES_M, d0 + dw, room.y0 + reach, True)
        elif room.door_side == "E":
            plan.rect(room.x1 - reach, d0, room.x1 + RASTER_RES_M, d0 + dw, True)
        else:
            plan.rect(room.x0 - RASTER_RES_M, d0, room.x0 + reach, d0 + dw, True)

    keep_clear = _corridor_junctions(xl=xl, xr=xr, yb=yb, yt=yt, w=w, middles=middles)
    _add_lobby(plan, rng, lobby, t)
    _add_pillars(plan, rng, corridors[:2], w, keep_clear)
    _add_corridor_clutter(plan, rng, corridors, w, keep_clear)
    for room in rooms:
        _add_room_clutter(plan, rng, room, t)
    _add_angled_partitions(plan, rng, rooms, t)
    _add_chamfers(plan, rng, (xl, xr, yb, yt), w)

    loop = np.array(
        [
            (xl + w / 2, yb + w / 2),
            (xr - w / 2, yb + w / 2),
            (xr - w / 2, yt - w / 2),
            (xl + w / 2, yt - w / 2),
        ],
        dtype=np.float64,
    )
    return World(
        seed=seed,
        size=size,
        width_m=width,
        height_m=height,
        corridor_width_m=w,
        segments_m=plan.segments(),
        loop_xy_m=loop,
        free_raster=plan.free,
    )


Box = tuple[float, float, float, float]  # x0, y0, x1, y1


def _corridor_junctions(
    *, xl: float, xr: float, yb: float, yt: float, w: float, middles: list[float]
) -> list[Box]:
    """Squares where corridors meet (ring corners and junctions): nothing may protrude there."""
    xs = [(xl, xl + w), (xr - w, xr), *[(xm, xm + w) for xm in middles]]
    ys = [(yb, yb + w), (yt - w, yt)]
    return [(x0, y0, x1, y1) for x0, x1 in xs for y0, y1 in ys]


def _near_any(box: Box, zones: list[Box], margin_m: float) -> bool:
    """True when ``box`` overlaps any zone grown by ``margin_m``."""
    x0, y0, x1, y1 = box
    return any(
        x1 > zx0 - margin_m and x0 < zx1 + margin_m and y1 > zy0 - margin_m and y0 < zy1 + margin_m
        for zx0, zy0, zx1, zy1 in zones
    )


def _add_lobby(
    plan: _Plan,
    rng: np.random.Generator,
    lobby: tuple[float, float, float, float] | None,
    t: float,
) -> None:
    """An open hall off a corridor: wide opening, a grid of pillars and a slanted back wall."""
    if lobby is None:
        return
    x0, y0, x1, y1 = lobby
    plan.rect(x0 + t, y0 - RASTER_RES_M, x1 - t, y1 - t, True)  # open onto the corridor below
    for px in np.arange(x0 + 3.0, x1 - 2.0, 4.0):
        for py in np.arange(y0 + 3.0, y1 - 2.5, 3.5):
            plan.rect(_snap(px), _snap(py), _snap(px) + 0.5, _snap(py) + 0.5, False)
    # Slanted wall (about 25-35 degrees) cutting off the hall's back-left corner.
    depth = y1 - t - (y0 + 2.0)
    run = depth / math.tan(math.radians(rng.uniform(25.0, 35.0)))
    run = min(run, (x1 - x0) * 0.6)
    p = (x0 + t, y0 + 2.0)
    q = (x0 + t + run, y1 - t)
    plan.seal_behind(p, q, keep=(x1 - 1.0, y0 + 0.5))


def _add_pillars(
    plan: _Plan,
    rng: np.random.Generator,
    corridors: list[tuple[float, float, float, float]],
    w: float,
    keep_clear: list[Box],
) -> None:
    """Regularly spaced pillars half embedded in the walls of the long corridors."""
    for x0, y0, x1, y1 in corridors:
        if rng.random() < 0.3:
            continue
        pitch = rng.uniform(5.0, 8.0)
        size = 0.4
        sticks = _snap(rng.uniform(0.15, 0.3))
        for px in np.arange(x0 + pitch / 2, x1 - size, pitch):
            sx = _snap(float(px))
            for wall_y, sign in ((y0, 1.0), (y1, -1.0)):
                inner = wall_y + sign * sticks
                box = (sx, min(wall_y, inner), sx + size, max(wall_y, inner))
                if _near_any(box, keep_clear, 1.5):
                    continue
                plan.rect(sx, wall_y - sign * 0.2, sx + size, inner, False)


def _add_corridor_clutter(
    plan: _Plan,
    rng: np.random.Generator,
    corridors: list[tuple[float, float, float, float]],
    w: float,
    keep_clear: list[Box],
) -> None:
    """A few small boxes (bins, cabinets) against corridor walls, leaving the centre clear."""
    for x0, y0, x1, y1 in corridors:
        horizontal = (x1 - x0) > (y1 - y0)
        length = (x1 - x0) if horizontal else (y1 - y0)
        for _ in range(int(rng.poisson(length / 15.0))):
            along = _snap(rng.uniform(0.0, length - 0.6))
            bw = _snap(rng.uniform(0.3, 0.6))
            depth = _snap(rng.uniform(0.25, min(0.45, w / 2 - 0.7)))
            side = rng.random() < 0.5
            if horizontal:
                bx = x0 + along
                by0, by1 = (y0, y0 + depth) if side else (y1 - depth, y1)
                if _near_any((bx, by0, bx + bw, by1), keep_clear, 1.5):
                    continue
                plan.rect(bx, by0, bx + bw, by1, False)
            else:
                by = y0 + along
                bx0, bx1 = (x0, x0 + depth) if side else (x1 - depth, x1)
                if _near_any((bx0, by, bx1, by + bw), keep_clear, 1.5):
                    continue
                plan.rect(bx0, by, bx1, by + bw, False)


def _add_room_clutter(plan: _Plan, rng: np.random.Generator, room: _Room, t: float) -> None:
    """Small boxes (furniture) inside a room, away from the door side."""
    ix0, iy0, ix1, iy1 = room.x0 + t + 0.3, room.y0 + t + 0.3, room.x1 - t - 0.3, room.y1 - t - 0.3
    # Keep a 1.5 m strip along the door wall free.
    if room.door_side == "N":
        iy1 -= 1.5
    elif room.door_side == "S":
        iy0 += 1.5
    elif room.door_side == "E":
        ix1 -= 1.5
    elif room.door_side == "W":
        ix0 += 1.5
    for _ in range(int(rng.poisson(2.0))):
        bw, bh = _snap(rng.uniform(0.3, 1.2)), _snap(rng.uniform(0.3, 1.2))
        if ix1 - ix0 < bw or iy1 - iy0 < bh:
            continue
        bx = _snap(rng.uniform(ix0, ix1 - bw))
        by = _snap(rng.uniform(iy0, iy1 - bh))
        plan.rect(bx, by, bx + bw, by + bh, False)


def _add_angled_partitions(
    plan: _Plan, rng: np.random.Generator, rooms: list[_Room], t: float
) -> None:
    """Thin free-standing partitions at non-Manhattan angles in a few rooms."""
    if not rooms:
        return
    picks = rng.choice(len(rooms), size=min(3, len(rooms)), replace=False)
    for k in picks:
        r = rooms[int(k)]
        cx, cy = (r.x0 + r.x1) / 2, (r.y0 + r.y1) / 2
        half = min(r.x1 - r.x0, r.y1 - r.y0) / 2 - t - 0.6
        if half < 0.5:
            continue
        ang = math.radians(rng.uniform(20.0, 70.0)) * (1 if rng.random() < 0.5 else -1)
        ux, uy = math.cos(ang) * half, math.sin(ang) * half
        nx_, ny_ = -math.sin(ang) * 0.05, math.cos(ang) * 0.05  # 0.1 m thick
        corners = [
            (cx - ux + nx_, cy - uy + ny_),
            (cx + ux + nx_, cy + uy + ny_),
            (cx + ux - nx_, cy + uy - ny_),
            (cx - ux - nx_, cy - uy - ny_),
        ]
        for i in range(4):
            p, q = corners[i], corners[(i + 1) % 4]
            plan.extra_segments.append((p[0], p[1], q[0], q[1]))


def _add_chamfers(
    plan: _Plan, rng: np.random.Generator, ring: tuple[float, float, float, float], w: float
) -> None:
    """45-degree chamfers across two outer corners of the corridor ring (xl, xr, yb, yt)."""
    xl, xr, yb, yt = ring
    c = 1.0
    corners = [(xl, yb, 1, 1), (xr, yb, -1, 1), (xr, yt, -1, -1), (xl, yt, 1, -1)]
    for k in rng.choice(4, size=2, replace=False):
        x, y, sx, sy = corners[int(k)]
        p = (x + sx * c, y)
        q = (x, y + sy * c)
        plan.seal_behind(p, q, keep=(x + sx * w / 2, y + sy * w / 2))


# --------------------------------------------------------------------------------------------
# Laser model and scan simulation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LaserModel:
    """Beam geometry, noise and error-code behaviour of a 2D laser scanner.

    Beam ``i`` points at ``angle_min_rad + i * angle_increment_rad`` (laser frame). Invalid beams
    are reported as integer codes below ``range_min_m`` in ``ranges_mm``, as the device does:
    ``no_return_code`` beyond ``range_max_m``, ``near_code`` below ``range_min_m`` and one of
    ``dropout_codes`` for random dropouts (probability ``dropout_prob`` per beam).
    """

    name: str
    angle_min_rad: float
    angle_increment_rad: float
    beam_count: int
    range_min_m: float
    range_max_m: float
    noise_sigma_m: float = 0.01
    dropout_prob: float = 0.002
    no_return_code: int = 1
    near_code: int = 4
    dropout_codes: tuple[int, ...] = (3,)
    scan_period_s: float = 0.025

    @property
    def angle_max_rad(self) -> float:
        return self.angle_min_rad + self.angle_increment_rad * (self.beam_count - 1)

    def angles_rad(self) -> FloatArray:
        """(beam_count,) float64 beam angles in the laser frame."""
        return self.angle_min_rad + self.angle_increment_rad * np.arange(
            self.beam_count, dtype=np.float64
        )

    def with_(self, **changes: float | int | str | tuple[int, ...]) -> LaserModel:
        """A copy with some fields changed, e.g. ``LaserModel.utm30lx().with_(noise_sigma_m=0)``."""
        return replace(self, **changes)  # type: ignore[arg-type]

    @classmethod
    def utm30lx(cls) -> LaserModel:
        """Hokuyo UTM-30LX: 270 deg, 1,081 beams at 0.25 deg, 0.023-30 m, 40 Hz (PROTOCOLS A.5).

        Codes: 1 no object in range, 4 object too near, 3 measurement error (dropouts).
        """
        ares = 1440
        return cls(
            name="UTM-30LX",
            angle_min_rad=(0 - 540) * 2.0 * math.pi / ares,
            angle_increment_rad=2.0 * math.pi / ares,
            beam_count=1081,
            range_min_m=0.023,
            range_max_m=30.0,
            noise_sigma_m=0.01,
            dropout_prob=0.002,
            no_return_code=1,
            near_code=4,
            dropout_codes=(3,),
            scan_period_s=0.025,
        )

    @classmethod
    def sick_lms200(cls) -> LaserModel:
        """SICK LMS200-like: 180 deg, 181 beams at 1 deg, up to 80 m, 5 Hz; invalid beams read 0."""
        return cls(
            name="SICK-LMS200",
            angle_min_rad=-math.pi / 2.0,
            angle_increment_rad=math.radians(1.0),
            beam_count=181,
            range_min_m=0.0,
            range_max_m=80.0,
            noise_sigma_m=0.01,
            dropout_prob=0.002,
            no_return_code=0,
            near_code=0,
            dropout_codes=(0,),
            scan_period_s=0.2,
        )

    @classmethod
    def urg04lx(cls, beam_count: int = 681) -> LaserModel:
        """Hokuyo URG-04LX: ~240 deg from step 44, 1024 steps per turn, 0.02-5.6 m, 10 Hz.

        The shared demo bag has 681 beams; drivers also publish 682 or 683. Codes follow the
        URG table (PROTOCOLS A.5, Table 3): 0 possibly far, 1/2 low intensity, 19 non-measurable.
        """
        ares = 1024
        return cls(
            name="URG-04LX",
            angle_min_rad=(44 - 384) * 2.0 * math.pi / ares,
            angle_increment_rad=2.0 * math.pi / ares,
            beam_count=beam_count,
            range_min_m=0.02,
            range_max_m=5.6,
            noise_sigma_m=0.01,
            dropout_prob=0.003,
            no_return_code=0,
            near_code=19,
            dropout_codes=(1, 2),
            scan_period_s=0.1,
        )


@dataclass(frozen=True, eq=False)
class ScanSample:
    """One simulated scan: device integers and metres.

    ``ranges_mm`` (B,) uint32: millimetres, or an error code below ``range_min_m`` for invalid
    beams. ``ranges_m`` (B,) float64: metres, NaN for invalid beams. ``true_ranges_m`` (B,)
    float64: the noise-free ray-cast distance (inf where nothing within range).
    """

    ranges_mm: npt.NDArray[np.uint32]
    ranges_m: FloatArray
    true_ranges_m: FloatArray
    model: LaserModel


def simulate_scan(
    world: World, pose: PoseLike, model: LaserModel, rng: np.random.Generator
) -> ScanSample:
    """Ray-cast ``model``'s beams from ``pose`` and apply its noise, dropouts and error codes."""
    true_m = world.raycast(pose, model.angles_rad(), model.range_max_m)
    return apply_beam_model(true_m, model, rng)


def apply_beam_model(true_m: FloatArray, model: LaserModel, rng: np.random.Generator) -> ScanSample:
    """``model``'s noise, dropouts and error codes on noise-free ranges (``inf``: no return).

    ``simulate_scan`` is a ray cast followed by this; callers that add their own obstacles to
    the ray cast (``sensor_agent.sim.families``: walking people) call it directly.
    """
    true_m = np.asarray(true_m, dtype=np.float64)
    n = true_m.shape[0]
    noisy_m = (
        true_m + rng.normal(0.0, model.noise_sigma_m, n) if model.noise_sigma_m > 0 else true_m
    )
    with np.errstate(invalid="ignore"):
        mm = np.rint(noisy_m * 1000.0)
    min_mm = math.ceil(model.range_min_m * 1000.0)
    max_mm = math.floor(model.range_max_m * 1000.0)
    codes = np.zeros(n, dtype=np.int64)
    far = ~np.isfinite(mm) | (mm > max_mm)
    near = ~far & (mm < max(min_mm, 1))
    codes[far] = model.no_return_code
    codes[near] = model.near_code
    dropped = rng.random(n) < model.dropout_prob
    if model.dropout_codes:
        pick = np.asarray(rng.integers(0, len(model.dropout_codes), size=n), dtype=np.int64)
        codes[dropped] = np.asarray(model.dropout_codes, dtype=np.int64)[pick[dropped]]
    invalid = far | near | dropped
    ranges_mm = np.where(invalid, codes, np.nan_to_num(mm, posinf=0.0)).astype(np.uint32)
    ranges_m = np.where(invalid, np.nan, ranges_mm.astype(np.float64) / 1000.0)
    return ScanSample(ranges_mm=ranges_mm, ranges_m=ranges_m, true_ranges_m=true_m, model=model)


# --------------------------------------------------------------------------------------------
# Trajectories
# --------------------------------------------------------------------------------------------


class _LoopPath:
    """A closed, smooth path: the corridor loop with filleted corners and a gentle lateral wiggle.

    Arc length ``s`` runs over [0, length_m); the centre line is made of straight pieces and
    circular arcs, and the wiggle is a sum of sinusoids periodic in the loop length, so the
    path closes exactly.
    """

    def __init__(
        self,
        corners_xy: FloatArray,
        turn_radius_m: float,
        wiggle_m: float,
        rng: np.random.Generator,
        reverse: bool,
    ) -> None:
        pts = np.asarray(corners_xy, dtype=np.float64)
        if reverse:
            pts = pts[::-1]
        k = pts.shape[0]
        p0s: list[tuple[float, float]] = []
        h0s: list[float] = []
        lens: list[float] = []
        curvs: list[float] = []
        arcs: list[tuple[tuple[float, float], tuple[float, float], float, float]] = []
        for i in range(k):
            prev_pt, pt, next_pt = pts[i - 1], pts[i], pts[(i + 1) % k]
            d_in = (pt - prev_pt) / np.linalg.norm(pt - prev_pt)
            d_out = (next_pt - pt) / np.linalg.norm(next_pt - pt)
            turn = math.atan2(
                d_in[0] * d_out[1] - d_in[1] * d_out[0], d_in[0] * d_out[0] + d_in[1] * d_out[1]
            )
            tau = turn_radius_m * math.tan(abs(turn) / 2.0)
            a = pt - tau * d_in
            b = pt + tau * d_out
            arcs.append(((a[0], a[1]), (b[0], b[1]), math.atan2(d_in[1], d_in[0]), turn))
        for i in range(k):
            _, b_prev, _, _ = arcs[i - 1]
            a, _, h_in, turn = arcs[i]
            seg_len = math.hypot(a[0] - b_prev[0], a[1] - b_prev[1])
            p0s.append(b_prev)
            h0s.append(h_in)
            lens.append(seg_len)
            curvs.append(0.0)
            p0s.append(a)
            h0s.append(h_in)
            lens.append(turn_radius_m * abs(turn))
            curvs.append(math.copysign(1.0 / turn_radius_m, turn) if turn != 0 else 0.0)
        self._p0 = np.asarray(p0s, dtype=np.float64)
        self._h0 = np.asarray(h0s, dtype=np.float64)
        self._len = np.asarray(lens, dtype=np.float64)
        self._curv = np.asarray(curvs, dtype=np.float64)
        self._cum = np.concatenate(([0.0], np.cumsum(self._len)))
        self.length_m = float(self._cum[-1])
        # Start somewhere along the first straight, drawn from the seed.
        self._s_start = float(rng.uniform(0.1, 0.6) * self._len[0])
        n_waves = 3
        # Wavelengths of about 15-60 m: a gentle weave, a few degrees of heading.
        lo_k = max(1, int(self.length_m / 60.0))
        harmonics = rng.integers(lo_k, max(lo_k + 1, int(self.length_m / 15.0)), n_waves)
        self._wave_k = harmonics.astype(np.float64)
        self._wave_a = rng.uniform(0.3, 1.0, n_waves) * wiggle_m / n_waves
        self._wave_phi = rng.uniform(0.0, 2.0 * math.pi, n_waves)

    def poses(self, s_m: FloatArray) -> FloatArray:
        """(N, 3) poses at arc lengths ``s_m`` (any real values; the loop repeats)."""
        s = (np.asarray(s_m, dtype=np.float64) + self._s_start) % self.length_m
        idx = np.clip(np.searchsorted(self._cum, s, side="right") - 1, 0, self._len.shape[0] - 1)
        ds = s - self._cum[idx]
        p0, h0, kappa = self._p0[idx], self._h0[idx], self._curv[idx]
        heading = h0 + kappa * ds
        straight = kappa == 0.0
        safe_k = np.where(straight, 1.0, kappa)
        x = np.where(
            straight, p0[:, 0] + ds * np.cos(h0), p0[:, 0] + (np.sin(heading) - np.sin(h0)) / safe_k
        )
        y = np.where(
            straight, p0[:, 1] + ds * np.sin(h0), p0[:, 1] - (np.cos(heading) - np.cos(h0)) / safe_k
        )
        # Lateral wiggle, periodic in the loop length so the loop closes.
        w = 2.0 * math.pi * self._wave_k / self.length_m
        phase = s[:, None] * w[None, :] + self._wave_phi[None, :]
        offset = (self._wave_a[None, :] * np.sin(phase)).sum(axis=1)
        slope = (self._wave_a[None, :] * w[None, :] * np.cos(phase)).sum(axis=1)
        x = x - offset * np.sin(heading)
        y = y + offset * np.cos(heading)
        theta = _wrap(heading + np.arctan(slope))
        return np.column_stack((x, y, theta))


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Ground truth: ``stamps_ns`` (N,) int64 and ``poses`` (N, 3) float64 ``x_m, y_m, theta_rad``.

    ``loop_length_m`` is the length of the closed loop driven; ``path_length_m`` the total
    travelled (larger when ``laps`` > 1).
    """

    stamps_ns: npt.NDArray[np.int64]
    poses: FloatArray
    loop_length_m: float
    path_length_m: float

    def __len__(self) -> int:
        return int(self.poses.shape[0])


def _make_path(world: World, seed: int, turn_radius_m: float, wiggle_m: float) -> _LoopPath:
    rng = np.random.default_rng([seed, 0x7EA1])
    reverse = bool(rng.random() < 0.5)
    return _LoopPath(world.loop_xy_m, turn_radius_m, wiggle_m, rng, reverse)


def generate_trajectory(
    world: World,
    seed: int,
    *,
    spacing_m: float = 0.3,
    rotation_step_deg: float = 10.0,
    speed_mps: float = 0.7,
    start_ns: int = 1_700_000_000_000_000_000,
    laps: float = 1.0,
    turn_radius_m: float = 1.0,
    wiggle_m: float = 0.2,
) -> Trajectory:
    """Ground-truth poses around the world's corridor loop (the paper's sampling).

    A pose is emitted whenever the robot has moved ``spacing_m`` or turned ``rotation_step_deg``
    since the previous one. With ``laps=1`` the final pose is the start pose again (the loop
    closes); stamps follow ``speed_mps``.
    """
    if spacing_m <= 0 or speed_mps <= 0 or laps <= 0:
        raise SimError("spacing_m, speed_mps and laps must be positive")
    path = _make_path(world, seed, turn_radius_m, wiggle_m)
    total_m = path.length_m * laps
    step_m = min(0.01, spacing_m / 10.0)
    s = np.arange(0.0, total_m + step_m / 2, step_m)
    s[-1] = total_m
    dense = path.poses(s)
    rot_step = math.radians(rotation_step_deg)
    xs, ys, ths = dense[:, 0].tolist(), dense[:, 1].tolist(), dense[:, 2].tolist()
    keep = [0]
    lx, ly, lth = xs[0], ys[0], ths[0]
    for i in range(1, len(xs)):
        dth = abs((ths[i] - lth + math.pi) % (2.0 * math.pi) - math.pi)
        if math.hypot(xs[i] - lx, ys[i] - ly) >= spacing_m or dth >= rot_step:
            keep.append(i)
            lx, ly, lth = xs[i], ys[i], ths[i]
    last = len(xs) - 1
    if keep[-1] != last:
        if math.hypot(xs[last] - lx, ys[last] - ly) < spacing_m * 0.25 and len(keep) > 1:
            keep[-1] = last  # replace a near-duplicate so the final pose is exactly the end
        else:
            keep.append(last)
    idx = np.asarray(keep, dtype=np.int64)
    stamps = start_ns + np.rint(s[idx] / speed_mps * 1e9).astype(np.int64)
    return Trajectory(
        stamps_ns=stamps,
        poses=np.ascontiguousarray(dense[idx]),
        loop_length_m=path.length_m,
        path_length_m=total_m,
    )


class RobotMotion:
    """Continuous-time motion around the world's corridor loop, looping forever.

    ``pose_at(t_s)`` is the ground-truth pose ``(x_m, y_m, theta_rad)`` at ``t_s`` seconds after
    the start; the robot drives at ``speed_mps`` along the same kind of path as
    ``generate_trajectory`` (same seed, same path).
    """

    def __init__(
        self,
        world: World,
        seed: int = 0,
        speed_mps: float = 0.7,
        turn_radius_m: float = 1.0,
        wiggle_m: float = 0.2,
    ) -> None:
        if speed_mps <= 0:
            raise SimError("speed_mps must be positive")
        self.world = world
        self.speed_mps = speed_mps
        self._path = _make_path(world, seed, turn_radius_m, wiggle_m)

    @property
    def loop_length_m(self) -> float:
        return self._path.length_m

    @property
    def loop_period_s(self) -> float:
        return self._path.length_m / self.speed_mps

    def pose_at(self, t_s: float) -> tuple[float, float, float]:
        p = self._path.poses(np.array([t_s * self.speed_mps]))[0]
        return (float(p[0]), float(p[1]), float(p[2]))

    def poses_at(self, t_s: FloatArray) -> FloatArray:
        """(N, 3) poses for an array of times."""
        return self._path.poses(np.asarray(t_s, dtype=np.float64) * self.speed_mps)
