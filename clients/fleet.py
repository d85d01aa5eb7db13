"""The fleet view: which mapping-service instances are up, which robots each claims, and clashes.

Every instance of `mapping-service serve` declares on Zenoh (see docs/architecture.md):

- a liveliness token `<prefix>/_instances/<instance_id>` (present while the instance runs);
- a queryable `<prefix>/_instances/<instance_id>/sessions` answering one JSON document
  (`InstanceInfo.to_json`): its robot patterns, HTTP address, sessions and the robots it
  receives scans from.

Robot ids never start with `_` (`clients.wire.is_valid_robot_id`), so `_instances` cannot be a
robot's chunk and none of these keys meets a robot's `scan`/`pose`/`alive` key. There is no
coordinator: anyone on the Zenoh network (`mapctl fleet`, any instance's `GET /fleet`) builds the
same view from one `get` on `<prefix>/_instances/*/sessions`.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import zenoh

from clients.keyexpr import DEFAULT_PREFIX, check_prefix, scan_wildcard
from clients.wire import is_valid_robot_id

log = logging.getLogger(__name__)

INSTANCES_CHUNK: Final = "_instances"  # starts with `_`: no robot id can be this chunk
INFO_VERSION: Final = 1
_INSTANCE_ID: Final = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")


class InvalidInstanceIdError(ValueError):
    """An instance id that is not one safe key-expression chunk."""


def check_instance_id(instance_id: str) -> str:
    if _INSTANCE_ID.fullmatch(instance_id) is None:
        raise InvalidInstanceIdError(
            f"invalid instance id {instance_id!r}: use 1-64 characters from [A-Za-z0-9_.-], "
            "starting with a letter or digit"
        )
    return instance_id


def instance_token_key(instance_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """The instance's liveliness token."""
    return f"{check_prefix(prefix)}/{INSTANCES_CHUNK}/{check_instance_id(instance_id)}"


