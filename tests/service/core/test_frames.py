"""Wall families ("Atlanta world", `service.core.frontend.frames`) on their own."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.frontend.frames import (
    FrameParams,
    WallFrames,
    family_support,
    strongest_other_family,
)


def _directions(rng: np.random.Generator, angles_deg: dict[float, int]) -> np.ndarray:
    """Surface directions (mod π) of walls at these angles (either axis), with 2° of noise."""
    out = []
    for angle, n in angles_deg.items():
        base = math.radians(angle) + (math.pi / 2.0) * rng.integers(0, 2, n)
        out.append((base + rng.normal(0.0, math.radians(2.0), n)) % math.pi)
    return np.concatenate(out)


def test_support_and_the_strongest_other_family() -> None:
    rng = np.random.default_rng(0)
    dirs = _directions(rng, {0.0: 300, 30.0: 150})
    support = family_support(dirs, [0.0, math.radians(30.0)], math.radians(4.0))
    assert support[0] > 250
    assert support[1] > 120
    found = strongest_other_family(dirs, [0.0], math.radians(12.0), math.radians(4.0))
    assert found is not None
    assert abs(math.degrees(found[0]) - 30.0) < 1.5
    assert found[1] > 120
    # Once 30° is known, nothing else is strong.
    rest = strongest_other_family(
        dirs, [0.0, math.radians(30.0)], math.radians(12.0), math.radians(4.0)
    )
    assert rest is None or rest[1] < 20


def test_selection_switches_only_by_a_margin() -> None:
    rng = np.random.default_rng(1)
    frames = WallFrames(FrameParams(), [0.0, math.radians(30.0)])
    assert frames.select(_directions(rng, {0.0: 100, 30.0: 150})) == 0  # 1.5×: stays
    assert frames.select(_directions(rng, {0.0: 60, 30.0: 200})) == 1
    assert frames.select(_directions(rng, {0.0: 150, 30.0: 100})) == 1  # sticky
    assert frames.select(_directions(rng, {0.0: 200, 30.0: 40})) == 0


def test_a_straight_family_is_added_once_seen_over_enough_path() -> None:
    frames = WallFrames()
    a = math.radians(30.0)
    # Three agreeing observations within 1 m of path: not yet (could be a curved wall).
    assert not any(frames.observe(a + 1e-4 * k, 0.5 * k, 0.0) for k in range(3))
    assert frames.observe(a, 1.6, 0.0)
    assert frames.angles_rad == pytest.approx([0.0, a], abs=1e-3)
    assert frames.current == 0  # added, not selected: `select` decides


def test_a_curved_wall_is_not_a_family() -> None:
    frames = WallFrames()
    # The tangent of a wall of 40 m radius turns 1.4° per metre driven past it.
    added = [
        frames.observe(math.radians(30.0) + (0.25 * k) / 40.0, 0.25 * k, 0.0) for k in range(20)
    ]
    assert not any(added)
    assert frames.angles_rad == [0.0]


def test_a_family_near_a_known_one_is_not_added() -> None:
    frames = WallFrames()
    assert not any(frames.observe(math.radians(6.0), 0.5 * k, 0.0) for k in range(10))
    assert frames.angles_rad == [0.0]


def test_nearest_member_picks_the_family_and_quadrant() -> None:
    frames = WallFrames(FrameParams(), [0.0, math.radians(30.0)])
    heading, k = frames.nearest_member(math.radians(2.0), math.radians(121.0))
    assert k == 1
    assert math.degrees(heading) == pytest.approx(122.0)
    heading, k = frames.nearest_member(math.radians(2.0), math.radians(-85.0))
    assert k == 0
    assert math.degrees(heading) == pytest.approx(-88.0)


def test_a_provisional_first_family_is_replaced_by_the_first_strong_one() -> None:
    """The first scan saw weak walls (a curved wall): the building's walls, once measured,
    are the first family, not a second one next to a family that is not in the building."""
    frames = WallFrames(provisional=True)
    a = math.radians(17.0)
    assert not any(frames.observe(a, 0.5 * k, 0.0) for k in range(3))
    assert frames.observe(a, 1.6, 0.0)
    assert frames.angles_rad == pytest.approx([a], abs=1e-3)
    assert not frames.provisional
