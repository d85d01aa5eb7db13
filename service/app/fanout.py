"""Pose fan-out: every new pose goes to Zenoh (`<prefix>/<robot>/pose`) and to browser streams.

Neither path costs the estimator more than a few microseconds per pose, whatever the number of
subscribers:
- Zenoh: one `put` of the bytes the session already recorded (encoded once), on a publisher with
  `CongestionControl.DROP`; Zenoh copies it to every matching subscriber off the GIL, and a slow
  or dead one costs at most a non-blocking enqueue;
- browser streams: the worker appends the pose to one pending list and schedules one flush on
  the HTTP event loop per burst (not per pose, not per stream). The loop encodes each pose's
  SSE frame once and appends the same bytes to each stream's bounded buffer (full: the oldest
  frame is dropped and counted, exactly once per pose lost). One timer per `min_interval_s`
  wakes the streams that have frames, and each writes all of them at once: 1,000 streams cost
  the loop at most 1,000 writes per interval, not one per pose per stream, and a stalled
  browser only fills its own buffer.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable
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

FrameEncoder = Callable[[Pose], bytes]  # one pose as one SSE frame (`event: pose` ...)
KEEPALIVE_S = 15.0
KEEPALIVE_FRAME = b": ping\n\n"


@dataclass(eq=False)
class PoseStream:
    """One browser's subscription to one session's poses; lives on the event loop."""

    session_id: str
    depth: int  # frames buffered at most (oldest dropped first)
    frames: deque[bytes] = field(default_factory=deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    ended: bool = False
    ping: bool = False  # a keep-alive comment is due
    dropped: int = 0  # poses this stream lost because it was not read in time
    skip: tuple[int, int] | None = None  # (seq, stamp_ns) already sent when the stream opened
    last_write: float = field(default_factory=time.monotonic)

    def offer(self, pose: Pose, frame: bytes) -> bool:
        """Buffer `frame` (of `pose`); False when the oldest frame had to go to make room.
        The stream is woken by the fan-out's tick, not here."""
        if self.skip is not None:
            if (pose.seq, pose.stamp_ns) == self.skip:
                return True
            self.skip = None
        lost = len(self.frames) >= self.depth
        if lost:
            self.frames.popleft()
            self.dropped += 1
        self.frames.append(frame)
        return not lost

    def end(self) -> None:
        self.ended = True
        self.wake.set()

    async def next_chunk(self) -> bytes | None:
        """Every frame buffered since the last chunk, as one write; a keep-alive comment when
        one is due; None once ended and emptied."""
        while True:
            if self.frames:
                chunk = b"".join(self.frames)
                self.frames.clear()
                self.last_write = time.monotonic()
                return chunk
            if self.ended:
                return None
            if self.ping:
                self.ping = False
                self.last_write = time.monotonic()
                return KEEPALIVE_FRAME
            await self.wake.wait()
            self.wake.clear()


@dataclass
class _Streams:
    by_session: dict[str, set[PoseStream]] = field(default_factory=lambda: defaultdict(set))


class PoseFanout:
    def __init__(
        self,
        prefix: str,
        metrics: Metrics,
        stream_queue_depth: int,
        stream_min_interval_s: float = 0.2,
    ) -> None:
        self._prefix = prefix
        self._metrics = metrics
        self._depth = stream_queue_depth
        self._min_interval_s = stream_min_interval_s
        self._encode_frame: FrameEncoder | None = None
        self._due: set[PoseStream] = set()  # streams with frames, woken at the next tick
        self._tick_pending = False
        self._keepalive: asyncio.TimerHandle | None = None
        self._pending: list[Pose] = []  # poses for the streams, not yet on the loop
        self._pending_lock = threading.Lock()
        self._zenoh: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._pub_lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._streams = _Streams()
        self._stream_count = 0  # read by workers without the loop; written on the loop
        self._closed = False
        metrics.counter(POSES_PUBLISHED, "Poses published on Zenoh.")
        metrics.counter(POSE_PUBLISH_ERRORS, "Zenoh pose publications that failed.")
        metrics.counter(
            STREAM_DROPPED,
            "Poses a browser stream lost because it did not read them in time (oldest first; "
            "counted once per pose and stream).",
        )
        metrics.gauge(STREAM_SUBSCRIBERS, "Open browser pose streams.", self._stream_gauge)
        metrics.gauge(
            ZENOH_POSE_SUBSCRIBERS,
            "1 when at least one Zenoh subscriber matches the robot's pose key.",
            self._matching_gauge,
        )

    # -- wiring ----------------------------------------------------------------------------

    def attach_zenoh(self, session: zenoh.Session | None) -> None:
        self._zenoh = session

    def bind_loop(
        self, loop: asyncio.AbstractEventLoop | None, encode_frame: FrameEncoder | None = None
    ) -> None:
        """The HTTP event loop that owns the browser streams (None when it stops), and how a
        pose becomes an SSE frame there."""
        self._loop = loop
        if encode_frame is not None:
            self._encode_frame = encode_frame
        if loop is not None:
            loop.call_soon_threadsafe(self._schedule_keepalive)
        elif self._keepalive is not None:
            self._keepalive.cancel()
            self._keepalive = None

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
            with self._pending_lock:
                first = not self._pending
                self._pending.append(pose)
            if first:  # one wake-up of the loop per burst of poses
                with contextlib.suppress(RuntimeError):  # loop closed during shutdown
                    loop.call_soon_threadsafe(self._flush)

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

    def _flush(self) -> None:
        """Hand the pending poses to their sessions' streams (on the loop)."""
        with self._pending_lock:
            poses, self._pending = self._pending, []
        lost = 0
        for pose in poses:
            streams = self._streams.by_session.get(pose.session_id)
            if not streams:
                continue
            frame = self.frame(pose)  # encoded once for every stream of the session
            for stream in streams:
                if not stream.offer(pose, frame):
                    lost += 1
            self._due.update(streams)
        if lost:
            self._metrics.inc(STREAM_DROPPED, lost)
        if self._due and not self._tick_pending:
            # One timer for all streams: each writes at most once per interval.
            self._tick_pending = True
            assert self._loop is not None
            self._loop.call_later(self._min_interval_s, self._tick)

    def _tick(self) -> None:
        """Wake every stream that has frames (on the loop)."""
        self._tick_pending = False
        due, self._due = self._due, set()
        for stream in due:
            stream.wake.set()

    def _schedule_keepalive(self) -> None:
        loop = self._loop
        if loop is None or self._closed:
            return
        now = time.monotonic()
        for streams in self._streams.by_session.values():
            for stream in streams:
                if now - stream.last_write >= KEEPALIVE_S:
                    stream.ping = True
                    stream.wake.set()
        self._keepalive = loop.call_later(KEEPALIVE_S / 3, self._schedule_keepalive)

    def frame(self, pose: Pose) -> bytes:
        """`pose` as an SSE frame."""
        if self._encode_frame is None:
            raise RuntimeError("no SSE frame encoder bound")
        return self._encode_frame(pose)

    def open_stream(self, session_id: str) -> PoseStream:
        """Subscribe on the event loop; pair with `close_stream` in a finally."""
        stream = PoseStream(session_id, self._depth)
        if self._closed:
            stream.end()
            return stream
        self._streams.by_session[session_id].add(stream)
        self._stream_count += 1
        return stream

    def close_stream(self, stream: PoseStream) -> None:
        streams = self._streams.by_session.get(stream.session_id)
        self._due.discard(stream)
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
                stream.end()  # what is buffered is still written

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
