"""The live back end: the back half of a session's core beside the 40 Hz front end, off its path.

A session's core is one `service.core.slam.SlamSession`, the same class `mapping-service map`
runs. `LocalMapper.map_scan` runs its front half (`SlamSession.track`: the front end and the
map rule) and answers at once; what the back half needs (a keyframe, a scan to draw) is handed
to the session's `LiveBackend` (a non-blocking append). One thread per process
(`BackendScheduler`) serves every session's back end round-robin, one item per turn, as the
ingest pool serves robots, and runs the back half on it (`SlamSession.integrate`: submaps,
loop search, iSAM2, the map's scans) in the order tracked, so that once it is idle its nodes,
closures and map are the offline run's. What the front end reads back is published, not
computed on demand: after each item the thread swaps in
- the newest node's correction (optimised ∘ front-end⁻¹), which moves every later front-end
  pose onto the graph (the published pose);
- a `GraphSnapshot` (nodes, closures, counters), at most every `VIEW_PERIOD_S` and at once
  after a closure;
- the map's revision, at most every `RENDER_PERIOD_S` (at most `RENDER_SHARE` of the
  thread's time) and at once after a closure; and with it, while somebody reads the map (a read
  in the last `WATCHED_S`), the map at the current corrections (`SlamSession.map_image`: the
  frozen map chunks composed at their anchors' corrections, a cost that grows with the chunks,
  not the scans). A read of a map nobody watched asks this thread to draw it at its next turn
  (`image` answers None meanwhile; the reader asks again), so a read is never older than one
  period, a request never draws (in a mapper process it would hold the process's pipe, and so
  every session's front end in it), and a fleet nobody watches spends nothing on drawing maps.
`finish` (a stopped session) queues the core's final search and batch optimisation.
Reads take references under a lock held for microseconds, never the lock of the work.

In a mapper process this all runs in that process (the service asks it over the pipe).
"""

from __future__ import annotations

import logging
import math
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from clients.wire import PoseFlag
from service.core.maps.grid import GridImage
from service.core.slam import SlamBackend, SlamSession, Tracked
from service.core.types import Pose2D, PoseEstimate

log = logging.getLogger(__name__)

VIEW_PERIOD_S: Final = 0.5  # graph snapshots, at most this often (and after every closure)
RENDER_PERIOD_S: Final = 1.0  # the map's revision, at most this often
# The thread draws each revision while the map was read in the last WATCHED_S (the live page
# reads it every 1.5 s, Foxglove every second); otherwise only when a read asks (`image`).
WATCHED_S: Final = 30.0
# ... and at most this share of the thread's time: composing every chunk grows with the area
# travelled (a few ms on a 91 m loop).
RENDER_SHARE: Final = 0.25
RECENT_REJECTED: Final = 100  # refused searches shown in a snapshot
# The back end's thread runs this much nicer than the pose path (Linux, where a thread has its
# own nice value): on cores the front end also needs, the back end falls behind (its queue,
# `pending`, grows) and the 40 Hz poses do not.
BACKEND_NICE: Final = 10

# Work waiting for the back half: a tracked scan and its pose sequence, or None: finish.
BackItem = tuple[Tracked, int] | None


def plain_item(item: BackItem) -> tuple[Any, ...] | None:
    """`item` as checkpoint data (its flags as an int: `PoseFlag` is the wire's, not data)."""
    if item is None:
        return None
    tracked, seq = item
    e = tracked.estimate
    estimate = (e.stamp_ns, e.pose, e.quality, int(e.flags), e.is_keyframe, e.covariance)
    return (tracked.scan, estimate, tracked.node, tracked.drawn, seq)


def item_of(plain: tuple[Any, ...] | None) -> BackItem:
    """`plain_item` undone."""
    if plain is None:
        return None
    scan, (stamp_ns, pose, quality, flags, keyframe, covariance), node, drawn, seq = plain
    estimate = PoseEstimate(
        int(stamp_ns), pose, float(quality), PoseFlag(flags), bool(keyframe), tuple(covariance)
    )
    return Tracked(scan, estimate, bool(node), bool(drawn)), int(seq)


@dataclass(frozen=True, slots=True)
class Closure:
    from_node: int  # the older node (the submap's anchor)
    to_node: int  # the query node
    score: float
    accepted: bool
    reason: str


@dataclass(frozen=True, slots=True)
class GraphSnapshot:
    """The back end's graph at one moment, as plain data (picklable across the mapper pipe)."""

    revision: int
    node_seq: npt.NDArray[np.int64]  # (N,) each node's pose sequence
    frontend: npt.NDArray[np.float64]  # (N, 3) x, y, theta
    optimised: npt.NDArray[np.float64]  # (N, 3)
    closures: tuple[Closure, ...]  # every accepted one, then the latest refused ones
    accepted: int
    rejected: dict[str, int]
    pending: int  # nodes queued, not yet in the graph
    errors: int  # nodes the back end failed on (logged)
    image_revision: int
    map_bytes: int = 0  # the map chunks' memory
    solver_restarts: int = 0  # iSAM2 rebuilt with QR after a failed update (`PoseGraph`)
    corrections: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def nodes(self) -> int:
        return int(self.node_seq.shape[0])


