"""PNG / PGM / YAML / TUM writers."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image

from service import mapio
from service.core.maps.grid import GridImage
from service.core.types import Pose2D


def grid(occ: np.ndarray, ox: float = -1.0, oy: float = 2.0, res: float = 0.05) -> GridImage:
    return GridImage(np.asarray(occ, dtype=np.int8), ox, oy, res)


def decode(png: bytes) -> np.ndarray:
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def has_colour(rgb: np.ndarray, colour: tuple[int, int, int], tol: int = 10) -> bool:
    return bool((np.abs(rgb.astype(int) - colour).max(axis=2) <= tol).any())


def test_png_small_map_is_upscaled_and_north_up() -> None:
    occ = np.full((40, 60), 10, dtype=np.int8)  # free
    occ[-1, :] = 100  # the top row (highest y) is a wall
    occ[:5, :5] = -1
    rgb = decode(mapio.render_png(grid(occ), margin_m=0.0, scale_bar=False))
    assert max(rgb.shape[:2]) >= 800
    assert rgb.shape[0] * 60 == rgb.shape[1] * 40  # aspect kept
    top, bottom = rgb[2].mean(), rgb[rgb.shape[0] // 2].mean()
    assert top < 80  # dark wall at the top
    assert bottom > 230  # light free space
    assert abs(int(rgb[-3, 3, 0]) - 196) < 3  # unknown corner bottom-left is grey


def test_png_draws_trajectory_and_robot() -> None:
    occ = np.full((100, 100), 10, dtype=np.int8)
    traj = np.array([[0.0, 3.0], [2.0, 4.0], [3.0, 6.0]])
    png = mapio.render_png(grid(occ), traj, Pose2D(1.0, 5.0, 0.7))
    rgb = decode(png)
    assert has_colour(rgb, (222, 74, 44))
    assert has_colour(rgb, (18, 140, 96))


def test_png_empty_map_and_trajectory_outside_the_map() -> None:
    empty = GridImage(np.zeros((0, 0), dtype=np.int8), 0.0, 0.0, 0.05)
    assert decode(mapio.render_png(empty)).shape[2] == 3
    rgb = decode(mapio.to_png(empty, [Pose2D(0, 0, 0), Pose2D(30, 10, 1)], Pose2D(30, 10, 1)))
    assert has_colour(rgb, (222, 74, 44))
    one = decode(mapio.to_png(empty, np.array([[1.0, 1.0, 0.0]])))
    assert one.size


def test_png_huge_map_is_downscaled_keeping_thin_walls() -> None:
    occ = np.full((200, 12000), 10, dtype=np.int8)
    occ[:, 6001] = 100  # one-cell wall
    rgb = decode(mapio.render_png(grid(occ), max_size_px=2000, scale_bar=False))
    assert rgb.shape[1] <= 2000
    middle_row = rgb[rgb.shape[0] // 2].mean(axis=1)
    assert middle_row.min() < 80  # the wall survived the downscale


def test_pgm_values_and_orientation() -> None:
    occ = np.array([[0, 25, 26], [64, 65, -1]], dtype=np.int8)  # row 0 = lowest y
    pgm = mapio.to_pgm(grid(occ))
    header, pixels = pgm.rsplit(b"\n", 1)[0], pgm[-6:]
    lines = [ln for ln in pgm[: len(pgm) - 6].split(b"\n") if ln and not ln.startswith(b"#")]
    assert lines[0] == b"P5"
    assert lines[1] == b"3 2"
    assert lines[2] == b"255"
    assert header.startswith(b"P5\n")
    # First file row is the highest y (occupancy row 1).
    assert list(pixels) == [205, 0, 205, 254, 254, 205]


def test_pgm_empty_map() -> None:
    pgm = mapio.to_pgm(GridImage(np.zeros((0, 0), dtype=np.int8), 0.0, 0.0, 0.05))
    assert b"\n1 1\n255\n" in pgm
    assert pgm.endswith(bytes([205]))


def test_yaml() -> None:
    text = mapio.to_yaml(grid(np.zeros((2, 2)), ox=-12.5, oy=3.25, res=0.05), "map.pgm")
    fields = dict(line.split(": ", 1) for line in text.strip().splitlines())
    assert fields["image"] == "map.pgm"
    assert float(fields["resolution"]) == 0.05
    ox, oy, yaw = (float(v) for v in fields["origin"].strip("[]").split(","))
    assert (ox, oy, yaw) == (-12.5, 3.25, 0.0)
    assert fields["occupied_thresh"] == "0.65"
    assert fields["free_thresh"] == "0.196"
    assert fields["negate"] == "0"
    assert fields["mode"] == "trinary"


@pytest.mark.parametrize("as_array", [False, True])
def test_tum(as_array: bool) -> None:
    stamps = [1_700_000_000_123_456_789, 5, 1_700_000_001_000_000_000]
    poses = [Pose2D(1.0, -2.0, 0.0), Pose2D(0.5, 0.25, math.pi / 2), Pose2D(3.0, 4.0, -3.0)]
    arg = np.array(poses) if as_array else poses
    text = mapio.format_tum(np.array(stamps) if as_array else stamps, arg)
    lines = text.splitlines()
    assert len(lines) == 3
    assert text.endswith("\n")
    f = lines[0].split()
    assert f[0] == "1700000000.123456789"
    assert lines[1].split()[0] == "0.000000005"
    assert len(f) == 8
    for line, pose in zip(lines, poses, strict=True):
        _, x, y, z, qx, qy, qz, qw = (float(v) for v in line.split())
        assert (x, y, z, qx, qy) == pytest.approx((pose.x_m, pose.y_m, 0.0, 0.0, 0.0))
        assert qz * qz + qw * qw == pytest.approx(1.0)
        assert 2 * math.atan2(qz, qw) == pytest.approx(pose.theta_rad, abs=1e-8)


def test_tum_length_mismatch() -> None:
    with pytest.raises(ValueError, match="stamps"):
        mapio.format_tum([1, 2], [Pose2D(0, 0, 0)])
    assert mapio.format_tum([], []) == ""
