"""Map and trajectory writers: PNG pictures, ROS map_server PGM + YAML, TUM trajectories.

All functions are pure (bytes / text out); callers write the files.

- ``render_png(image, trajectory_xy=None, robot_pose=None, ...) -> bytes``: a picture for people:
  light free space, dark walls, grey unknown, the trajectory as a coloured line and the robot as a
  triangle. Small maps are scaled up, huge ones scaled down keeping thin walls visible. North is
  up (``GridImage`` row 0 is the lowest y, so rows are flipped).
- ``to_png`` is the same with ``trajectory`` given as poses (``Pose2D`` list or (N, 2|3) array).
- ``to_pgm(image) -> bytes``: binary P5 as ``map_saver`` writes it: 0 occupied, 254 free,
  205 unknown, first row = highest y.
- ``to_yaml(image, image_file) -> str``: the map_server YAML beside it.
- ``format_tum(stamps_ns, poses) -> str``: ``stamp x y z qx qy qz qw`` per line, stamp in seconds
  with 9 decimals, z = 0 and the quaternion of the yaw.
"""

from __future__ import annotations

import io
import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import Image, ImageDraw, ImageFont

from service.core.maps.grid import GridImage
from service.core.types import Pose2D

log = logging.getLogger(__name__)

# map_saver's thresholds on the 0..100 occupancy (ROS 1 map_server defaults).
OCCUPIED_PERCENT = 65
FREE_PERCENT = 25
PGM_OCCUPIED = 0
PGM_FREE = 254
PGM_UNKNOWN = 205

_UNKNOWN_RGB = np.array([196, 200, 206], dtype=np.float64)
_FREE_RGB = np.array([250, 250, 247], dtype=np.float64)
_WALL_RGB = np.array([28, 31, 40], dtype=np.float64)
_TRAJECTORY_RGB = (222, 74, 44)
_ROBOT_RGB = (18, 140, 96)
_INK_RGB = (40, 44, 52)


# ----------------------------------------------------------------------------------------
# PNG
# ----------------------------------------------------------------------------------------


def _make_palette() -> list[int]:
    """Palette of the shade levels: 0..100 free to wall, then the unknown colour."""
    t = np.linspace(0.0, 1.0, 101)[:, None]
    shades = _FREE_RGB + (_WALL_RGB - _FREE_RGB) * t
    colours = np.vstack((shades, _UNKNOWN_RGB[None, :]))
    return [int(v) for v in np.rint(colours).astype(np.uint8).reshape(-1)]


_UNKNOWN_LEVEL = 101
_PALETTE = _make_palette()
# Occupancy -1..100 (index + 1) to shade level: free-looking up to 45 % (a cell seen free once
# is at 40 %), ramping to a wall colour at 70 %.
_LEVEL_OF_OCC = np.concatenate(
    (
        [_UNKNOWN_LEVEL],
        np.rint(np.clip((np.arange(101) - 45.0) / 25.0, 0.0, 1.0) * 100.0),
    )
).astype(np.uint8)


def _as_xy(poses: Any) -> npt.NDArray[np.float64] | None:
    """(N, 2) positions from an (N, 2|3) array or a sequence of Pose2D / tuples."""
    if poses is None:
        return None
    if isinstance(poses, np.ndarray):
        arr = poses.astype(np.float64)
    else:
        seq = list(poses)
        if not seq:
            return None
        arr = np.asarray([(float(p[0]), float(p[1])) for p in seq], dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] < 2:
        return None
    xy = arr[:, :2]
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    return xy if xy.shape[0] else None


