"""Key-expression helpers: the shapes of the keys, and refusal of unsafe ids and prefixes."""

from __future__ import annotations

import pytest
import zenoh

from clients.keyexpr import (
    DEFAULT_PREFIX,
    InvalidPrefixError,
    alive_key,
    alive_wildcard,
    check_prefix,
    pose_key,
    pose_wildcard,
    robot_id_from_key,
    scan_key,
    scan_wildcard,
)
from clients.wire import InvalidRobotIdError, WireError

KEY_FUNCS = [scan_key, pose_key, alive_key]
WILDCARD_FUNCS = [scan_wildcard, pose_wildcard, alive_wildcard]


def test_default_shapes() -> None:
    assert DEFAULT_PREFIX == "robots"
    assert scan_key("amr-07") == "robots/amr-07/scan"
    assert pose_key("amr-07") == "robots/amr-07/pose"
    assert alive_key("amr-07") == "robots/amr-07/alive"
    assert scan_wildcard() == "robots/*/scan"
    assert pose_wildcard() == "robots/*/pose"
    assert alive_wildcard() == "robots/*/alive"


def test_custom_prefix() -> None:
    assert scan_key("r1", prefix="site-a/fleet") == "site-a/fleet/r1/scan"
    assert pose_wildcard(prefix="site-a/fleet") == "site-a/fleet/*/pose"


@pytest.mark.parametrize("func", KEY_FUNCS)
@pytest.mark.parametrize(
    "robot_id", ["", "a/b", "*", "**", "a*", "$*", "a$b", "a b", "a?b", "a#b", "-a", "x" * 65]
)
def test_unsafe_robot_ids_are_refused(func: object, robot_id: str) -> None:
    with pytest.raises(InvalidRobotIdError):
        func(robot_id)  # type: ignore[operator]


@pytest.mark.parametrize(
    "prefix", ["", "/", "/robots", "robots/", "a//b", "robots/*", "**", "a b", "r$", "r?", "r#"]
)
def test_unsafe_prefixes_are_refused(prefix: str) -> None:
    with pytest.raises(InvalidPrefixError):
        check_prefix(prefix)
    with pytest.raises(InvalidPrefixError):
        scan_key("r1", prefix=prefix)
    with pytest.raises(InvalidPrefixError):
        scan_wildcard(prefix=prefix)


@pytest.mark.parametrize("pattern", ["", "a/b", "**", "a**", "a b", "$*", "a?"])
def test_unsafe_robot_patterns_are_refused(pattern: str) -> None:
    for func in WILDCARD_FUNCS:
        with pytest.raises(InvalidPrefixError):
            func(robots=pattern)


def test_errors_share_the_package_base() -> None:
    assert issubclass(InvalidPrefixError, WireError)
    assert issubclass(InvalidRobotIdError, WireError)


@pytest.mark.parametrize("robot_id", ["a", "amr-07", "warehouse-a.unit_3", "X" * 64])
@pytest.mark.parametrize("prefix", ["robots", "site-a/fleet.1"])
def test_keys_are_valid_zenoh_key_expressions(robot_id: str, prefix: str) -> None:
    for func, wildcard in zip(KEY_FUNCS, WILDCARD_FUNCS, strict=True):
        key = zenoh.KeyExpr(func(robot_id, prefix=prefix))
        assert str(key) == func(robot_id, prefix=prefix)
        assert zenoh.KeyExpr(wildcard(prefix=prefix)).includes(key)
    # A scan subscription never matches another robot's poses or presence.
    assert not zenoh.KeyExpr(scan_wildcard(prefix=prefix)).intersects(
        zenoh.KeyExpr(pose_key(robot_id, prefix=prefix))
    )


@pytest.mark.parametrize(
    ("pattern", "matches", "misses"),
    [
        ("*", ["a", "warehouse-a-7"], []),
        ("warehouse-a-*", ["warehouse-a-1", "warehouse-a-xyz", "warehouse-a-"], ["warehouse-b-1"]),
        ("*-07", ["amr-07", "x-07"], ["amr-08"]),
        ("a*b", ["ab", "axxb"], ["ba", "abc"]),
        ("amr-07", ["amr-07"], ["amr-070"]),
    ],
)
def test_robot_patterns_split_a_fleet(pattern: str, matches: list[str], misses: list[str]) -> None:
    # Zenoh accepts `*` only as a whole chunk; inside a chunk the helper must write `$*`.
    for func, wildcard in zip(KEY_FUNCS, WILDCARD_FUNCS, strict=True):
        sub = zenoh.KeyExpr(wildcard(robots=pattern))
        for robot_id in matches:
            assert sub.includes(zenoh.KeyExpr(func(robot_id))), (pattern, robot_id)
        for robot_id in misses:
            assert not sub.intersects(zenoh.KeyExpr(func(robot_id))), (pattern, robot_id)


def test_sub_chunk_wildcard_spelling() -> None:
    assert scan_wildcard(robots="warehouse-a-*") == "robots/warehouse-a-$*/scan"


def test_robot_id_from_key() -> None:
    assert robot_id_from_key("robots/amr-07/scan") == "amr-07"
    assert robot_id_from_key("site/a/r1/pose", prefix="site/a") == "r1"
    assert robot_id_from_key("other/amr-07/scan") is None
    assert robot_id_from_key("robots/amr-07") is None
    assert robot_id_from_key("robots/a/b/scan") is None
    assert robot_id_from_key("robotsx/amr-07/scan") is None
    assert robot_id_from_key("robots/a b/scan") is None
    assert robot_id_from_key("robots/-x/scan") is None
