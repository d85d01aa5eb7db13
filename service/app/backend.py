"""The live back end: loop search and the pose graph beside the 40 Hz front end, never in its way.

`LocalMapper.map_scan` runs the front end and answers at once; a keyframe is handed to the
session's `LiveBackend` (a non-blocking append). One thread per process (`BackendScheduler`)
serves every session's back end round-robin, one node per turn, as the ingest pool serves
robots: submaps, loop search, iSAM2 (`service.core.slam.SlamBackend`, pure). What the front
end reads back is published, not computed on demand: after each node the thread swaps in
- the newest node's correction (optimised ∘ front-end⁻¹), which moves every later front-end
  pose onto the graph (the published pose);
- a `GraphSnapshot` (nodes, closures, counters), at most every `VIEW_PERIOD_S` and at once
  after a closure;
- the map composed from the chunks at the optimised poses, at most every `RENDER_PERIOD_S`.
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

from service.core.maps.grid import GridImage
from service.core.slam import SlamBackend, SlamParams
from service.core.types import LaserScan, Pose2D

log = logging.getLogger(__name__)

VIEW_PERIOD_S: Final = 0.5  # graph snapshots, at most this often (and after every closure)
RENDER_PERIOD_S: Final = 1.0  # the composed map, at most this often
RECENT_REJECTED: Final = 100  # refused searches shown in a snapshot
# The back end's thread runs this much nicer than the pose path (Linux, where a thread has its
# own nice value): on cores the front end also needs, the back end falls behind (its queue,
# `pending`, grows) and the 40 Hz poses do not.
BACKEND_NICE: Final = 10

# A node waiting for the back end: (scan, front-end pose, covariance (9), flags, pose sequence).
NodeItem = tuple[LaserScan, Pose2D, tuple[float, ...], int, int]


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
    """One session's back end, fed by the front end's thread and run by the scheduler's."""

    def __init__(
        self,
        resolution_m: float,
        params: SlamParams | None = None,
        scheduler: BackendScheduler | None = None,
    ) -> None:
        self._resolution_m = resolution_m
        self._params = params if params is not None else SlamParams()
        self._scheduler = scheduler if scheduler is not None else _SCHEDULER
        self._core = SlamBackend(self._params, map_resolution_m=resolution_m)
        self._work = threading.Lock()  # held while the core changes (a node, a render)
        self._lock = threading.Lock()  # guards the queue and the published references
        self._queue: deque[NodeItem] = deque()
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
        self._image_revision = 0
        self._image_due = False
        self._view_due = False
        self._timer_armed = False
        self._last_view_s = 0.0
        self._last_render_s = 0.0
        self.errors = 0
        self._idle = threading.Condition(self._lock)

    # -- front end's side (never waits for the work) -----------------------------------------

    def submit(self, scan: LaserScan, pose: Pose2D, covariance: Any, flags: int, seq: int) -> None:
        cov = tuple(float(v) for v in covariance)
        with self._lock:
            if self._closed:
                return
            self._queue.append((scan, pose, cov, int(flags), int(seq)))
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
        with self._lock:
            return self._image

    # -- the scheduler's side --------------------------------------------------------------

    def step(self) -> bool:
        """Process one queued node (and publish what changed); True while more are queued."""
        with self._work:
            with self._lock:
                item = self._queue.popleft() if self._queue else None
                generation = self._generation
            closure = False
            if item is not None:
                scan, pose, cov, flags, seq = item
                try:
                    closure = self._core.add_node(scan, pose, cov, flags, seq)
                except Exception:
                    self.errors += 1
                    if self.errors == 1 or math.log2(self.errors).is_integer():
                        log.exception(
                            "back end failed on node seq %d (%d so far)", seq, self.errors
                        )
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
            now = time.monotonic()
            if self._view_due and (
                closure or not queued or now - self._last_view_s >= VIEW_PERIOD_S
            ):
                self._publish_view()
            if self._image_due and (closure or now - self._last_render_s >= RENDER_PERIOD_S):
                self._render()
            if not queued and self._image_due and not self._timer_armed:
                # Drawn at most once a period: come back when it is due, not before.
                self._timer_armed = True
                delay = max(0.0, RENDER_PERIOD_S - (now - self._last_render_s))
                timer = threading.Timer(delay, self._render_due)
                timer.daemon = True
                timer.start()
            if not queued and not self._image_due:
                with self._lock:
                    self._idle.notify_all()
            return queued > 0

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
            snap = GraphSnapshot(
                revision=self._revision,
                node_seq=np.array(core.node_seq, dtype=np.int64),
                frontend=fe,
                optimised=opt,
                closures=closures,
                accepted=core.stats.accepted,
                rejected=dict(core.stats.rejected),
                pending=len(self._queue),
                errors=self.errors,
                image_revision=self._image_revision,
                map_bytes=core.chunks.nbytes if core.chunks is not None else 0,
                solver_restarts=core.graph.isam_restarts,
                corrections=_corrections(fe, opt),
            )
            self._snapshot = snap
            self._unpublished = len(self._queue)
        self._view_due = False
        self._last_view_s = time.monotonic()

    def _render(self) -> None:
        core = self._core
        if core.chunks is None:
            self._image_due = False
            return
        image = core.chunks.compose([_snap(c) for c in core.corrections()])
        with self._lock:
            self._image = image
            self._image_revision += 1
            # A new map is a new revision too: readers that hold the last one ask again.
            self._revision += 1
            self._snapshot = replace(
                self._snapshot, revision=self._revision, image_revision=self._image_revision
            )
        self._image_due = False
        self._last_render_s = time.monotonic()

    # -- control -----------------------------------------------------------------------------

    def wait_idle(self, timeout_s: float = 60.0) -> bool:
        """Until every queued node is in the graph and the map is drawn (tests, shutdown)."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._queue or self.scheduled or self._view_due or self._image_due:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._idle.wait(min(left, 0.05))
        return True

    def state(self, encode: Callable[[dict[str, Any]], bytes]) -> bytes:
        """`encode` of the core and the nodes still queued (plain data for `statecodec`), with
        the back end's thread held off the core until it is encoded (it waits for the node
        being processed, at most one)."""
        with self._work:
            with self._lock:
                queued = list(self._queue)
            return encode({"core": self._core, "queued": queued})

    def restore(self, state: dict[str, Any]) -> None:
        core = state["core"]
        if not isinstance(core, SlamBackend):
            raise TypeError("not a back end state")
        with self._work:
            with self._lock:
                self._generation += 1
                self._core = core
                self._queue = deque(state.get("queued", ()))
                self._unpublished = len(self._queue) + 1
                self._correction = _snap(core.latest_correction())
                self._revision += 1
            self._view_due = self._image_due = True
        self._scheduler.schedule(self)

    def reset(self) -> None:
        with self._work:
            with self._lock:
                self._generation += 1
                self._queue.clear()
                self._unpublished = 1
                self._core = SlamBackend(self._params, map_resolution_m=self._resolution_m)
                self._correction = Pose2D(0.0, 0.0, 0.0)
                self._revision += 1
                self._image = None
                self._image_revision += 1
            self._view_due = True
        self._scheduler.schedule(self)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._queue.clear()
