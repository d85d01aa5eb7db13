"""The fleet documents and robot patterns (`clients.fleet`), without a network."""

from __future__ import annotations

import pytest

from clients.fleet import (
    FleetView,
    InstanceInfo,
    InvalidInstanceIdError,
    RobotPatterns,
    SessionEntry,
    find_conflicts,
    instance_id_from_key,
    instance_sessions_key,
    instance_token_key,
    patterns_intersect,
)
from clients.keyexpr import robot_id_from_key
from clients.wire import is_valid_robot_id


def info(instance_id: str, patterns: tuple[str, ...], *active: str) -> InstanceInfo:
    sessions = tuple(SessionEntry(f"s-{instance_id}-{r}", r, "active", 1) for r in active)
    return InstanceInfo(instance_id, patterns, None, 0, sessions)


def test_instance_keys_cannot_meet_a_robot_key() -> None:
    assert instance_token_key("svc-1") == "robots/_instances/svc-1"
    assert instance_sessions_key("svc-1", "site/a") == "site/a/_instances/svc-1/sessions"
    assert instance_id_from_key("robots/_instances/svc-1/sessions") == "svc-1"
    assert not is_valid_robot_id("_instances")
    assert robot_id_from_key("robots/_instances/alive") is None
    with pytest.raises(InvalidInstanceIdError):
        instance_token_key("a/b")


@pytest.mark.parametrize(
    ("a", "b", "overlap"),
    [
        ("*", "warehouse-a-*", True),
        ("warehouse-a-*", "warehouse-b-*", False),
        ("warehouse-a-*", "warehouse-a-1*", True),
        ("a-*", "*-1", True),
        ("amr-1", "amr-2", False),
        ("amr-1", "amr-*", True),
    ],
)
def test_pattern_overlap_is_zenohs_key_intersection(a: str, b: str, overlap: bool) -> None:
    assert patterns_intersect(a, b) is overlap


def test_a_robot_goes_to_the_first_pattern_it_matches() -> None:
    patterns = RobotPatterns(["wa-*", "wa-1*", "b"])
    assert patterns.first_match("wa-12") == 0
    assert patterns.first_match("b") == 2
    assert patterns.first_match("bb") is None
    assert RobotPatterns(()).patterns == ("*",)


def test_conflicts_name_overlapping_patterns_and_robots_mapped_twice() -> None:
    a = info("a", ("ov-*",), "ov-12")
    b = info("b", ("ov-1*", "x-*"), "ov-12")
    c = info("c", ("z-*",))
    (conflict,) = find_conflicts([c, b, a])
    assert conflict.instances == ("a", "b")
    assert conflict.patterns == (("ov-*", "ov-1*"),)
    assert conflict.robots == ("ov-12",)
    assert "both map ov-12" in conflict.describe()
    assert find_conflicts([a, c]) == []


def test_fleet_view_round_trips_and_refuses_bad_documents() -> None:
    view = FleetView((info("a", ("a-*",), "a-1"), info("b", ("a-*",))))
    again = FleetView.from_json(view.to_json())
    assert again.instances == view.instances
    assert len(again.conflicts) == 1
    with pytest.raises(ValueError, match="version"):
        InstanceInfo.from_json({"v": 2})
    bad = view.to_json()["instances"][0] | {"sessions": [{"session_id": "s"}]}
    with pytest.raises(ValueError, match="missing"):
        InstanceInfo.from_json(bad)