EMPTY_SNAPSHOT: Final = GraphSnapshot(
    0, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), (), 0, {}, 0, 0, 0
)


# A correction below this (m, rad) is none: iSAM2 rebuilt from a checkpoint agrees with the one
# that never stopped to ~1e-14, and a pose must not change in its last bits for that.
NO_CORRECTION: Final = 1e-9


def _corrections(frontend: npt.NDArray[np.float64], optimised: npt.NDArray[np.float64]) -> Any:
    """Per node: optimised ∘ frontend⁻¹ as (N, 3) (x, y, theta); rounding noise is 0."""
    dth = optimised[:, 2] - frontend[:, 2]
    c, s = np.cos(dth), np.sin(dth)
    x = optimised[:, 0] - (c * frontend[:, 0] - s * frontend[:, 1])
    y = optimised[:, 1] - (s * frontend[:, 0] + c * frontend[:, 1])
    out = np.stack([x, y, np.arctan2(np.sin(dth), np.cos(dth))], axis=1)
    out[np.abs(out) < NO_CORRECTION] = 0.0
    return out


def _snap(c: Pose2D) -> Pose2D:
    return Pose2D(*(0.0 if abs(v) < NO_CORRECTION else float(v) for v in c))


def correct_poses(
    snapshot: GraphSnapshot, seqs: npt.NDArray[np.int64], xyt: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """Front-end poses (N, 3) of sequences `seqs` moved by their latest node's correction."""
    if snapshot.nodes == 0 or xyt.shape[0] == 0:
        return xyt
    node = np.searchsorted(snapshot.node_seq, seqs, side="right") - 1
    corr = snapshot.corrections
    has = node >= 0
    c = corr[np.clip(node, 0, None)]
    c[~has] = 0.0
    cs, sn = np.cos(c[:, 2]), np.sin(c[:, 2])
    out = np.empty_like(xyt)
    out[:, 0] = c[:, 0] + cs * xyt[:, 0] - sn * xyt[:, 1]
    out[:, 1] = c[:, 1] + sn * xyt[:, 0] + cs * xyt[:, 1]
    th = xyt[:, 2] + c[:, 2]
    out[:, 2] = (th + math.pi) % (2 * math.pi) - math.pi
    none = (c == 0.0).all(axis=1)
    out[none] = xyt[none]  # no correction: the pose exactly as recorded
    return out


class BackendScheduler:
    """One thread serving every back end of this process, one node per turn (round-robin)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._ready: deque[LiveBackend] = deque()
        self._thread: threading.Thread | None = None

    def schedule(self, backend: LiveBackend) -> None:
        with self._lock:
            if backend.scheduled:
                # Being stepped (or queued): step it once more after this turn, so that a wake-up
                # arriving during its step (the render timer) is not lost.
                backend.again = True
                return
            backend.scheduled = True
            self._ready.append(backend)
            self._wake.notify()
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="backend", daemon=True)
                self._thread.start()

    def _run(self) -> None:
        _lower_thread_priority(BACKEND_NICE)
        while True:
            with self._lock:
                while not self._ready:
                    self._wake.wait()
                backend = self._ready.popleft()
            more = False
            try:
                more = backend.step()
            except Exception:  # the thread must not die: every session's back end needs it
                log.exception("back end step failed")
            with self._lock:
                if more or backend.again:
                    backend.again = False
                    self._ready.append(backend)
                else:
                    backend.scheduled = False


def _lower_thread_priority(increment: int) -> None:
    """This thread's nice value raised by `increment` (Linux only: elsewhere a thread id is
    not a process id, and `setpriority` would reach another process)."""
    if not sys.platform.startswith("linux"):
        return
    tid = threading.get_native_id()
    try:
        nice = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, nice + increment))
    except OSError as err:  # a sandbox without setpriority: the back end runs at the same priority
        log.warning("back end thread keeps the pose path's priority: %s", err)


_SCHEDULER = BackendScheduler()


class LiveBackend:
    """The back half of one session's core (`SlamSession`), fed by the front end's thread and
    run by the scheduler's. The front half (`SlamSession.track`) stays with the caller."""

    def __init__(self, session: SlamSession, scheduler: BackendScheduler | None = None) -> None:
        self._session = session
        self._scheduler = scheduler if scheduler is not None else _SCHEDULER
        self._work = threading.Lock()  # held while the core's back half changes (work, render)
        self._lock = threading.Lock()  # guards the queue and the published references
        self._queue: deque[BackItem] = deque()
        self.scheduled = False  # guarded by the scheduler's lock
        self.again = False  # scheduled again while scheduled (guarded by the scheduler's lock)
        self._closed = False
        self._generation = 0  # bumped by reset/restore: items of an older core are dropped
        self._revision = 0
        self._correction = Pose2D(0.0, 0.0, 0.0)
        self._snapshot = EMPTY_SNAPSHOT
        # Work not yet in `_snapshot` (nodes queued or being added; 1 for a restored or reset
        # core): a snapshot read between a submit and the next view must not say "pending 0".
        self._unpublished = 0
        self._image: GridImage | None = None
        self._image_revision = 0  # the map's: bumped when a changed map is published
        self._image_of = -1  # the revision `_image` shows (-1: none)
        self._image_due = False  # the map changed since the last revision
        self._draw_wanted = False  # a reader waits for the map at its revision (guarded)
        self._view_due = False
        self._timer_armed = False
        self._last_view_s = 0.0
        self._last_map_s = 0.0  # the last map revision published
        self._render_cost_s = 0.0  # the last render's duration
        self._watched_until_s = 0.0  # rendered in the background until then (`WATCHED_S`)
        self.errors = 0
        self._idle = threading.Condition(self._lock)

    @property
    def _core(self) -> SlamBackend:
        """The core's back end (its graph, submaps and loop search)."""
        return self._session.backend

    # -- front end's side (never waits for the work) -----------------------------------------

    def submit(self, tracked: Tracked, seq: int) -> None:
        """Queue a tracked scan's back half (a node, a scan to draw)."""
        self._put((tracked, int(seq)))

    def finish(self) -> None:
        """Queue the core's final search and batch optimisation (after the queued scans)."""
        self._put(None)

    def _put(self, item: BackItem) -> None:
        with self._lock:
            if self._closed:
                return
            self._queue.append(item)
            if item is None or item[0].node:
                self._unpublished += 1
        self._scheduler.schedule(self)

    def correction(self) -> tuple[int, Pose2D, int]:
        """(graph revision, the newest node's correction, image revision)."""
        with self._lock:
            return self._revision, self._correction, self._image_revision

    def snapshot(self) -> GraphSnapshot:
        with self._lock:
            snap = self._snapshot
            if snap.pending != self._unpublished:
                snap = replace(snap, pending=self._unpublished)
            return snap

    def image(self) -> GridImage | None:
        """The map at its latest revision; None while the back end's thread draws it, at its
        next turn (nobody read it in the last `WATCHED_S`, so it was not drawn): ask again.
        Either way the thread draws each revision for the next `WATCHED_S`."""
        if not self._session.has_map:
            raise ValueError("this session keeps no map (map_resolution_m is None)")
        with self._lock:
            self._watched_until_s = time.monotonic() + WATCHED_S
            if self._image_of == self._image_revision:
                return self._image
            self._draw_wanted = True
        self._scheduler.schedule(self)
        return None

    # -- the scheduler's side --------------------------------------------------------------

    def step(self) -> bool:
        """Process one queued item (and publish what changed); True while more are queued."""
        with self._work:
            with self._lock:
                has_item = bool(self._queue)
                item = self._queue.popleft() if has_item else None
                generation = self._generation
            closure = False
            if has_item:
                closure, changed = self._apply(item)
                if changed:
                    correction = _snap(self._core.latest_correction())
                    with self._lock:
                        if generation == self._generation:
                            self._revision += 1
                            self._correction = correction
                    self._view_due = True
                self._image_due = True
                if closure:
                    log.info(
                        "loop closure %d accepted at node %d",
                        self._core.stats.accepted,
                        self._core.node_count - 1,
                    )
            with self._lock:
                queued = len(self._queue)
                wanted, self._draw_wanted = self._draw_wanted, False
            now = time.monotonic()
            if self._view_due and (
                closure or not queued or now - self._last_view_s >= VIEW_PERIOD_S
            ):
                self._publish_view()
            period = self._render_period()
            if self._image_due and (closure or wanted or now - self._last_map_s >= period):
                self._publish_map(drawn=wanted or now < self._watched_until_s)
            elif wanted:
                self._draw()
            if not queued and self._image_due and not self._timer_armed:
                # Drawn at most once a period: come back when it is due, not before.
                self._timer_armed = True
                delay = max(0.0, self._render_period() - (now - self._last_map_s))
                timer = threading.Timer(delay, self._render_due)
                timer.daemon = True
                timer.start()
            if not queued and not self._image_due:
                with self._lock:
                    self._idle.notify_all()
            return queued > 0

    def _apply(self, item: BackItem) -> tuple[bool, bool]:
        """One item on the core: (a closure was accepted, the graph changed)."""
        session = self._session
        try:
            if item is None:
                nodes = session.backend.node_count
                accepted = session.stats.accepted
                session.finish()
                return session.stats.accepted > accepted, nodes > 0
            tracked, seq = item
            return session.integrate(tracked, seq), tracked.node
        except Exception:
            self.errors += 1
            if self.errors == 1 or math.log2(self.errors).is_integer():
                seq = -1 if item is None else item[1]
                log.exception("back end failed on seq %d (%d so far)", seq, self.errors)
            return False, item is None or item[0].node

    def _render_period(self) -> float:
        return max(RENDER_PERIOD_S, self._render_cost_s / RENDER_SHARE)

    def _render_due(self) -> None:
        self._timer_armed = False
        self._scheduler.schedule(self)

    def _publish_view(self) -> None:
        core = self._core
        n = core.node_count
        fe = np.array(core.node_frontend, dtype=np.float64).reshape(n, 3)
        opt = np.array(core.node_poses(), dtype=np.float64).reshape(n, 3)
        recent = list(core.stats.recent_rejected)[-RECENT_REJECTED:]
        closures = tuple(
            Closure(r.anchor_node, r.query_node, float(r.score), r.accepted, r.reason)
            for r in [*core.stats.closures, *recent]
        )
        with self._lock:
            pending = sum(1 for item in self._queue if item is None or item[0].node)
            snap = GraphSnapshot(
                revision=self._revision,
                node_seq=np.array(core.node_seq, dtype=np.int64),
                frontend=fe,
                optimised=opt,
                closures=closures,
                accepted=core.stats.accepted,
                rejected=dict(core.stats.rejected),
                pending=pending,
                errors=self.errors,
                image_revision=self._image_revision,
                map_bytes=self._session.map_bytes,
                solver_restarts=core.graph.isam_restarts,
                corrections=_corrections(fe, opt),
            )
            self._snapshot = snap
            self._unpublished = pending
        self._view_due = False
        self._last_view_s = time.monotonic()

    def _render(self) -> GridImage:
        """The map at the current corrections (`_work` held; the session keeps one)."""
        t0 = time.perf_counter()
        image = self._session.map_image()
        self._render_cost_s = time.perf_counter() - t0
        return image

    def _draw(self) -> None:
        """The map at the published revision, for a reader (`_work` held)."""
        image = self._render()
        with self._lock:
            self._image, self._image_of = image, self._image_revision

    def _publish_map(self, *, drawn: bool) -> None:
        """A new map revision, drawn when `drawn` (else at a reader's request: `image`)."""
        self._image_due = False
        if not self._session.has_map:
            return
        image = self._render() if drawn else None
        with self._lock:
            self._image_revision += 1
            if drawn:
                self._image, self._image_of = image, self._image_revision
            # A new map is a new revision too: readers that hold the last one ask again.
            self._revision += 1
            self._snapshot = replace(
                self._snapshot, revision=self._revision, image_revision=self._image_revision
            )
        self._last_map_s = time.monotonic()

    # -- control -----------------------------------------------------------------------------

    def wait_idle(self, timeout_s: float = 60.0) -> bool:
        """Until every queued item is in the core and the map's revision published (tests,
        shutdown; a read then draws the map, if the back end did not)."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._queue or self.scheduled or self._view_due or self._image_due:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._idle.wait(min(left, 0.05))
        return True

    def state(self, encode: Callable[[list[Any]], bytes]) -> bytes:
        """`encode` of the items still queued (`plain_item`), with the back end's thread held
        off the core until it is encoded (it waits for the item being processed, at most one)."""
        with self._work:
            with self._lock:
                queued = [plain_item(item) for item in self._queue]
            return encode(queued)

    def restore(self, session: SlamSession, queued: list[Any]) -> None:
        """Run `session` (restored from a checkpoint) with its `queued` items (`state`)."""
        with self._work:
            with self._lock:
                self._generation += 1
                self._session = session
                self._queue = deque(item_of(plain) for plain in queued)
                self._unpublished = len(self._queue) + 1
                self._correction = _snap(session.backend.latest_correction())
                self._revision += 1
                self._image_of = -1  # the image was the old core's
            self._view_due = self._image_due = True
        self._scheduler.schedule(self)

    def reset(self, session: SlamSession) -> None:
        """Start again on a fresh `session`."""
        with self._work:
            with self._lock:
                self._generation += 1
                self._queue.clear()
                self._unpublished = 1
                self._session = session
                self._correction = Pose2D(0.0, 0.0, 0.0)
                self._revision += 1
                self._image, self._image_of = None, -1
                self._image_revision += 1
            self._view_due = True
        self._scheduler.schedule(self)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._queue.clear()