def render_png(
    image: GridImage,
    trajectory_xy: npt.NDArray[np.float64] | Sequence[Sequence[float]] | None = None,
    robot_pose: Pose2D | None = None,
    *,
    min_size_px: int = 800,
    max_size_px: int = 4096,
    margin_m: float = 1.0,
    scale_bar: bool = True,
) -> bytes:
    """Render the map (and optionally the trajectory and the robot) as PNG bytes.

    The canvas covers the map and the trajectory/robot plus ``margin_m``. The pixel size is an
    integer up-scale of the map cells so the longer side reaches ``min_size_px``, or an integer
    down-scale (a cell block shows its darkest cell, so walls stay visible) so it fits
    ``max_size_px``.
    """
    res = float(image.resolution_m)
    occ = np.asarray(image.occupancy)
    xy = _as_xy(trajectory_xy)

    # World extent of everything to draw.
    xs: list[float] = []
    ys: list[float] = []
    if occ.size:
        xs += [image.origin_x_m, image.origin_x_m + occ.shape[1] * res]
        ys += [image.origin_y_m, image.origin_y_m + occ.shape[0] * res]
    if xy is not None:
        xs += [float(xy[:, 0].min()), float(xy[:, 0].max())]
        ys += [float(xy[:, 1].min()), float(xy[:, 1].max())]
    if robot_pose is not None:
        xs.append(float(robot_pose.x_m))
        ys.append(float(robot_pose.y_m))
    if not xs:
        xs, ys = [-5.0, 5.0], [-5.0, 5.0]
    # Canvas in whole cells, aligned to the map's cell grid.
    ox = image.origin_x_m + math.floor((min(xs) - margin_m - image.origin_x_m) / res) * res
    oy = image.origin_y_m + math.floor((min(ys) - margin_m - image.origin_y_m) / res) * res
    w_cells = max(1, math.ceil((max(xs) + margin_m - ox) / res))
    h_cells = max(1, math.ceil((max(ys) + margin_m - oy) / res))

    # Shade levels on the canvas: 0 free .. 100 wall, _UNKNOWN_LEVEL unknown; row 0 = lowest y.
    level = np.full((h_cells, w_cells), _UNKNOWN_LEVEL, dtype=np.uint8)
    if occ.size:
        r0 = round((image.origin_y_m - oy) / res)
        c0 = round((image.origin_x_m - ox) / res)
        level[r0 : r0 + occ.shape[0], c0 : c0 + occ.shape[1]] = _LEVEL_OF_OCC[
            np.clip(occ.astype(np.int16), -1, 100) + 1
        ]
    level = level[::-1]

    longest = max(h_cells, w_cells)
    down = max(1, math.ceil(longest / max_size_px))
    up = 1
    if down > 1:
        level = _block_reduce(level, down)
        px_per_cell = 1.0 / down
    else:
        up = max(1, min(16, -(-min_size_px // longest)))  # ceil: reach min_size_px
        px_per_cell = float(up)

    canvas = Image.fromarray(np.ascontiguousarray(level), mode="P")
    canvas.putpalette(_PALETTE)
    if up > 1:
        canvas = canvas.resize((canvas.width * up, canvas.height * up), Image.Resampling.NEAREST)
    canvas = canvas.convert("RGB")
    draw = ImageDraw.Draw(canvas)
    px_per_m = px_per_cell / res
    height_px = canvas.height

    def to_px(x: float, y: float) -> tuple[float, float]:
        return ((x - ox) * px_per_m, height_px - (y - oy) * px_per_m)

    line_w = max(2, round(min(canvas.width, canvas.height) / 300))
    if xy is not None and xy.shape[0] >= 2:
        pts = [to_px(float(x), float(y)) for x, y in xy]
        draw.line(pts, fill=_TRAJECTORY_RGB, width=line_w, joint="curve")
    elif xy is not None:
        cx, cy = to_px(float(xy[0, 0]), float(xy[0, 1]))
        draw.ellipse((cx - line_w, cy - line_w, cx + line_w, cy + line_w), fill=_TRAJECTORY_RGB)
    if robot_pose is not None:
        _draw_robot(draw, to_px, robot_pose, px_per_m, line_w)
    if scale_bar:
        _draw_scale_bar(draw, canvas.width, canvas.height, px_per_m)

    buf = io.BytesIO()
    canvas.save(buf, format="PNG", optimize=False)
    return buf.getvalue()


def to_png(
    image: GridImage,
    trajectory: Any = None,
    robot_pose: Pose2D | None = None,
    **kwargs: Any,
) -> bytes:
    """``render_png`` with the trajectory given as poses (Pose2D list or (N, 2|3) array)."""
    return render_png(image, trajectory_xy=_as_xy(trajectory), robot_pose=robot_pose, **kwargs)


def _block_reduce(level: npt.NDArray[np.uint8], k: int) -> npt.NDArray[np.uint8]:
    """Down-scale by ``k``: a block is as dark as its darkest known cell, unknown if none is."""
    h, w = level.shape
    padded = np.pad(level, ((0, -h % k), (0, -w % k)), constant_values=_UNKNOWN_LEVEL)
    blocks = padded.reshape(padded.shape[0] // k, k, padded.shape[1] // k, k)
    known = blocks != _UNKNOWN_LEVEL
    darkest = np.where(known, blocks, 0).max(axis=(1, 3))
    return np.where(known.any(axis=(1, 3)), darkest, _UNKNOWN_LEVEL).astype(np.uint8)


def _draw_robot(
    draw: ImageDraw.ImageDraw,
    to_px: Any,
    pose: Pose2D,
    px_per_m: float,
    line_w: int,
) -> None:
    """An isosceles triangle pointing along the heading, at least 14 px long."""
    length_px = max(14.0, 0.8 * px_per_m)
    cx, cy = to_px(float(pose.x_m), float(pose.y_m))
    th = float(pose.theta_rad)
    # Image y grows downwards: rotate with -theta.
    c, s = math.cos(th), -math.sin(th)
    local = [(0.6, 0.0), (-0.4, 0.35), (-0.25, 0.0), (-0.4, -0.35)]
    pts = [(cx + length_px * (c * u - s * v), cy + length_px * (s * u + c * v)) for u, v in local]
    draw.polygon(pts, fill=_ROBOT_RGB, outline=_INK_RGB, width=max(1, line_w // 2))


def _draw_scale_bar(draw: ImageDraw.ImageDraw, width: int, height: int, px_per_m: float) -> None:
    """A 1-2-5 metre bar about a sixth of the width, bottom left."""
    target_m = width / 6.0 / px_per_m
    if target_m <= 0 or height < 40:
        return
    exp = 10.0 ** math.floor(math.log10(target_m))
    bar_m = max(m * exp for m in (1.0, 2.0, 5.0) if m * exp <= target_m)
    bar_px = bar_m * px_per_m
    x0, y0 = 12.0, height - 14.0
    draw.rectangle((x0 - 4, y0 - 18, x0 + bar_px + 50, y0 + 6), fill=(255, 255, 255))
    draw.line((x0, y0, x0 + bar_px, y0), fill=_INK_RGB, width=3)
    draw.line((x0, y0 - 5, x0, y0 + 3), fill=_INK_RGB, width=2)
    draw.line((x0 + bar_px, y0 - 5, x0 + bar_px, y0 + 3), fill=_INK_RGB, width=2)
    label = f"{bar_m:g} m"
    draw.text((x0 + bar_px + 6, y0 - 14), label, fill=_INK_RGB, font=ImageFont.load_default())


# ----------------------------------------------------------------------------------------
# ROS map_server
# ----------------------------------------------------------------------------------------


def trinary(image: GridImage) -> npt.NDArray[np.uint8]:
    """(H, W) uint8 map_saver values, first row = highest y: 0 occupied, 254 free, 205 unknown."""
    occ = np.asarray(image.occupancy)
    out = np.full(occ.shape, PGM_UNKNOWN, dtype=np.uint8)
    out[(occ >= 0) & (occ <= FREE_PERCENT)] = PGM_FREE
    out[occ >= OCCUPIED_PERCENT] = PGM_OCCUPIED
    return np.ascontiguousarray(out[::-1])


def to_pgm(image: GridImage) -> bytes:
    """Binary PGM (P5) as written by map_saver; an empty map becomes one unknown pixel."""
    pixels = trinary(image)
    if pixels.size == 0:
        pixels = np.full((1, 1), PGM_UNKNOWN, dtype=np.uint8)
    h, w = pixels.shape
    header = f"P5\n# CREATOR: manhattan-mapper {image.resolution_m:.3f} m/pix\n{w} {h}\n255\n"
    return header.encode("ascii") + pixels.tobytes()


def to_yaml(image: GridImage, image_file: str = "map.pgm") -> str:
    """The map_server YAML describing the PGM from ``to_pgm``."""
    return (
        f"image: {image_file}\n"
        "mode: trinary\n"
        f"resolution: {float(image.resolution_m):.6g}\n"
        f"origin: [{float(image.origin_x_m):.6f}, {float(image.origin_y_m):.6f}, 0.0]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
    )


# ----------------------------------------------------------------------------------------
# TUM trajectories
# ----------------------------------------------------------------------------------------


def format_tum_stamp(stamp_ns: int) -> str:
    """Seconds with exactly 9 decimals, computed from integer nanoseconds (no float rounding)."""
    ns = int(stamp_ns)
    sign = "-" if ns < 0 else ""
    sec, frac = divmod(abs(ns), 1_000_000_000)
    return f"{sign}{sec}.{frac:09d}"


def format_tum(stamps_ns: Sequence[int] | npt.NDArray[np.int64], poses: Any) -> str:
    """TUM text: ``stamp x y z qx qy qz qw`` per pose (z = 0, rotation about z only).

    ``poses`` is a sequence of ``Pose2D`` / ``(x, y, theta)`` or an (N, 3) array.
    """
    arr = np.asarray([tuple(map(float, p[:3])) for p in poses], dtype=np.float64).reshape(-1, 3)
    stamps = [int(s) for s in stamps_ns]
    if len(stamps) != arr.shape[0]:
        raise ValueError(f"{len(stamps)} stamps but {arr.shape[0]} poses")
    lines = []
    for stamp, (x, y, th) in zip(stamps, arr, strict=True):
        qz, qw = math.sin(th / 2.0), math.cos(th / 2.0)
        lines.append(
            f"{format_tum_stamp(stamp)} {x:.6f} {y:.6f} 0.000000 "
            f"0.000000000 0.000000000 {qz:.9f} {qw:.9f}\n"
        )
    return "".join(lines)
