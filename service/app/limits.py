"""Process limits: file descriptors, and a log filter against storms of identical lines.

Descriptors: the service raises its soft RLIMIT_NOFILE to the hard limit at start, and sizes the
default robot limit to what fits: a robot that is sending holds one descriptor (its recording;
idle recordings are closed) plus a transient one while it is fsynced or checkpointed, and the
rest of the process (Zenoh sockets, HTTP connections, mapper pipes, the lock file) needs a
reserve.

Time: stamps a recording or an export can hold are ROS time, seconds in an int32 (ROS 2's
`builtin_interfaces/Time`, and the year-2038 limit) and never before the epoch (MCAP's log
times are unsigned). `in_ros_time` is the one test of that range, for ingest and export.

Log storms: at the descriptor limit, asyncio logs a traceback for every connection waiting in
the listen backlog, every second (1.48 M lines in 100 s before this filter). `RepeatFilter`
passes the first few identical records per window and then one summary line per window.
"""

from __future__ import annotations

import logging
import resource
import threading
import time
from typing import Final

log = logging.getLogger(__name__)

DESCRIPTOR_RESERVE: Final = 128  # sockets, HTTP connections, pipes, files being written
DESCRIPTORS_PER_ROBOT: Final = 2
MAX_ROBOTS_CAP: Final = 1024

ROS_TIME_MIN_NS: Final = 0
ROS_TIME_MAX_NS: Final = (2**31 - 1) * 1_000_000_000 + 999_999_999  # 2038-01-19T03:14:07.999999999Z


def in_ros_time(stamp_ns: int) -> bool:
    """True when a stamp fits ROS time (and an MCAP log time): 1970 to 2038."""
    return ROS_TIME_MIN_NS <= stamp_ns <= ROS_TIME_MAX_NS


def nofile_limits() -> tuple[int, int]:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    return int(soft), int(hard)


def raise_nofile_limit() -> tuple[int, int]:
    """Raise the soft descriptor limit to the hard one; returns (before, after)."""
    soft, hard = nofile_limits()
    if resource.RLIM_INFINITY in (hard, soft):
        return soft, soft
    if soft < hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        except (ValueError, OSError) as err:
            log.warning("could not raise the descriptor limit from %d to %d: %s", soft, hard, err)
            return soft, soft
        return soft, hard
    return soft, soft


def default_max_robots(nofile: int | None = None) -> int:
    """Robots that fit under the descriptor limit, at most `MAX_ROBOTS_CAP`."""
    if nofile is None:
        nofile = nofile_limits()[0]
    if nofile == resource.RLIM_INFINITY or nofile < 0:
        return MAX_ROBOTS_CAP
    return max(8, min(MAX_ROBOTS_CAP, (nofile - DESCRIPTOR_RESERVE) // DESCRIPTORS_PER_ROBOT))


class RepeatFilter(logging.Filter):
    """Let through `burst` identical records (same logger, level, message template) per
    `window_s`; then count them, and say how many were suppressed when the window ends."""

    def __init__(self, burst: int = 5, window_s: float = 10.0, max_keys: int = 4096) -> None:
        super().__init__()
        self.burst = burst
        self.window_s = window_s
        self.max_keys = max_keys
        self._lock = threading.Lock()
        self._seen: dict[tuple[str, int, str], tuple[float, int]] = {}  # key -> (start, count)

    def filter(self, record: logging.LogRecord) -> bool:
        # The first line of the template: asyncio's messages differ only in later lines
        # (the handle's timer, the socket), our own only in their arguments.
        key = (record.name, record.levelno, str(record.msg).split("\n", 1)[0])
        now = time.monotonic()
        with self._lock:
            start, count = self._seen.get(key, (now, 0))
            if now - start >= self.window_s:
                suppressed = count - self.burst
                if suppressed > 0:
                    record.msg = (
                        f"{record.msg} [{suppressed} identical lines suppressed in the last "
                        f"{self.window_s:.0f} s]"
                    )
                self._seen[key] = (now, 1)
                return True
            if len(self._seen) >= self.max_keys and key not in self._seen:
                self._seen.clear()  # bounded memory: a flood of distinct lines resets counting
            self._seen[key] = (start, count + 1)
            if count + 1 == self.burst + 1:
                record.msg = (
                    f"{record.msg} [repeated: further identical lines suppressed for "
                    f"{self.window_s:.0f} s]"
                )
                record.exc_info = None
                record.exc_text = None
                return True
            return count + 1 <= self.burst
