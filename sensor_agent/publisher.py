"""One Zenoh publisher for every scan source: `<prefix>/<robot_id>/scan` plus liveliness tokens.

Two tokens: the robot's `<prefix>/<robot_id>/alive` (presence) and this publisher's own
`<prefix>/<robot_id>/alive/<zenoh id>`, and every scan carries the publisher's source id
(`source_info`): Zenoh merges tokens on one key, so without them the service could not tell
two agents that use the same robot id apart (it refuses the second one's scans).

Sources hand scans to `ScanPublisher.submit()`, which numbers them consecutively, stamps the
robot id and queues them; a worker thread encodes (`clients.wire.encode_scan`) and puts them.

Congestion control is BLOCK: on a healthy link no scan is ever dropped by Zenoh (DROP would
silently discard samples whenever the transmission queue is momentarily full, e.g. during a
burst after a Wi-Fi hiccup). Blocking is confined to the worker thread; the source (the serial
port) never waits for the network. If the network stays stalled long enough for the bounded
queue (2 s of scans by default) to fill, new scans are dropped *there*, counted and logged;
they have already consumed a sequence number, so subscribers see the gap.

Zenoh tells the publisher whether any subscriber matches its key (a matching listener): a put
nobody matches goes nowhere, so that state is logged when it changes (`has_subscriber`).
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Final

import zenoh

from clients.keyexpr import DEFAULT_PREFIX, alive_key, publisher_alive_key, scan_key
from clients.wire import Scan, WireError, encode_scan

log = logging.getLogger(__name__)

DEFAULT_QUEUE_SCANS: Final = 80  # 2 s at 40 Hz
_DROP_LOG_INTERVAL_S: Final = 5.0
_SN_MASK: Final = 0xFFFFFFFF  # Zenoh's source sequence number is a u32


@dataclass(slots=True)
class PublisherCounters:
    submitted: int = 0  # scans numbered (= next sequence number)
    published: int = 0
    dropped: int = 0  # queue full (network stalled) or the put failed
    encode_errors: int = 0  # scans that violate the wire contract (never sent)

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


class _Stop:
    """Queue sentinel."""


_STOP: Final = _Stop()


class ScanPublisher:
    """Publishes scans of one robot. Use as a context manager or call `close()`."""

    def __init__(
        self,
        session: zenoh.Session,
        robot_id: str,
        prefix: str = DEFAULT_PREFIX,
        *,
        queue_scans: int = DEFAULT_QUEUE_SCANS,
        congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK,
    ) -> None:
        self.robot_id = robot_id
        self.key = scan_key(robot_id, prefix)
        self.counters = PublisherCounters()
        self._publisher = session.declare_publisher(
            self.key,
            encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM,
            congestion_control=congestion_control,
            priority=zenoh.Priority.DATA,
        )
        # Kept on self: a liveliness token is undeclared as soon as it is garbage-collected.
        self._token = session.liveliness().declare_token(alive_key(robot_id, prefix))
        self._publisher_token = session.liveliness().declare_token(
            publisher_alive_key(robot_id, str(session.zid()), prefix)
        )
        # Unstable API in zenoh-python 1.x: without it, scans go out without a source id.
        self._source_id: zenoh.EntityGlobalId | None = getattr(self._publisher, "id", None)
        # Whether a subscriber matches (the service, a recorder): the listener reports each
        # change; the state at start is read once, unless a change came first.
        self._match_lock = threading.Lock()
        self._matching: bool | None = None
        self._told_unmatched = False
        self._matching_listener = self._publisher.declare_matching_listener(self._on_matching)
        # The stubs say bool; zenoh 1.10 returns a MatchingStatus: take either.
        status: Any = self._publisher.matching_status
        initial = bool(getattr(status, "matching", status))
        with self._match_lock:
            if self._matching is None:
                self._matching = initial
        self._queue: queue.Queue[Scan | _Stop] = queue.Queue(maxsize=queue_scans)
        self._seq = 0
        self._last_drop_log = 0.0
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="scan-publisher", daemon=True)
        self._thread.start()
        log.info("publishing scans on %s", self.key)

    def __enter__(self) -> ScanPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def queue_depth(self) -> int:
        return self._queue.qsize()

    @property
    def has_subscriber(self) -> bool:
        """Whether a subscriber on the network matches this publisher's key."""
        with self._match_lock:
            return bool(self._matching)

    def tell_unmatched(self) -> None:
        """Log once (until a subscriber appears) that no subscriber matches."""
        with self._match_lock:
            if self._matching or self._told_unmatched:
                return
            self._told_unmatched = True
        log.warning(
            "no subscriber matches %s: scans go to nobody (%d published so far); "
            "is the service running and connected?",
            self.key,
            self.counters.published,
        )

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        """Zenoh's callback thread: log the change (no Zenoh call in here)."""
        matching = bool(status.matching)
        with self._match_lock:
            changed = matching != self._matching
            self._matching = matching
            if matching:
                self._told_unmatched = False
            elif changed:
                self._told_unmatched = True  # told here: the summary does not repeat it
        if not changed:
            return
        if matching:
            log.info("a subscriber matches %s: scans are received", self.key)
        else:
            log.warning("no subscriber matches %s any more: scans go to nobody", self.key)

    def submit(self, scan: Scan) -> bool:
        """Number and queue `scan` (never blocks). False if it had to be dropped."""
        scan = dataclasses.replace(scan, robot_id=self.robot_id, seq=self._seq)
        self._seq += 1
        self.counters.submitted += 1
        try:
            self._queue.put_nowait(scan)
        except queue.Full:
            self.counters.dropped += 1
            now = time.monotonic()
            if now - self._last_drop_log >= _DROP_LOG_INTERVAL_S:
                self._last_drop_log = now
                log.warning(
                    "network stalled: publish queue full, dropping scans (%d dropped so far)",
                    self.counters.dropped,
                )
            return False
        return True

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if isinstance(item, _Stop):
                return
            try:
                payload = encode_scan(item)
            except WireError as err:
                self.counters.encode_errors += 1
                log.error("scan %d violates the wire contract: %s", item.seq, err)
                continue
            try:
                self._publisher.put(payload, source_info=self._source_info(item.seq))
            except zenoh.ZError as err:
                self.counters.dropped += 1
                log.warning("put of scan %d failed: %s", item.seq, err)
                continue
            self.counters.published += 1

    def _source_info(self, seq: int) -> zenoh.SourceInfo | None:
        """This publisher's id and the scan's number, so that a second agent is told apart."""
        if self._source_id is None:
            return None
        try:
            return zenoh.SourceInfo(self._source_id, seq & _SN_MASK)
        except (TypeError, ValueError) as err:
            log.warning("scans go out without a source id: %s", err)
            self._source_id = None
            return None

    def close(self, timeout_s: float = 2.0) -> None:
        """Send what is queued (up to `timeout_s`), then undeclare the publisher and token."""
        if self._closed:
            return
        self._closed = True
        deadline = time.monotonic() + timeout_s
        try:
            self._queue.put(_STOP, timeout=timeout_s)
        except queue.Full:
            log.warning("publish queue still full at shutdown; %d scans lost", self.queue_depth)
        self._thread.join(max(0.0, deadline - time.monotonic()))
        if self._thread.is_alive():
            log.warning("publisher thread did not finish within %.1f s", timeout_s)
        try:
            self._token.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stubs
            self._matching_listener.undeclare()  # type: ignore[no-untyped-call]
            self._publisher_token.undeclare()  # type: ignore[no-untyped-call]
            self._publisher.undeclare()  # type: ignore[no-untyped-call]
        except zenoh.ZError as err:  # session already closed
            log.debug("undeclare failed: %s", err)


__all__ = ["DEFAULT_QUEUE_SCANS", "PublisherCounters", "ScanPublisher"]
