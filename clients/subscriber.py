"""`PoseSubscriber`: receive the poses the mapping service publishes over Zenoh.

Two forms:

    with PoseSubscriber(connect=["tcp/10.0.0.5:7447"], on_pose=print):   # callback
        ...

    with PoseSubscriber(connect=["tcp/10.0.0.5:7447"], robot_id="amr-07") as sub:  # iterator
        for pose in sub:
            ...

In the default peer mode, opening succeeds even while the service is down and Zenoh keeps
reconnecting in the background, so a subscriber outlives service restarts. Malformed payloads
are counted (`malformed_count`) and logged once, never raised into the caller.
"""

from __future__ import annotations

import logging
import queue
import threading
import weakref
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Final, Self

import zenoh

from clients.keyexpr import DEFAULT_PREFIX, pose_key, pose_wildcard
from clients.wire import DecodeError, Pose, decode_pose
from clients.zenoh_config import ZenohMode, build_zenoh_config

log = logging.getLogger(__name__)

DEFAULT_QUEUE_SIZE: Final = 4096
_CLOSED: Final = object()  # queue sentinel that wakes a blocked `recv`

# Subscribers still open at interpreter exit. Zenoh's callback thread is not a daemon thread, so
# an open session would make `threading._shutdown()` wait forever (PROTOCOLS B.9.1); `atexit`
# runs too late, `threading._register_atexit` runs before that join.
_live: weakref.WeakSet[PoseSubscriber] = weakref.WeakSet()
_live_lock = threading.Lock()
_exit_hook_installed = False


def _close_live_subscribers() -> None:
    with _live_lock:
        subs = list(_live)
    for sub in subs:
        sub.close()


def _install_exit_hook() -> None:
    global _exit_hook_installed  # noqa: PLW0603 - one process-wide hook
    with _live_lock:
        if _exit_hook_installed:
            return
        _exit_hook_installed = True
    register = getattr(threading, "_register_atexit", None)
    if register is not None:
        register(_close_live_subscribers)


class SubscriberClosedError(RuntimeError):
    """`recv` on a subscriber that has been closed."""


class PoseSubscriber:
    """Poses of one robot (`robot_id="amr-07"`) or of many (`"*"`, or a pattern like `"amr-*"`).

    `connect`: Zenoh endpoints of the service (or of a router), e.g. `tcp/10.0.0.5:7447`.
    `on_pose`: if given, called with every `Pose` on Zenoh's delivery thread (keep it quick);
    otherwise poses are queued for `recv()` / iteration (the oldest are dropped when
    `queue_size` is exceeded, and counted in `dropped_count`).
    `zenoh_config`: a Zenoh JSON5 config file or a ready `zenoh.Config` (then `connect`,
    `listen` and `mode` are not applied).
    """

    def __init__(
        self,
        connect: Sequence[str] = (),
        robot_id: str = "*",
        prefix: str = DEFAULT_PREFIX,
        *,
        on_pose: Callable[[Pose], Any] | None = None,
        mode: ZenohMode = "peer",
        listen: Sequence[str] = (),
        zenoh_config: str | Path | zenoh.Config | None = None,
        queue_size: int = DEFAULT_QUEUE_SIZE,
    ) -> None:
        if robot_id == "*" or "*" in robot_id:
            self.key_expr = pose_wildcard(prefix, robot_id)
        else:
            self.key_expr = pose_key(robot_id, prefix)
        if isinstance(zenoh_config, zenoh.Config):
            config = zenoh_config
        else:
            config = build_zenoh_config(
                mode=mode, listen=listen, connect=connect, config_file=zenoh_config
            )
        self._on_pose = on_pose
        self._queue: queue.Queue[object] = queue.Queue(maxsize=max(1, queue_size))
        self._lock = threading.Lock()
        self._closed = False
        self._received = 0
        self._malformed = 0
        self._dropped = 0
        self._callback_errors = 0
        self._logged_malformed = False
        self._logged_callback_error = False

        _install_exit_hook()
        self._session = zenoh.open(config)
        try:
            self._subscriber = self._session.declare_subscriber(self.key_expr, self._on_sample)
        except BaseException:
            self._session.close()  # type: ignore[no-untyped-call]
            raise
        with _live_lock:
            _live.add(self)
        log.debug("subscribed to %s", self.key_expr)

    # -- counters ---------------------------------------------------------------------------

    @property
    def received_count(self) -> int:
        """Valid poses received."""
        return self._received

    @property
    def malformed_count(self) -> int:
        """Payloads on the pose key that were not valid poses (ignored)."""
        return self._malformed

    @property
    def dropped_count(self) -> int:
        """Poses discarded because nobody consumed the queue fast enough."""
        return self._dropped

    @property
    def closed(self) -> bool:
        return self._closed

    # -- receiving --------------------------------------------------------------------------

    def recv(self, timeout: float | None = None) -> Pose:
        """The next pose; raises `TimeoutError` after `timeout` seconds, or
        `SubscriberClosedError` once the subscriber is closed (and its queue drained)."""
        if self._on_pose is not None:
            raise RuntimeError("recv() is not available when on_pose is set")
        if self._closed and self._queue.empty():
            raise SubscriberClosedError("pose subscriber is closed")
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"no pose within {timeout} s on {self.key_expr}") from None
        if item is _CLOSED:
            self._queue.put_nowait(_CLOSED)  # wake any other waiter too
            raise SubscriberClosedError("pose subscriber is closed")
        assert isinstance(item, Pose)
        return item

    def try_recv(self) -> Pose | None:
        """The next queued pose, or None if there is none right now."""
        try:
            return self.recv(timeout=0)
        except TimeoutError:
            return None

    def __iter__(self) -> Iterator[Pose]:
        """Poses as they arrive, until `close()` is called."""
        while True:
            try:
                yield self.recv()
            except SubscriberClosedError:
                return

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Runs on Zenoh's delivery thread: never raise, never block.
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            pose = decode_pose(sample.payload.to_bytes())
        except DecodeError as err:
            self._count_malformed(str(sample.key_expr), err)
            return
        self._received += 1
        if self._on_pose is not None:
            try:
                self._on_pose(pose)
            except Exception:
                self._callback_errors += 1
                if not self._logged_callback_error:
                    self._logged_callback_error = True
                    log.exception("on_pose callback raised (logged once; poses keep flowing)")
            return
        self._enqueue(pose)

    def _enqueue(self, pose: Pose) -> None:
        while True:
            try:
                self._queue.put_nowait(pose)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                    self._dropped += 1
                except queue.Empty:
                    pass

    def _count_malformed(self, key: str, err: DecodeError) -> None:
        self._malformed += 1
        if not self._logged_malformed:
            self._logged_malformed = True
            log.warning(
                "ignoring malformed pose on %s (%s); further ones are only counted", key, err
            )

    # -- lifecycle --------------------------------------------------------------------------

    def close(self) -> None:
        """Undeclare the subscription and close the Zenoh session. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        with _live_lock:
            _live.discard(self)
        try:
            self._subscriber.undeclare()  # type: ignore[no-untyped-call]
        except zenoh.ZError:  # session already gone
            pass
        finally:
            self._session.close()  # type: ignore[no-untyped-call]
        try:
            self._queue.put_nowait(_CLOSED)
        except queue.Full:
            # Make room for the sentinel: a closed subscriber's backlog is still readable
            # up to this point, but waking blocked readers matters more.
            self._queue.get_nowait()
            self._queue.put_nowait(_CLOSED)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


__all__ = ["PoseSubscriber", "SubscriberClosedError"]
