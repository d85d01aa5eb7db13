"""Points where an earlier scan saw free space (`service.core.frontend.dynamic`)."""

from __future__ import annotations

import math
import pickle

import numpy as np

from service.core.frontend.dynamic import FreeSpace, SeenThroughParams, free_reach_m, seen_through
from service.core.types import Pose2D

INC = math.radians(0.25)
A_MIN = -math.radians(135.0)
N = 1081
ORIGIN = Pose2D(0.0, 0.0, 0.0)
PARAMS = SeenThroughParams()


def _points(ranges_m: np.ndarray) -> np.ndarray:
    a = A_MIN + INC * np.arange(N)
    ok = np.isfinite(ranges_m)
    return np.column_stack((np.cos(a[ok]), np.sin(a[ok]))) * ranges_m[ok, None]


def _free(ranges_m: np.ndarray, params: SeenThroughParams = PARAMS) -> FreeSpace:
    return FreeSpace.of(ORIGIN, ranges_m, 0.02, 30.0, A_MIN, INC, params)


def test_a_person_in_previously_free_space_is_flagged_and_the_walls_are_not() -> None:
    previous = np.full(N, 4.0)  # a round room of 4 m radius
    current = previous.copy()
    current[500:540] = 0.6  # somebody 0.6 m ahead
    moved = seen_through(_points(current), Pose2D(0.05, 0.0, 0.0), _free(previous), PARAMS)
    assert moved[505:535].all()  # the edges may be kept: within 0.1 m of a wall beam
    assert not moved[:500].any()
    assert not moved[540:].any()


def test_a_prediction_error_within_the_margin_flags_nothing() -> None:
    """A wall ahead and the pose predicted 0.25 m short of the truth: the wall's points land
    in front of where the previous beams ended, but within the margin."""
    previous = np.full(N, 3.0)
    current = previous - 0.25  # roughly: the wall is 0.25 m closer now
    assert not seen_through(_points(current), ORIGIN, _free(previous), PARAMS).any()


def test_no_return_is_free_only_nearby_and_a_blocked_beam_is_unknown() -> None:
    params = SeenThroughParams(no_return_reach_m=5.0)
    previous = np.full(N, np.nan)  # nothing returned: a corridor's beams along it
    previous[:300] = 0.01  # below the minimum range: blocked at the sensor, unknown
    reach = free_reach_m(previous, 0.02, 30.0, params)
    assert np.isnan(reach[:300]).all()
    assert (reach[300:] == 5.0).all()
    current = np.full(N, np.nan)
    current[100:140] = 0.6  # behind the blocked beams: no evidence
    current[500:540] = 0.6  # where the beams passed freely: moved in
    current[800:840] = 12.0  # a wall beyond what "no return" vouches for
    moved = seen_through(_points(current), ORIGIN, _free(previous, params), params)
    assert not moved[:40].any()
    assert moved[45:75].all()
    assert not moved[80:].any()


def test_every_beam_near_the_point_must_reach_beyond() -> None:
    """The edge of an opening: a few previous beams went through, their neighbours hit the jamb
    0.05 m away (within the lateral margin)."""
    previous = np.full(N, 2.0)
    previous[539:542] = 10.0  # three beams through a gap, 2.6 cm wide at 2 m
    current = np.full(N, np.nan)
    current[540] = 2.0
    assert not seen_through(_points(current), ORIGIN, _free(previous), PARAMS).any()


def test_free_space_survives_a_checkpoint_without_its_table() -> None:
    free = _free(np.linspace(1.0, 9.0, N))
    data = pickle.dumps(free)
    assert len(data) < 2 * N * 8  # the reach, not the 11 levels
    restored = pickle.loads(data)
    assert np.array_equal(restored.levels, free.levels)
