"""The service's long-lived objects and their start/stop order (the composition root's core).

Start: lock the data directory, replay every session, open Zenoh, subscribe, start the syncer.
Stop (reverse): unsubscribe (no new samples), let workers drain, fsync and close recordings,
undeclare publishers, close Zenoh (an unclosed session with a callback subscriber hangs the
interpreter at exit), unlock the data directory.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from types import TracebackType
from typing import TYPE_CHECKING, Any

import zenoh

from clients.fleet import InstanceInfo, RobotPatterns, SessionEntry
from clients.keyexpr import (
    alive_wildcard,
    publisher_alive_wildcard,
    publisher_from_alive_key,
    robot_id_from_key,
    scan_wildcard,
)
from clients.zenoh_config import build_zenoh_config
from service.app import render
from service.app.errors import ConflictError, SettingsError, TransportError
from service.app.fanout import PoseFanout
from service.app.ingest import Ingest
from service.app.instance import FleetMember
from service.app.mapper import Engine, MapperPool
from service.app.metrics import Labels, Metrics, labels
from service.app.publishers import DUPLICATE_PUBLISHERS, PublisherGuard, PublisherStatus
from service.app.sessions import SessionManager
from service.app.settings import ServiceSettings, is_loopback_host
from service.app.store import DataDir, MapStore
from service.core.frontend.scan_matcher import warm_up

if TYPE_CHECKING:
    from clients.wire import Pose
    from service.app.backend import GraphSnapshot
    from service.app.foxglove import FoxgloveView
    from service.app.ingest import IngestStats
    from service.app.mapper_ingest import IngestConfig
    from service.app.metrics import Snapshot

log = logging.getLogger(__name__)

HOUSEKEEPING_PERIOD_S = 10.0


class MappingRuntime:
    def __init__(
        self,
        settings: ServiceSettings,
        *,
        engine: Engine | None = None,
        zenoh_config: zenoh.Config | None = None,
    ) -> None:
        self.settings = settings
        self.metrics = Metrics()
        self.data = DataDir(settings.storage.data_dir)
        self.maps = MapStore(self.data.maps_dir)
        processes = settings.ingest.mapper_processes
        if engine is None:
            engine = Engine(
                front_end=settings.ingest.front_end, loop_closure=settings.ingest.loop_closure
            )
        # With mapper processes they take the robots' scans from Zenoh themselves (the default);
        # this process does not subscribe to them (service/app/mapper_ingest.py). They connect
        # to this process's Zenoh endpoints, so without any the scans come through here.
        z = settings.zenoh
        self.ingest_in_mappers = settings.ingest.scans_in_mappers(bool(z.listen or z.connect))
        if processes and not self.ingest_in_mappers and settings.ingest.ingest_in_mappers is None:
            log.warning(
                "%d mapper processes, but no --zenoh-listen or --zenoh-connect endpoint for "
                "them to take the scans from: the scans go through the service's process",
                processes,
            )
        self.mapper_pool = (
            MapperPool(
                processes,
                engine,
                self._ingest_config if self.ingest_in_mappers else None,
                self._on_mapper_stats,
            )
            if processes
            else None
        )
        if self.mapper_pool is None:  # this process maps: its kernels load now (the processes'
            # do at their start), not on a robot's first scan
            threading.Thread(target=warm_up, name="warm-up", daemon=True).start()
        self.sessions = SessionManager(
            self.data,
            self.maps,
            fsync_each=settings.storage.fsync_interval_s == 0,
            engine=engine,
            make_mapper=self.mapper_pool.new_mapper if self.mapper_pool is not None else None,
            render_map_files=render.map_files,
            max_open_sessions=settings.ingest.max_robots,
            router=self.mapper_pool if self.ingest_in_mappers else None,
            on_pose=self._to_streams,
        )
        prefix = settings.zenoh.prefix
        self.fanout = PoseFanout(
            prefix,
            self.metrics,
            settings.http.sse_queue_depth,
            settings.http.sse_interval_s,
            settings.http.sse_max_writes_per_s,
        )
        self.metrics.counter(
            DUPLICATE_PUBLISHERS,
            "Second publishers detected on a robot's key (their scans are refused).",
        )
        self.publishers = PublisherGuard(
            on_refused=lambda robot: self.metrics.inc(
                "mapping_scans_rejected_total", reason="duplicate_publisher"
            ),
            on_intruder=lambda robot: self.metrics.inc(DUPLICATE_PUBLISHERS, robot=robot),
        )
        self.ingest = Ingest(
            prefix,
            self.sessions,
            self.fanout.publish,
            self.metrics,
            settings.ingest,
            admit=self.publishers.admit,
            forget=self.publishers.forget,
        )
        self.foxglove: FoxgloveView | None = None  # started with the runtime when configured
        self.patterns = RobotPatterns(settings.fleet.robots)
        self.instance_id = settings.fleet.effective_instance_id(settings.http.port)
        self.fleet = FleetMember(
            self.instance_id, prefix, self.describe, self.metrics, poll_s=settings.fleet.poll_s
        )
        self.http_url: str | None = None  # set once the HTTP socket is bound
        self._zenoh_config = zenoh_config
        self.zenoh: zenoh.Session | None = None
        self._subscribers: list[Any] = []
        self._alive: set[str] = set()
        self._alive_lock = threading.Lock()
        self._stop = threading.Event()
        self._syncer: threading.Thread | None = None
        self.fsync_errors = 0
        self.pruned_bytes = 0
        self.started_ns = 0
        self.metrics.gauge("mapping_sessions", "Sessions by state.", self._session_gauge)
        if self.mapper_pool is not None:
            pool = self.mapper_pool
            self.metrics.gauge(
                "mapping_mapper_restarts",
                "Mapper processes started again after they died.",
                lambda: [(labels(), float(pool.restarts))],
            )
        self.metrics.gauge(
            "mapping_sessions_status",
            "Sessions by restore status: ok, restoring, degraded (damage found and skipped), "
            "damaged (files that cannot be restored; kept for fsck).",
            self._status_gauge,
        )
        self.metrics.gauge(
            "mapping_session_records_lost",
            "Records lost to damage in a session's recording (a lower bound), by session.",
            lambda: self._damage_gauge("records_lost"),
        )
        self.metrics.gauge(
            "mapping_session_bytes_lost",
            "Bytes of a session's recording skipped as damaged, by session.",
            lambda: self._damage_gauge("bytes_lost"),
        )
        self.metrics.gauge(
            "mapping_session_checkpoints_rejected",
            "Checkpoints rejected at restore (checksum, format), by session: replayed instead.",
            lambda: self._damage_gauge("checkpoints_rejected"),
        )
        self.metrics.gauge(
            "mapping_recordings_open",
            "Recording files open (sessions whose robot sent a scan in the last 30 s).",
            lambda: [(labels(), float(sum(s.writer_open for s in self.sessions.list())))],
        )
        self.metrics.gauge(
            "mapping_recordings_pruned_bytes",
            "Bytes of covered scans pruned by the retention policy since the start.",
            lambda: [(labels(), float(self.pruned_bytes))],
        )
        self.metrics.gauge(
            "mapping_loop_closures_accepted",
            "Loop closures accepted into the pose graph, by session (loop closure on).",
            lambda: self._loop_gauge(accepted=True),
        )
        self.metrics.gauge(
            "mapping_loop_closures_rejected",
            "Loop closure searches refused, by session and reason.",
            lambda: self._loop_gauge(accepted=False),
        )
        self.metrics.gauge(
            "mapping_graph_solver_restarts",
            "iSAM2 rebuilt from every factor with QR after a failed update, by session.",
            self._solver_restart_gauge,
        )
        self.metrics.gauge(
            "mapping_robots_alive",
            "Robots whose agent liveliness token is present.",
            self._alive_gauge,
        )

    # -- mapper processes that ingest ----------------------------------------------------------

    def _ingest_config(self, index: int) -> IngestConfig:
        """Mapper process `index`'s share of the ingest: a Zenoh client of this service's
        endpoints (its listeners, reached on loopback; else the routers it connects to)."""
        from service.app.mapper_ingest import IngestConfig  # noqa: PLC0415

        z = self.settings.zenoh
        endpoints = tuple(_loopback(e) for e in z.listen) or tuple(z.connect)
        return IngestConfig(
            index=index,
            processes=self.settings.ingest.mapper_processes,
            prefix=z.prefix,
            patterns=tuple(RobotPatterns(self.settings.fleet.robots).patterns),
            endpoints=endpoints,
            settings=self.settings.ingest,
        )

    def _to_streams(self, pose: Pose) -> None:
        """A pose a mapper process published itself: the browser streams and the Foxglove
        view (which the ingest here would otherwise have fed)."""
        self.fanout.to_streams(pose)
        view = self.foxglove
        if view is not None:
            view.observe_pose(pose)

    def _on_mapper_stats(
        self, source: str, generation: int, snap: Snapshot, stats: IngestStats
    ) -> None:
        """A mapper process's counters (every half second): /metrics and /health add them."""
        self.metrics.set_external(source, generation, snap)
        self.ingest.remote[source] = stats

    # -- lifecycle -------------------------------------------------------------------------

    def start(self) -> None:
        try:
            self.data.open()
            self.maps.load()
            if self.mapper_pool is not None and not self.ingest_in_mappers:
                self.mapper_pool.start()
            t0 = time.monotonic()
            self.sessions.load_all()
            log.info(
                "found %d sessions in %s in %.2f s; restoring them in the background",
                len(self.sessions.list()),
                self.data.root,
                time.monotonic() - t0,
            )
            self._open_zenoh()
            if self.mapper_pool is not None and self.ingest_in_mappers:
                self.mapper_pool.start()  # their Zenoh sessions connect to ours
            self._start_foxglove()
            # HTTP serves at once: each session reports `restoring` until it is replayed.
            self.sessions.restore_all(background=True)
            self._syncer = threading.Thread(target=self._sync_loop, name="fsync", daemon=True)
            self._syncer.start()
            self.started_ns = time.time_ns()
        except BaseException:
            self.close()
            raise

    def _open_zenoh(self) -> None:
        z = self.settings.zenoh
        try:
            conf = self._zenoh_config or build_zenoh_config(
                mode=z.mode, listen=z.listen, connect=z.connect, config_file=z.config_file
            )
            self.zenoh = zenoh.open(conf)
        except zenoh.ZError as err:
            raise TransportError(f"cannot open Zenoh: {err}") from err
        self.fanout.attach_zenoh(self.zenoh)
        patterns = self.patterns.patterns
        for index, pattern in enumerate(patterns):
            on_scan: Any = self.ingest.on_sample
            if len(patterns) > 1:  # overlapping patterns: each scan is taken by its first one
                on_scan = functools.partial(self._on_scan, index)
            if not self.ingest_in_mappers:
                self._subscribers.append(
                    self.zenoh.declare_subscriber(scan_wildcard(z.prefix, pattern), on_scan)
                )
            self._subscribers.append(
                self.zenoh.liveliness().declare_subscriber(
                    alive_wildcard(z.prefix, pattern), self._on_alive, history=True
                )
            )
            # One token per publisher of a robot: who else publishes on its key (followed
            # where the scans arrive: here, or in the mapper processes that ingest).
            if not self.ingest_in_mappers:
                self._subscribers.append(
                    self.zenoh.liveliness().declare_subscriber(
                        publisher_alive_wildcard(z.prefix, pattern),
                        self._on_publisher_alive,
                        history=True,
                    )
                )
        log.info(
            "Zenoh session %s: %s subscribed to %s",
            self.zenoh.zid(),
            "the mapper processes" if self.ingest_in_mappers else "this process",
            ", ".join(scan_wildcard(z.prefix, p) for p in patterns),
        )
        for session in self.sessions.list():
            if session.is_active and not self.patterns.matches(session.robot_id):
                log.warning(
                    "session %s: robot %s matches none of --robots %s: it receives no scans",
                    session.id,
                    session.robot_id,
                    " ".join(patterns),
                )
        self.fleet.start(self.zenoh)

    def _on_scan(self, index: int, sample: Any) -> None:
        """Scan callback of pattern `index` when there are several: a robot matching two of
        them would otherwise be queued twice."""
        robot_id = robot_id_from_key(str(sample.key_expr), self.settings.zenoh.prefix)
        if robot_id is not None and self.patterns.first_match(robot_id) != index:
            return
        self.ingest.on_sample(sample)

    def _start_foxglove(self) -> None:
        port = self.settings.http.foxglove_port
        if not port:
            return
        from service.app.foxglove import FoxgloveView, zenoh_scan_tap  # noqa: PLC0415

        # With the scans in the mapper processes, a watched robot's scans are taken from
        # Zenoh here, for display only, while a viewer subscribes to them (foxglove.py).
        tap = None
        if self.ingest_in_mappers and self.zenoh is not None:
            tap = zenoh_scan_tap(self.zenoh, self.settings.zenoh.prefix)
        view = FoxgloveView(
            self.sessions.list, host=self.settings.http.host, port=port, scan_tap=tap
        )
        try:
            view.start()
        except OSError as err:
            raise SettingsError(str(err)) from err
        self.foxglove = view
        self.ingest.scan_observers.append(view.observe)
        if not is_loopback_host(self.settings.http.host):
            log.warning(
                "Foxglove view on %s: the token does not protect it (read-only: maps, scans "
                "and poses of every robot)",
                view.url,
            )

    def _on_alive(self, sample: Any) -> None:
        """Liveliness callback: just bookkeeping, never blocks."""
        robot_id = robot_id_from_key(str(sample.key_expr), self.settings.zenoh.prefix)
        if robot_id is None:
            return
        with self._alive_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(robot_id)
            else:
                self._alive.discard(robot_id)

    def _on_publisher_alive(self, sample: Any) -> None:
        """Per-publisher liveliness callback (`<prefix>/<id>/alive/<zid>`): bookkeeping."""
        parsed = publisher_from_alive_key(str(sample.key_expr), self.settings.zenoh.prefix)
        if parsed is not None:
            robot_id, source = parsed
            self.publishers.token_changed(robot_id, source, sample.kind == zenoh.SampleKind.PUT)

    def _sync_loop(self) -> None:
        """Group commit: fsync every recording that changed, once per interval; close the
        recordings of idle sessions; apply the retention policy."""
        interval = self.settings.storage.fsync_interval_s
        period = interval if interval > 0 else 1.0  # with 0 every append is fsynced already
        next_housekeeping = time.monotonic()
        while not self._stop.wait(period):
            if interval > 0:
                self._sync_once()
            if time.monotonic() >= next_housekeeping:
                next_housekeeping = time.monotonic() + HOUSEKEEPING_PERIOD_S
                self.housekeeping()

    def housekeeping(self) -> None:
        """Close idle recordings (descriptors) and prune what the retention policy allows."""
        self.sessions.close_idle()
        days = self.settings.storage.retain_recordings_days
        if days is not None and not self.sessions.restoring:
            freed = self.sessions.prune(days * 86400.0)
            if freed:
                log.info("retention: %d bytes of covered scans pruned", freed)
                self.pruned_bytes += freed

    def _sync_once(self) -> None:
        for session in self.sessions.list():
            try:
                session.sync()
            except OSError as err:
                self.fsync_errors += 1
                log.error("fsync of session %s failed: %s", session.id, err)

    def close(self) -> None:
        t0 = time.monotonic()
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except Exception as err:
                log.debug("undeclare: %s", err)
        self._subscribers.clear()
        self.fleet.close()
        self.ingest.close()
        if self.foxglove is not None:
            self.foxglove.close()
            self.foxglove = None
        self._stop.set()
        if self._syncer is not None:
            self._syncer.join(timeout=10)
            self._syncer = None
        self.sessions.sync_all()
        sessions_closed, checkpoints = self.sessions.close()
        if self.mapper_pool is not None:
            self.mapper_pool.close()
        self.fanout.close()
        zenoh_closed = self.zenoh is not None
        if self.zenoh is not None:
            close: Any = self.zenoh.close  # untyped in zenoh's stubs
            close()
            self.zenoh = None
        self.data.close()
        # One line an operator can trust: what was made durable, and that nothing is left open.
        log.info(
            "shut down in %.1f s: %d session(s) fsynced and closed, %d checkpoint(s) written, "
            "%s, data directory %s unlocked",
            time.monotonic() - t0,
            sessions_closed,
            checkpoints,
            "Zenoh session closed" if zenoh_closed else "no Zenoh session",
            self.settings.storage.data_dir,
        )

    def __enter__(self) -> MappingRuntime:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- fleet ---------------------------------------------------------------------------------

    def describe(self) -> InstanceInfo:
        """What this instance answers on `<prefix>/_instances/<id>/sessions` (no session lock:
        a scan being mapped must not delay the answer)."""
        sessions = tuple(
            SessionEntry(s.id, s.robot_id, "active" if s.is_active else s.state, s.scans_accepted)
            for s in self.sessions.list()
        )
        return InstanceInfo(
            instance_id=self.instance_id,
            patterns=self.patterns.patterns,
            http_url=self.http_url,
            started_ns=self.started_ns,
            sessions=sessions,
            robots_receiving=tuple(r.robot_id for r in self.ingest.robots()),
        )

    def check_claim(self, robot_id: str) -> None:
        """Refuse a session for a robot this instance does not serve, or one that another
        instance already maps (as last seen on Zenoh)."""
        if not self.patterns.matches(robot_id):
            raise ConflictError(
                f"robot {robot_id!r} matches none of this instance's robot patterns "
                f"({' '.join(self.patterns.patterns)}): start it on the instance that owns it"
            )
        other = self.fleet.active_elsewhere(robot_id)
        if other is not None:
            raise ConflictError(f"robot {robot_id!r} already has an active session on {other}")

    # -- observations ------------------------------------------------------------------------

    def publisher_status(self) -> list[PublisherStatus]:
        """Who publishes each robot's scans: this process's guard (liveliness tokens) and,
        for robots whose scans mapper processes take in, theirs (which saw the scans)."""
        merged = {p.robot_id: p for p in self.publishers.status()}
        for remote in list(self.ingest.remote.values()):
            merged.update((p.robot_id, p) for p in remote.publishers)
        return [merged[r] for r in sorted(merged)]

    def alive_robots(self) -> set[str]:
        with self._alive_lock:
            return set(self._alive)

    def _alive_gauge(self) -> list[tuple[Labels, float]]:
        return [(labels(), float(len(self.alive_robots())))]

    def _status_gauge(self) -> list[tuple[Labels, float]]:
        counts = dict.fromkeys(("ok", "restoring", "degraded", "damaged"), 0)
        for session in self.sessions.list():
            counts[session.status] += 1
        return [(labels(status=k), float(v)) for k, v in counts.items()]

    def _damage_gauge(self, name: str) -> list[tuple[Labels, float]]:
        out = []
        for session in self.sessions.list():
            value = getattr(session.damage, name)
            if value:
                out.append((labels(session=session.id), float(value)))
        return out

    def _graphs(self) -> list[tuple[str, GraphSnapshot]]:
        """Each session with a pose graph of at least one node, and that graph's counts."""
        out: list[tuple[str, GraphSnapshot]] = []
        for session in self.sessions.list():
            snap = session.graph_counts()
            if snap is not None and snap.nodes:
                out.append((session.id, snap))
        return out

    def _loop_gauge(self, *, accepted: bool) -> list[tuple[Labels, float]]:
        if accepted:
            return [(labels(session=sid), float(snap.accepted)) for sid, snap in self._graphs()]
        return [
            (labels(session=sid, reason=reason), float(n))
            for sid, snap in self._graphs()
            for reason, n in sorted(snap.rejected.items())
        ]

    def _solver_restart_gauge(self) -> list[tuple[Labels, float]]:
        return [(labels(session=sid), float(snap.solver_restarts)) for sid, snap in self._graphs()]

    def _session_gauge(self) -> list[tuple[Labels, float]]:
        counts = {"active": 0, "stopped": 0}
        for session in self.sessions.list():
            counts[session.state] += 1
        return [(labels(state=k), float(v)) for k, v in counts.items()]

    def zenoh_info(self) -> dict[str, Any]:
        session = self.zenoh
        if session is None or session.is_closed():
            return {"open": False}
        info = session.info
        return {
            "open": True,
            "zid": str(session.zid()),
            "peers": len(list(info.peers_zid())),
            "routers": len(list(info.routers_zid())),
        }


def _loopback(endpoint: str) -> str:
    """A listen endpoint as a process on this machine connects to it (`0.0.0.0` -> `127.0.0.1`)."""
    return endpoint.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:")
