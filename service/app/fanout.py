"""Pose fan-out: every new pose goes to Zenoh (`<prefix>/<robot>/pose`) and to browser streams.

Neither path can slow the estimator:
- Zenoh publishers use `CongestionControl.DROP`, so a slow or dead network subscriber costs the
  worker at most a non-blocking enqueue in Zenoh's transmit queue;
- each browser stream has its own bounded `asyncio.Queue` on the HTTP event loop. A worker only
  schedules one `call_soon_threadsafe` per pose; the loop then offers the pose to every stream,
  dropping that stream's oldest pose when it is full (counted), so one stalled browser never
  delays the others or the worker.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import zenoh

from clients.keyexpr import pose_key
from clients.wire import Pose, encode_pose
from service.app.metrics import Labels, Metrics, labels

log = logging.getLogger(__name__)

POSES_PUBLISHED = "mapping_poses_published_total"
POSE_PUBLISH_ERRORS = "mapping_pose_publish_errors_total"
STREAM_SUBSCRIBERS = "mapping_pose_stream_subscribers"
STREAM_DROPPED = "mapping_pose_stream_dropped_total"
ZENOH_POSE_SUBSCRIBERS = "mapping_zenoh_pose_subscribers_present"


@dataclass(eq=False)
class PoseStream:
    """One browser's subscription to one session's poses. `None` in the queue ends it."""

    session_id: str
    queue: asyncio.Queue[Pose | None]
    dropped: int = 0


@dataclass
class _Streams:
    by_session: dict[str, set[PoseStream]] = field(default_factory=lambda: defaultdict(set))


class PoseFanout:
    def __init__(self, prefix: str, metrics: Metrics, stream_queue_depth: int) -> None:
        self._prefix = prefix
        self._metrics = metrics
        self._depth = stream_queue_depth
        self._zenoh: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._pub_lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._streams = _Streams()
        self._stream_count = 0  # read by workers without the loop; written on the loop
        self._closed = False
        metrics.counter(POSES_PUBLISHED, "Poses published on Zenoh.")
        metrics.counter(POSE_PUBLISH_ERRORS, "Zenoh pose publications that failed.")
        metrics.counter(STREAM_DROPPED, "Poses dropped for slow browser streams (oldest first).")
        metrics.gauge(STREAM_SUBSCRIBERS, "Open browser pose streams.", self._stream_gauge)
        metrics.gauge(
            ZENOH_POSE_SUBSCRIBERS,
            "1 when at least one Zenoh subscriber matches the robot's pose key.",
            self._matching_gauge,
        )

    # -- wiring ----------------------------------------------------------------------------

    def attach_zenoh(self, session: zenoh.Session | None) -> None:
        self._zenoh = session

    def bind_loop(self, loop: asyncio.AbstractEventLoop | None) -> None:
        """The HTTP event loop that owns the browser streams (None when it stops)."""
        self._loop = loop

    # -- worker side (any thread) --------------------------------------------------------------

    def publish(self, pose: Pose, encoded: bytes | None = None) -> None:
        """Send `pose` to Zenoh and the browser streams; `encoded` is `encode_pose(pose)` when
        the caller already has it (the session records those bytes)."""
        if self._closed:
            return
        publisher = self._publisher(pose.robot_id)
        if publisher is not None:
            try:
                publisher.put(encoded if encoded is not None else encode_pose(pose))
                self._metrics.inc(POSES_PUBLISHED)
            except Exception as err:  # ZError when the session is closing
                self._metrics.inc(POSE_PUBLISH_ERRORS)
                log.debug("pose publication failed: %s", err)
        loop = self._loop
        if loop is not None and self._stream_count > 0:
            with contextlib.suppress(RuntimeError):  # loop closed during shutdown
                loop.call_soon_threadsafe(self._deliver, pose)

    def _publisher(self, robot_id: str) -> zenoh.Publisher | None:
        publisher = self._publishers.get(robot_id)
        if publisher is not None or self._zenoh is None:
            return publisher
        with self._pub_lock:
            publisher = self._publishers.get(robot_id)
            if publisher is None and not self._closed:
                publisher = self._zenoh.declare_publisher(
                    pose_key(robot_id, self._prefix),
                    encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM,
                    congestion_control=zenoh.CongestionControl.DROP,
                )
                self._publishers[robot_id] = publisher  # keep it: dropping undeclares
            return publisher

    # -- event-loop side -------------------------------------------------------------------

    def _deliver(self, pose: Pose) -> None:
        for stream in self._streams.by_session.get(pose.session_id, ()):
            if stream.queue.full():
                stream.queue.get_nowait()
                stream.dropped += 1
                self._metrics.inc(STREAM_DROPPED)
            stream.queue.put_nowait(pose)

    def open_stream(self, session_id: str) -> PoseStream:
        """Subscribe on the event loop; pair with `close_stream` in a finally."""
        stream = PoseStream(session_id, asyncio.Queue(maxsize=self._depth))
        if self._closed:
            stream.queue.put_nowait(None)
            return stream
        self._streams.by_session[session_id].add(stream)
        self._stream_count += 1
        return stream

    def close_stream(self, stream: PoseStream) -> None:
        streams = self._streams.by_session.get(stream.session_id)
        if streams is not None and stream in streams:
            streams.discard(stream)
            self._stream_count -= 1
            if not streams:
                del self._streams.by_session[stream.session_id]

    def end_streams(self, session_id: str | None = None) -> None:
        """Tell streams (of one session, or all) to finish; runs on the event loop."""
        for sid, streams in list(self._streams.by_session.items()):
            if session_id is not None and sid != session_id:
                continue
            for stream in streams:
                if stream.queue.full():  # the end marker must fit
                    stream.queue.get_nowait()
                    stream.dropped += 1
                    self._metrics.inc(STREAM_DROPPED)
                stream.queue.put_nowait(None)

    def end_streams_threadsafe(self, session_id: str | None = None) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self.end_streams, session_id)

    def _stream_gauge(self) -> list[tuple[Labels, float]]:
        return [(labels(), float(self._stream_count))]

    def _matching_gauge(self) -> list[tuple[Labels, float]]:
        out: list[tuple[Labels, float]] = []
        for robot_id, publisher in sorted(self._publishers.items()):
            try:
                status: Any = publisher.matching_status  # MatchingStatus (stubs say bool)
                matching = bool(status.matching)
            except Exception:
                continue
            out.append((labels(robot=robot_id), 1.0 if matching else 0.0))
        return out

    def close(self) -> None:
        """Undeclare the Zenoh publishers (before the session closes)."""
        with self._pub_lock:
            self._closed = True
            publishers = list(self._publishers.values())
            self._publishers.clear()
        for publisher in publishers:
            try:
                undeclare: Any = publisher.undeclare  # untyped in zenoh's stubs
                undeclare()
            except Exception as err:
                log.debug("undeclaring a pose publisher: %s", err)
