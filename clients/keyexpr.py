"""Zenoh key expressions of the system: `<prefix>/<robot_id>/scan|pose|alive`."""

from __future__ import annotations

import re
from typing import Final

from clients.wire import WireError, check_robot_id, is_valid_robot_id

DEFAULT_PREFIX: Final = "robots"
_PREFIX_CHUNK: Final = re.compile(r"^[A-Za-z0-9_.\-]+$")


class InvalidPrefixError(WireError, ValueError):
    """A key-expression prefix with wildcards, empty chunks or unsafe characters."""


def check_prefix(prefix: str) -> str:
    """Return `prefix` if it is one or more safe chunks separated by `/`, else raise."""
    chunks = prefix.split("/")
    if not prefix or any(_PREFIX_CHUNK.fullmatch(c) is None for c in chunks):
        raise InvalidPrefixError(
            f"invalid key prefix {prefix!r}: use chunks of [A-Za-z0-9_.-] separated by '/'"
        )
    return prefix


def scan_key(robot_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    return f"{check_prefix(prefix)}/{check_robot_id(robot_id)}/scan"


def pose_key(robot_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    return f"{check_prefix(prefix)}/{check_robot_id(robot_id)}/pose"


def alive_key(robot_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    return f"{check_prefix(prefix)}/{check_robot_id(robot_id)}/alive"


def scan_wildcard(prefix: str = DEFAULT_PREFIX, robots: str = "*") -> str:
    """Subscription for many robots: `robots="*"` or a pattern such as `warehouse-a-*`."""
    return f"{check_prefix(prefix)}/{_check_pattern(robots)}/scan"


def pose_wildcard(prefix: str = DEFAULT_PREFIX, robots: str = "*") -> str:
    return f"{check_prefix(prefix)}/{_check_pattern(robots)}/pose"


def alive_wildcard(prefix: str = DEFAULT_PREFIX, robots: str = "*") -> str:
    return f"{check_prefix(prefix)}/{_check_pattern(robots)}/alive"


def robot_id_from_key(key: str, prefix: str = DEFAULT_PREFIX) -> str | None:
    """The robot id in `<prefix>/<id>/<leaf>`, or None if the key does not have that shape
    or the id is not a safe robot id."""
    head = check_prefix(prefix) + "/"
    if not key.startswith(head):
        return None
    parts = key[len(head) :].split("/")
    if len(parts) != 2 or not is_valid_robot_id(parts[0]):
        return None
    return parts[0]


def _check_pattern(robots: str) -> str:
    """One chunk of safe characters and `*`, as a valid Zenoh chunk.

    Zenoh only accepts `*` as a whole chunk; inside a chunk the sub-chunk wildcard is `$*`,
    so `warehouse-a-*` becomes `warehouse-a-$*`.
    """
    if robots == "*":
        return robots
    if "/" in robots or "**" in robots or not re.fullmatch(r"[A-Za-z0-9_.\-*]+", robots):
        raise InvalidPrefixError(f"invalid robot pattern {robots!r}: one chunk, '*' allowed")
    return robots.replace("*", "$*")
