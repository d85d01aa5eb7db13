"""Pose fan-out: every new pose goes to Zenoh (`<prefix>/<robot>/pose`) and to browser streams.

Neither path costs the estimator more than a few microseconds per pose, whatever the number of
subscribers:
- Zenoh: one `put` of the bytes the session already recorded (encoded once), on a publisher with
  `CongestionControl.DROP`; Zenoh copies it to every matching subscriber off the GIL, and a slow
  or dead one costs at most a non-blocking enqueue;
- browser streams: the worker appends the pose to one pending list and schedules one flush on
  the HTTP event loop per burst (not per pose, not per stream). The loop encodes each pose's
  SSE frame once and appends it once to its session's `FrameLog`, a bounded log shared by the
  session's streams, each reading from its own cursor (a stream that falls more than the depth
  behind loses the oldest frames, each counted exactly once per pose and stream). One timer per
  `min_interval_s` wakes the streams of the sessions that have new frames, and each writes all
  of its frames at once: per pose the loop does one append whatever the number of streams; a
  stalled browser holds only its cursor. The interval grows with the streams so that all of
  them together make at most `max_writes_per_s` writes a second (1,000 streams at the default
  1,000: one write each per second, not five): the loop's cost is bounded, not the streams'.
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


class FrameLog:
    """One session's recent SSE frames, shared by all its streams (on the event loop).

    A pose's frame is appended once, whatever the number of streams; each stream reads from
    its own cursor. The log keeps the newest `depth` frames: a stream that falls further behind
    loses the oldest, counted when it next reads (or closes). So the fan-out's work per pose is
    one append, and per stream one join per write: O(poses + streams), not O(poses x streams).
    """

    def __init__(self, depth: int) -> None:
        self.depth = depth
        self.items: deque[tuple[tuple[int, int], bytes]] = deque()  # ((seq, stamp_ns), frame)
        self.first = 0  # position of items[0] since the log began

    @property
    def end(self) -> int:
        return self.first + len(self.items)

    def append(self, key: tuple[int, int], frame: bytes) -> None:
        self.items.append((key, frame))
        if len(self.items) > self.depth:
            self.items.popleft()
            self.first += 1


@dataclass(eq=False)
class PoseStream:
    """One browser's subscription to one session's poses; lives on the event loop."""

    session_id: str
    log: FrameLog
    cursor: int = 0  # the next position of `log` this stream has not written
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    ended: bool = False
    ping: bool = False  # a keep-alive comment is due
    woken: bool = False  # a tick (or a ping) came since the last write
    dropped: int = 0  # poses this stream lost because it was not read in time
    skip: tuple[int, int] | None = None  # (seq, stamp_ns) already sent when the stream opened
    last_write: float = field(default_factory=time.monotonic)
    on_lost: Callable[[int], None] | None = None

    @property
    def has_frames(self) -> bool:
        return self.cursor < self.log.end

    def _lost(self, count: int) -> None:
        self.dropped += count
        if self.on_lost is not None:
            self.on_lost(count)

    def take(self) -> bytes:
        """Every frame since the last take, as one chunk (the oldest lost ones counted)."""
        log = self.log
        if self.cursor < log.first:
            self._lost(log.first - self.cursor)
            self.cursor = log.first
        start = self.cursor - log.first
        items = [log.items[i] for i in range(start, len(log.items))]
        self.cursor = log.end
        if items and self.skip is not None:
            if items[0][0] == self.skip:
                items = items[1:]
            self.skip = None
        return b"".join(frame for _, frame in items)

    def end(self) -> None:
        self.ended = True
        self.wake.set()

    async def next_chunk(self) -> bytes | None:
        """Every frame buffered since the last chunk, as one write, once the fan-out's tick
        wakes the stream (at most one write per tick: frames that come while a write is
        being sent wait for the next tick); a keep-alive comment when one is due; the rest
        and then None once ended."""
        while True:
            if self.has_frames and (self.woken or self.ended):
                self.woken = False
                chunk = self.take()
                if chunk:
                    self.last_write = time.monotonic()
                    return chunk
                continue
            if self.ended:
                return None
            if self.ping:
                self.ping = self.woken = False
                self.last_write = time.monotonic()
                return KEEPALIVE_FRAME
            await self.wake.wait()
            self.wake.clear()
            self.woken = True


@dataclass
class _Streams:
    by_session: dict[str, set[PoseStream]] = field(default_factory=lambda: defaultdict(set))
    logs: dict[str, FrameLog] = field(default_factory=dict)


class PoseFanout:
    def __init__(
        self,
        prefix: str,
        metrics: Metrics,
        stream_queue_depth: int,
        stream_min_interval_s: float = 0.2,
        max_writes_per_s: float = 0.0,
    ) -> None:
        self._prefix = prefix
        self._metrics = metrics
        self._depth = stream_queue_depth
        self._min_interval_s = stream_min_interval_s
        self._max_writes_per_s = max_writes_per_s
        self._encode_frame: FrameEncoder | None = None
        self._due: set[str] = set()  # sessions with new frames, their streams woken at the tick
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
        self.to_streams(pose)

    def to_streams(self, pose: Pose) -> None:
        """Send `pose` to the browser streams only (a mapper process that ingests published
        it on Zenoh itself)."""
        loop = self._loop
        if loop is not None and self._stream_count > 0 and not self._closed:
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
        """Append the pending poses' frames to their sessions' logs (on the loop): one frame
        per pose, however many streams read it."""
        with self._pending_lock:
            poses, self._pending = self._pending, []
        logs = self._streams.logs
        for pose in poses:
            log = logs.get(pose.session_id)
            if log is None:  # nobody streams this session
                continue
            log.append((pose.seq, pose.stamp_ns), self.frame(pose))  # encoded once
            self._due.add(pose.session_id)
        if self._due and not self._tick_pending:
            # One timer for all streams: each writes at most once per interval.
            self._tick_pending = True
            assert self._loop is not None
            self._loop.call_later(self.interval_s(), self._tick)

    def interval_s(self) -> float:
        """Time between two writes to a stream: the configured interval, longer when the open
        streams would together write more than `max_writes_per_s` times a second."""
        if self._max_writes_per_s <= 0.0:
            return self._min_interval_s
        return max(self._min_interval_s, self._stream_count / self._max_writes_per_s)

    def _tick(self) -> None:
        """Wake every stream of the sessions that have new frames (on the loop)."""
        self._tick_pending = False
        due, self._due = self._due, set()
        for session_id in due:
            for stream in self._streams.by_session.get(session_id, ()):
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
        log = self._streams.logs.get(session_id)
        if log is None:
            log = FrameLog(self._depth)
            if not self._closed:
                self._streams.logs[session_id] = log
        stream = PoseStream(session_id, log, cursor=log.end, on_lost=self._count_lost)
        if self._closed:
            stream.end()
            return stream
        self._streams.by_session[session_id].add(stream)
        self._stream_count += 1
        return stream

    def _count_lost(self, count: int) -> None:
        self._metrics.inc(STREAM_DROPPED, count)

    def close_stream(self, stream: PoseStream) -> None:
        if stream.cursor < stream.log.first:  # lost and never read: still counted
            stream._lost(stream.log.first - stream.cursor)
            stream.cursor = stream.log.first
        streams = self._streams.by_session.get(stream.session_id)
        if streams is not None and stream in streams:
            streams.discard(stream)
            self._stream_count -= 1
            if not streams:
                del self._streams.by_session[stream.session_id]
                self._streams.logs.pop(stream.session_id, None)
                self._due.discard(stream.session_id)

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
