"""This instance's place in a fleet of mapping services: presence, self-description, clashes.

On Zenoh (keys in `clients.fleet`), with no coordinator of our own:
- a liveliness token `<prefix>/_instances/<id>`: present while we run; a crash removes it when
  the transport closes (at once for a killed process, after the lease on a silent link);
- a queryable `<prefix>/_instances/<id>/sessions` answering our patterns, sessions and robots;
- a watcher thread that asks every instance once per `poll_s` (and at once when an instance
  token appears or goes) and reports each conflict with us once: a WARNING log line, `/health`
  degraded, and `mapping_fleet_conflicts`. A conflict is two instances whose robot patterns
  overlap, or that both have an active session for one robot.

The Zenoh callbacks here only reply from a snapshot or set an event: the `get` runs in the
watcher thread (a `get` inside a callback can deadlock).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from clients.fleet import (
    Conflict,
    FleetView,
    InstanceInfo,
    find_conflicts,
    instance_sessions_key,
    instance_token_key,
    instances_wildcard,
    query_fleet,
)
from service.app.metrics import Labels, Metrics, labels

log = logging.getLogger(__name__)

FLEET_CONFLICTS = "mapping_fleet_conflicts"
FLEET_INSTANCES = "mapping_fleet_instances"


class FleetMember:
    def __init__(
        self,
        instance_id: str,
        prefix: str,
        describe: Callable[[], InstanceInfo],
        metrics: Metrics,
        *,
        poll_s: float = 1.0,
        query_timeout_s: float = 2.0,
    ) -> None:
        self.instance_id = instance_id
        self._prefix = prefix
        self._describe = describe
        self._poll_s = poll_s
        self._timeout_s = query_timeout_s
        self._session: zenoh.Session | None = None
        self._entities: list[Any] = []  # token, queryable, subscriber: dropping undeclares
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._view = FleetView(instances=())
        self._conflicts: dict[tuple[str, str], Conflict] = {}
        metrics.gauge(
            FLEET_CONFLICTS, "Other instances that claim robots of this one.", self._conflict_gauge
        )
        metrics.gauge(
            FLEET_INSTANCES, "Mapping-service instances seen (this one included).", self._inst_gauge
        )

    def start(self, session: zenoh.Session) -> None:
        self._session = session
        key = instance_sessions_key(self.instance_id, self._prefix)
        self._entities.append(session.declare_queryable(key, self._on_query))
        self._entities.append(
            session.liveliness().declare_token(instance_token_key(self.instance_id, self._prefix))
        )
        self._entities.append(
            session.liveliness().declare_subscriber(
                instances_wildcard(self._prefix), self._on_presence, history=True
            )
        )
        self._thread = threading.Thread(target=self._watch, name="fleet", daemon=True)
        self._thread.start()
        log.info("fleet: instance %s announced on %s", self.instance_id, key)

    # -- Zenoh callbacks (never block) -------------------------------------------------------

    def _on_query(self, query: Any) -> None:
        try:
            body = json.dumps(self._describe().to_json(), separators=(",", ":"))
            query.reply(
                instance_sessions_key(self.instance_id, self._prefix),
                body,
                encoding=zenoh.Encoding.APPLICATION_JSON,
            )
        except Exception:  # a callback that raises only prints
            log.exception("fleet: answering a query failed")

    def _on_presence(self, sample: Any) -> None:
        self._wake.set()  # an instance came or went: look again now

    # -- watcher ---------------------------------------------------------------------------

    def _watch(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()
            try:
                self._update(self.query())
            except Exception as err:  # the session closing, or a network error: try again
                if self._stop.is_set():
                    return
                log.debug("fleet: query failed: %s", err)
            self._wake.wait(self._poll_s)
            if self._wake.is_set():
                self._stop.wait(0.1)  # a burst of tokens (a restart): one query for them all

    def query(self) -> FleetView:
        """The fleet now (blocking, up to the query timeout); this instance always included."""
        session = self._session
        if session is None or session.is_closed():
            raise RuntimeError("Zenoh is not open")
        view = query_fleet(session, self._prefix, self._timeout_s)
        if all(i.instance_id != self.instance_id for i in view.instances):
            # Our own reply timed out (a busy process): describe ourselves directly.
            instances = sorted((*view.instances, self._describe()), key=lambda i: i.instance_id)
            alive = tuple(a for a in view.alive_without_answer if a != self.instance_id)
            view = FleetView(tuple(instances), alive, tuple(find_conflicts(instances)))
        return view

    def _update(self, view: FleetView) -> None:
        mine = {c.instances: c for c in view.conflicts if self.instance_id in c.instances}
        with self._lock:
            before = self._conflicts
            self._conflicts = mine
            self._view = view
        for key, conflict in mine.items():
            old = before.get(key)
            if old is None or old.robots != conflict.robots or old.patterns != conflict.patterns:
                log.warning("fleet conflict: %s", conflict.describe())
        for key in before.keys() - mine.keys():
            log.info("fleet conflict resolved: instances %s and %s", *key)

    # -- reads -------------------------------------------------------------------------------

    def conflicts(self) -> list[Conflict]:
        with self._lock:
            return sorted(self._conflicts.values(), key=lambda c: c.instances)

    def last_view(self) -> FleetView:
        with self._lock:
            return self._view

    def active_elsewhere(self, robot_id: str) -> str | None:
        """Another instance with an active session for `robot_id`, if any: asked now (the
        last periodic view when the query fails)."""
        try:
            view = self.query()
        except Exception as err:
            log.debug("fleet: query failed, using the last view: %s", err)
            view = self.last_view()
        for info in view.instances:
            if info.instance_id != self.instance_id and robot_id in info.active_robots:
                return info.instance_id
        return None

    def _conflict_gauge(self) -> list[tuple[Labels, float]]:
        return [(labels(), float(len(self.conflicts())))]

    def _inst_gauge(self) -> list[tuple[Labels, float]]:
        return [(labels(), float(len(self.last_view().instances)))]

    def close(self) -> None:
        """Stop watching and undeclare (before the Zenoh session closes)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=self._timeout_s + 5)
            self._thread = None
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except Exception as err:
                log.debug("fleet: undeclare: %s", err)
        self._entities.clear()
        self._session = None
