"""The map rule (`SlamSession.select`): keyframes, and a scan per `draw_period_s` of scan time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from clients.wire import PoseFlag
from service.core.slam import SlamSession
from service.core.types import LaserScan, Pose2D, PoseEstimate

pytestmark = pytest.mark.timeout(60)

PERIOD_NS = 25_000_000  # 40 Hz


def _scan(stamp_ns: int) -> LaserScan:
    return LaserScan(stamp_ns, -0.75 * math.pi, 1.5 * math.pi / 1080, np.full(1081, 3.0), 0.1, 30.0)


def _estimate(
    stamp_ns: int, keyframe: bool = False, flags: PoseFlag = PoseFlag.NONE
) -> PoseEstimate:
    return PoseEstimate(stamp_ns, Pose2D(0.0, 0.0, 0.0), 1.0, flags, keyframe)


def test_a_40_hz_robot_standing_still_draws_one_scan_a_second() -> None:
    session = SlamSession(map_resolution_m=0.05, keep_trajectory=False)
    drawn = [
        session.select(_scan(i * PERIOD_NS), _estimate(i * PERIOD_NS)).drawn for i in range(121)
    ]
    # The first scan, then one each second of scan time (scans 40, 80, 120): not every 5th.
    assert [i for i, d in enumerate(drawn) if d] == [0, 40, 80, 120]


def test_keyframes_are_always_drawn_and_degenerate_scans_never() -> None:
    session = SlamSession(map_resolution_m=0.05, keep_trajectory=False)
    assert session.select(_scan(0), _estimate(0)).drawn
    assert session.select(_scan(PERIOD_NS), _estimate(PERIOD_NS, keyframe=True)).drawn
    late = 10 * 10**9
    assert not session.select(_scan(late), _estimate(late, flags=PoseFlag.DEGENERATE)).drawn
    assert session.select(_scan(late + PERIOD_NS), _estimate(late + PERIOD_NS)).drawn


def test_a_session_restored_from_a_checkpoint_of_the_every_nth_scan_rule_draws_on() -> None:
    """A checkpoint restores a session's attributes one by one (`statecodec`): one written
    before the rule was in scan time has a scan count and no stamp; the class's defaults
    stand in, and the next usable scan is drawn."""
    session = SlamSession(map_resolution_m=0.05, keep_trajectory=False)
    session.select(_scan(0), _estimate(0))
    old = dict(session.__dict__)
    for name in ("_drawn_stamp_ns", "draw_period_s"):
        del old[name]
    old.update(_since_drawn=3, integrate_every=5)
    restored = object.__new__(SlamSession)
    restored.__dict__.update(old)
    assert restored.select(_scan(PERIOD_NS), _estimate(PERIOD_NS)).drawn
    assert not restored.select(_scan(2 * PERIOD_NS), _estimate(2 * PERIOD_NS)).drawn
