"""The agent loop: one source feeding one publisher, with a periodic one-line summary (while
a subscriber matches; otherwise one line says that none does)."""

from __future__ import annotations

import logging
import threading
import time
from typing import Final

from sensor_agent.publisher import ScanPublisher
from sensor_agent.sources import ScanSource

log = logging.getLogger(__name__)

DEFAULT_STATS_INTERVAL_S: Final = 10.0


class Agent:
    """Moves scans from `source` to `publisher` until `stop` is set or the source ends."""

    def __init__(
        self,
        source: ScanSource,
        publisher: ScanPublisher,
        *,
        stats_interval_s: float = DEFAULT_STATS_INTERVAL_S,
    ) -> None:
        self.source = source
        self.publisher = publisher
        self.stats_interval_s = stats_interval_s
        self._last_published = 0
        self._last_t = time.monotonic()

    def run(self, stop: threading.Event) -> None:
        log.info("source: %s", self.source.name)
        done = threading.Event()
        reporter = threading.Thread(
            target=self._report_loop, args=(done,), name="agent-stats", daemon=True
        )
        reporter.start()
        try:
            for scan in self.source.scans(stop):
                self.publisher.submit(scan)
        finally:
            done.set()
            reporter.join(timeout=1.0)
            log.info("final: %s", self.summary())

    def _report_loop(self, done: threading.Event) -> None:
        if self.stats_interval_s <= 0:
            return
        while not done.wait(self.stats_interval_s):
            line = self.summary()  # also restarts the rate's window
            if not self.publisher.has_subscriber:
                # `published=` counting up while nobody listens reads as success: say so, once.
                self.publisher.tell_unmatched()
                continue
            log.info("%s", line)

    def summary(self) -> str:
        """One line: rate, published, dropped, queue depth, then the source's counters."""
        c = self.publisher.counters
        now = time.monotonic()
        rate_hz = (c.published - self._last_published) / max(1e-9, now - self._last_t)
        self._last_published, self._last_t = c.published, now
        source = " ".join(f"{k}={v}" for k, v in self.source.stats().items())
        return (
            f"{rate_hz:.1f} Hz published={c.published} dropped={c.dropped} "
            f"queue={self.publisher.queue_depth} | {source}"
        )


__all__ = ["DEFAULT_STATS_INTERVAL_S", "Agent"]
