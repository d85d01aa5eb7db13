"""Zenoh key expressions of the system: `<prefix>/<robot_id>/scan|pose|alive`, and the
per-publisher liveliness token `<prefix>/<robot_id>/alive/<zenoh_id>`."""

from __future__ import annotations

import re
from typing import Final

from clients.wire import WireError, check_robot_id, is_valid_robot_id

DEFAULT_PREFIX: Final = "robots"
_PREFIX_CHUNK: Final = re.compile(r"^[A-Za-z0-9_.\-]+$")
_ZENOH_ID: Final = re.compile(r"^[0-9a-f]{1,32}$")


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


def publisher_alive_key(robot_id: str, zenoh_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """The liveliness token of one publisher of a robot: Zenoh merges tokens on one key, so
    two agents with the same robot id look like one on `alive`; here each has its own."""
    if _ZENOH_ID.fullmatch(zenoh_id) is None:
        raise InvalidPrefixError(f"invalid Zenoh id {zenoh_id!r}")
    return f"{alive_key(robot_id, prefix)}/{zenoh_id}"


def publisher_alive_wildcard(prefix: str = DEFAULT_PREFIX, robots: str = "*") -> str:
    return f"{check_prefix(prefix)}/{_check_pattern(robots)}/alive/*"


def publisher_from_alive_key(key: str, prefix: str = DEFAULT_PREFIX) -> tuple[str, str] | None:
    """(robot id, Zenoh id) of a `<prefix>/<id>/alive/<zenoh id>` key, or None."""
    head = check_prefix(prefix) + "/"
    if not key.startswith(head):
        return None
    parts = key[len(head) :].split("/")
    if len(parts) != 3 or parts[1] != "alive" or not is_valid_robot_id(parts[0]):
        return None
    if _ZENOH_ID.fullmatch(parts[2]) is None:
        return None
    return parts[0], parts[2]


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