def instance_sessions_key(instance_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """The instance's queryable: its patterns, sessions and robots as JSON."""
    return instance_token_key(instance_id, prefix) + "/sessions"


def instances_wildcard(prefix: str = DEFAULT_PREFIX) -> str:
    return f"{check_prefix(prefix)}/{INSTANCES_CHUNK}/*"


def instances_sessions_wildcard(prefix: str = DEFAULT_PREFIX) -> str:
    return instances_wildcard(prefix) + "/sessions"


def instance_id_from_key(key: str, prefix: str = DEFAULT_PREFIX) -> str | None:
    head = f"{check_prefix(prefix)}/{INSTANCES_CHUNK}/"
    if not key.startswith(head):
        return None
    rest = key[len(head) :].split("/", maxsplit=1)[0]
    return rest if _INSTANCE_ID.fullmatch(rest) else None


# -- robot patterns ------------------------------------------------------------------------------


def pattern_regex(pattern: str) -> re.Pattern[str]:
    """`warehouse-a-*` as a regex over robot ids (`*`: any run of id characters)."""
    scan_wildcard(DEFAULT_PREFIX, pattern)  # validates: one chunk of safe characters and `*`
    parts = [re.escape(p) for p in pattern.split("*")]
    return re.compile("^" + r"[A-Za-z0-9_.\-]*".join(parts) + "$")


def patterns_intersect(a: str, b: str) -> bool:
    """Whether some robot id matches both patterns (Zenoh's own key-expression algebra)."""
    return bool(
        zenoh.KeyExpr(scan_wildcard(DEFAULT_PREFIX, a)).intersects(
            zenoh.KeyExpr(scan_wildcard(DEFAULT_PREFIX, b))
        )
    )


class RobotPatterns:
    """The robots one instance maps: ids matching any of its patterns (`*` = all)."""

    def __init__(self, patterns: Sequence[str] = ("*",)) -> None:
        self.patterns: tuple[str, ...] = tuple(dict.fromkeys(patterns)) or ("*",)
        self._regexes = [pattern_regex(p) for p in self.patterns]

    def first_match(self, robot_id: str) -> int | None:
        """Index of the first pattern `robot_id` matches, None if none does."""
        for index, regex in enumerate(self._regexes):
            if regex.fullmatch(robot_id):
                return index
        return None

    def matches(self, robot_id: str) -> bool:
        return self.first_match(robot_id) is not None

    def overlaps(self, others: Iterable[str]) -> list[tuple[str, str]]:
        """(ours, theirs) pattern pairs that some robot id matches both of."""
        return [(a, b) for a in self.patterns for b in others if patterns_intersect(a, b)]


# -- the documents ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SessionEntry:
    session_id: str
    robot_id: str
    state: str
    scans_accepted: int

    def to_json(self) -> dict[str, Any]:
        return {
            "session_id": self.session_id,
            "robot_id": self.robot_id,
            "state": self.state,
            "scans_accepted": self.scans_accepted,
        }


@dataclass(frozen=True, slots=True)
class InstanceInfo:
    """What one instance answers on its queryable."""

    instance_id: str
    patterns: tuple[str, ...]
    http_url: str | None
    started_ns: int
    sessions: tuple[SessionEntry, ...] = ()
    robots_receiving: tuple[str, ...] = ()  # robots whose scans reach this instance

    @property
    def active_robots(self) -> set[str]:
        return {s.robot_id for s in self.sessions if s.state == "active"}

    def to_json(self) -> dict[str, Any]:
        return {
            "v": INFO_VERSION,
            "instance_id": self.instance_id,
            "patterns": list(self.patterns),
            "http_url": self.http_url,
            "started_ns": self.started_ns,
            "sessions": [s.to_json() for s in self.sessions],
            "robots_receiving": list(self.robots_receiving),
        }

    @staticmethod
    def from_json(body: Any) -> InstanceInfo:
        """Parse one reply; `ValueError` says what is wrong with it."""
        if not isinstance(body, dict) or body.get("v") != INFO_VERSION:
            raise ValueError("not an instance document of version 1")
        try:
            sessions = tuple(
                SessionEntry(
                    str(s["session_id"]),
                    str(s["robot_id"]),
                    str(s["state"]),
                    int(s["scans_accepted"]),
                )
                for s in body["sessions"]
            )
            info = InstanceInfo(
                instance_id=check_instance_id(str(body["instance_id"])),
                patterns=tuple(str(p) for p in body["patterns"]),
                http_url=None if body.get("http_url") is None else str(body["http_url"]),
                started_ns=int(body["started_ns"]),
                sessions=sessions,
                robots_receiving=tuple(str(r) for r in body.get("robots_receiving", ())),
            )
        except (KeyError, TypeError) as err:
            raise ValueError(f"missing or mistyped field: {err}") from err
        if not all(is_valid_robot_id(s.robot_id) for s in info.sessions):
            raise ValueError("a session names an invalid robot id")
        return info


@dataclass(frozen=True, slots=True)
class Conflict:
    """Two instances that claim the same robots.

    `robots` are robots with an active session on both (both map them); `patterns` are the
    pattern pairs that overlap (both would map any such robot once a session exists).
    """

    instances: tuple[str, str]
    patterns: tuple[tuple[str, str], ...]
    robots: tuple[str, ...]

    def describe(self) -> str:
        a, b = self.instances
        what = []
        if self.robots:
            what.append("both map " + ", ".join(self.robots))
        if self.patterns:
            what.append(
                "overlapping robot patterns " + ", ".join(f"{p!r}/{q!r}" for p, q in self.patterns)
            )
        return f"instances {a} and {b} claim the same robots: {'; '.join(what)}"

    def to_json(self) -> dict[str, Any]:
        return {
            "instances": list(self.instances),
            "patterns": [list(p) for p in self.patterns],
            "robots": list(self.robots),
            "detail": self.describe(),
        }


def find_conflicts(instances: Sequence[InstanceInfo]) -> list[Conflict]:
    """Every pair of instances whose patterns overlap or that both map a robot."""
    out: list[Conflict] = []
    ordered = sorted(instances, key=lambda i: i.instance_id)
    for i, a in enumerate(ordered):
        for b in ordered[i + 1 :]:
            patterns = tuple(RobotPatterns(a.patterns).overlaps(b.patterns))
            robots = tuple(sorted(a.active_robots & b.active_robots))
            if patterns or robots:
                out.append(Conflict((a.instance_id, b.instance_id), patterns, robots))
    return out


@dataclass(frozen=True, slots=True)
class FleetView:
    instances: tuple[InstanceInfo, ...]
    alive_without_answer: tuple[str, ...] = ()  # tokens present, no (readable) reply in time
    conflicts: tuple[Conflict, ...] = field(default=())

    def to_json(self) -> dict[str, Any]:
        return {
            "instances": [i.to_json() for i in self.instances],
            "alive_without_answer": list(self.alive_without_answer),
            "conflicts": [c.to_json() for c in self.conflicts],
        }

    @staticmethod
    def from_json(body: Any) -> FleetView:
        if not isinstance(body, dict):
            raise ValueError("not a fleet document")
        instances = tuple(InstanceInfo.from_json(i) for i in body.get("instances", ()))
        return FleetView(
            instances=instances,
            alive_without_answer=tuple(str(x) for x in body.get("alive_without_answer", ())),
            conflicts=tuple(find_conflicts(instances)),
        )


def query_fleet(
    session: zenoh.Session, prefix: str = DEFAULT_PREFIX, timeout_s: float = 2.0
) -> FleetView:
    """Ask every instance on the network (blocking: never call it from a Zenoh callback)."""
    infos: dict[str, InstanceInfo] = {}
    replies = session.get(
        instances_sessions_wildcard(prefix),
        target=zenoh.QueryTarget.ALL,  # every instance, not the "best" one
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout_s,
    )
    for reply in replies:
        ok = reply.ok
        if ok is None:
            continue
        try:
            info = InstanceInfo.from_json(json.loads(ok.payload.to_bytes()))
        except ValueError as err:  # json.JSONDecodeError is a ValueError
            log.warning("unreadable instance reply on %s: %s", ok.key_expr, err)
            continue
        infos[info.instance_id] = info
    alive: set[str] = set()
    for reply in session.liveliness().get(instances_wildcard(prefix), timeout=timeout_s):
        ok = reply.ok
        if ok is not None:
            instance_id = instance_id_from_key(str(ok.key_expr), prefix)
            if instance_id is not None:
                alive.add(instance_id)
    instances = tuple(sorted(infos.values(), key=lambda i: i.instance_id))
    return FleetView(
        instances=instances,
        alive_without_answer=tuple(sorted(alive - set(infos))),
        conflicts=tuple(find_conflicts(instances)),
    )
