"""One publisher per robot key: detect a second one, and refuse its scans.

Two agents configured with the same robot id (or anyone on the Zenoh network) can publish on
`<prefix>/<id>/scan`; merged into one session, their scans make the pose jump between two
buildings. Zenoh gives two signals, both declared by the publisher (so they catch mistakes, not
an attacker: against those, Zenoh's own authentication and access control are the answer):

- the sample's source id (`sample.source_info.source_id.zid`), which `sensor-agent` sets on
  every scan;
- a liveliness token per publisher, `<prefix>/<id>/alive/<zid>`, beside the robot's shared
  `<prefix>/<id>/alive` (tokens on one key are merged by Zenoh: two agents look like one).

The first source seen owns the robot's key. Scans of any other source (or without a source id
once the owner has one) are refused while the owner is present: its per-publisher token is
alive, or it published within `takeover_after_s`. When the owner is gone (its token was
withdrawn, or it fell silent without a token), the next source takes the key over: an agent
restarted with a new Zenoh session continues at once.

`PublisherGuard.admit` runs in the Zenoh callback: dictionary work under one lock, no IO.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final

log = logging.getLogger(__name__)

DUPLICATE_PUBLISHERS: Final = "mapping_duplicate_publishers_total"
DEFAULT_TAKEOVER_AFTER_S: Final = 5.0
# A conflict stays flagged in /health this long after the second publisher's last scan.
DEFAULT_CONFLICT_HOLD_S: Final = 30.0
# Robots tracked at most (a flood of made-up robot ids must not grow memory without bound;
# ingest has its own, lower robot limit, and drops the scans of robots beyond it).
DEFAULT_MAX_ROBOTS: Final = 4096
_MAX_LOGGED: Final = 4096


@dataclass(slots=True)
class _RobotPublishers:
    owner: str | None = None  # source id (Zenoh id, hex) holding the key; None = unknown
    owner_last_ns: int = 0  # monotonic ns of the owner's last admitted scan
    tokens: set[str] = field(default_factory=set)  # live per-publisher liveliness tokens
    refused: int = 0  # scans refused as coming from a second publisher
    intruders: set[str] = field(default_factory=set)  # other sources seen (bounded)
    last_refused_ns: int = 0


@dataclass(frozen=True, slots=True)
class PublisherStatus:
    robot_id: str
    owner: str | None
    publishers: int  # live per-publisher tokens
    refused: int
    conflict: bool  # a second publisher is active now


def source_id_of(sample: Any) -> str | None:
    """The Zenoh id of the session that published `sample`, if it said (unstable API)."""
    try:
        info = sample.source_info
        return None if info is None else str(info.source_id.zid)
    except Exception:  # a Zenoh without the unstable API, or a malformed source info
        return None


class PublisherGuard:
    """Tracks who publishes each robot's scans; `admit()` says whether to take a scan."""

    def __init__(
        self,
        *,
        takeover_after_s: float = DEFAULT_TAKEOVER_AFTER_S,
        conflict_hold_s: float = DEFAULT_CONFLICT_HOLD_S,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        on_refused: Callable[[str], None] | None = None,
        on_intruder: Callable[[str], None] | None = None,
        max_robots: int = DEFAULT_MAX_ROBOTS,
        speaks_for: Callable[[str], bool] | None = None,
    ) -> None:
        """`speaks_for(robot_id)`: whether this guard logs a second publisher's token for
        that robot (several mapper processes follow every token; the robot's own logs it)."""
        self._max_robots = max_robots
        self._speaks_for = speaks_for
        self._takeover_ns = int(takeover_after_s * 1e9)
        self._hold_ns = int(conflict_hold_s * 1e9)
        self._clock_ns = clock_ns
        self._on_refused = on_refused
        self._on_intruder = on_intruder
        self._robots: dict[str, _RobotPublishers] = {}
        self._lock = threading.Lock()
        self._logged: set[tuple[str, str | None]] = set()

    # -- signals ----------------------------------------------------------------------------

    def token_changed(self, robot_id: str, source: str, present: bool) -> None:
        """A per-publisher liveliness token `<prefix>/<robot>/alive/<source>` came or went."""
        with self._lock:
            robot = self._robots.get(robot_id)
            if robot is None:
                if not present or len(self._robots) >= self._max_robots:
                    return
                robot = self._robots[robot_id] = _RobotPublishers()
            if present:
                robot.tokens.add(source)
            else:
                robot.tokens.discard(source)
            count, owner = len(robot.tokens), robot.owner
        speaks = self._speaks_for is None or self._speaks_for(robot_id)
        if present and count > 1 and source != owner and speaks:
            # Same log key as a refused scan of that source: one line per second publisher.
            self._log_once(
                robot_id,
                source,
                "a second publisher (%s) appeared while %s holds the key (%d publishers): "
                "refusing its scans",
                source,
                owner or "another publisher",
                count,
            )

    def admit(self, robot_id: str, source: str | None) -> bool:
        """True to take the scan; False if it comes from a second publisher (counted)."""
        now = self._clock_ns()
        takeover_from: str | None = None
        new_intruder = False
        owner: str | None = None
        with self._lock:
            robot = self._robots.get(robot_id)
            if robot is None:
                if len(self._robots) >= self._max_robots:
                    return True  # untracked: ingest's robot limit decides
                robot = self._robots[robot_id] = _RobotPublishers()
            if source is not None and source == robot.owner:
                robot.owner_last_ns = now
                return True
            if robot.owner is None:
                if source is not None:  # the first source with an id owns the key
                    robot.owner = source
                robot.owner_last_ns = now
                return True
            if self._owner_gone(robot, now):
                takeover_from, robot.owner = robot.owner, source
                robot.owner_last_ns = now
            else:
                robot.refused += 1
                robot.last_refused_ns = now
                new_intruder = source not in robot.intruders and len(robot.intruders) < 64
                if new_intruder:
                    robot.intruders.add(source or "?")
                owner = robot.owner
        if takeover_from is not None:
            log.info(
                "robot %s: publisher %s took over the key from %s (gone)",
                robot_id,
                source or "without a source id",
                takeover_from,
            )
            return True
        if self._on_refused is not None:
            self._on_refused(robot_id)
        if new_intruder and self._on_intruder is not None:
            self._on_intruder(robot_id)
        self._log_once(
            robot_id,
            source,
            "a second publisher (%s) sends scans while %s holds the key: refusing its scans",
            source or "without a source id",
            owner,
        )
        return False

    def forget(self, robot_id: str) -> None:
        """Ingest forgot a silent robot: drop its entry unless a publisher token is present
        (valid scans on made-up ids must not fill `max_robots` here for good either)."""
        with self._lock:
            robot = self._robots.get(robot_id)
            if robot is not None and not robot.tokens:
                del self._robots[robot_id]
                self._logged = {k for k in self._logged if k[0] != robot_id}

    def _owner_gone(self, robot: _RobotPublishers, now: int) -> bool:
        if robot.owner in robot.tokens:
            return False
        return now - robot.owner_last_ns > self._takeover_ns

    # -- observations -------------------------------------------------------------------------

    def status(self) -> list[PublisherStatus]:
        now = self._clock_ns()
        with self._lock:
            return [
                PublisherStatus(
                    robot_id=robot_id,
                    owner=r.owner,
                    publishers=len(r.tokens),
                    refused=r.refused,
                    conflict=len(r.tokens) > 1
                    or (r.refused > 0 and now - r.last_refused_ns <= self._hold_ns),
                )
                for robot_id, r in sorted(self._robots.items())
            ]

    def _log_once(self, robot_id: str, source: str | None, message: str, *args: object) -> None:
        key = (robot_id, source)
        with self._lock:
            if key in self._logged or len(self._logged) >= _MAX_LOGGED:
                return
            self._logged.add(key)
        log.warning("robot %s: " + message + " [duplicate_publisher]", robot_id, *args)


__all__ = ["PublisherGuard", "PublisherStatus", "source_id_of"]
