"""A small thread-safe metrics registry rendered in the Prometheus text format (0.0.4).

Hand-written on purpose: a handful of counters, gauges and one histogram do not justify a
dependency, and the text format is stable and simple.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal

Labels = tuple[tuple[str, str], ...]
MetricKind = Literal["counter", "gauge", "histogram"]

# Per-scan processing time: from well under a millisecond (rejects) to a slow match.
SCAN_SECONDS_BUCKETS: tuple[float, ...] = (
    0.0005,
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
)


@dataclass
class _Histogram:
    buckets: tuple[float, ...]
    counts: list[int]
    total: float = 0.0
    count: int = 0


@dataclass
class _Family:
    name: str
    kind: MetricKind
    help: str
    buckets: tuple[float, ...] = ()
    values: dict[Labels, float] = field(default_factory=dict)
    histograms: dict[Labels, _Histogram] = field(default_factory=dict)
    # Gauges whose value is read at scrape time (queue depth, subscribers...).
    collector: Callable[[], Iterable[tuple[Labels, float]]] | None = None


def labels(**kv: str) -> Labels:
    return tuple(sorted(kv.items()))


class Metrics:
    """Counters and histograms updated from any thread; `render()` for `GET /metrics`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._families: dict[str, _Family] = {}

    def counter(self, name: str, help_text: str) -> None:
        self._declare(_Family(name, "counter", help_text))

    def gauge(
        self,
        name: str,
        help_text: str,
        collector: Callable[[], Iterable[tuple[Labels, float]]] | None = None,
    ) -> None:
        self._declare(_Family(name, "gauge", help_text, collector=collector))

    def histogram(self, name: str, help_text: str, buckets: Sequence[float]) -> None:
        self._declare(_Family(name, "histogram", help_text, buckets=tuple(sorted(buckets))))

    def _declare(self, family: _Family) -> None:
        with self._lock:
            if family.name in self._families:
                raise ValueError(f"metric {family.name} declared twice")
            self._families[family.name] = family

    def inc(self, name: str, amount: float = 1.0, **label_values: str) -> None:
        key = labels(**label_values)
        with self._lock:
            fam = self._families[name]
            fam.values[key] = fam.values.get(key, 0.0) + amount

    def set(self, name: str, value: float, **label_values: str) -> None:
        key = labels(**label_values)
        with self._lock:
            self._families[name].values[key] = value

    def observe(self, name: str, value: float, **label_values: str) -> None:
        key = labels(**label_values)
        with self._lock:
            fam = self._families[name]
            hist = fam.histograms.get(key)
            if hist is None:
                hist = _Histogram(fam.buckets, [0] * len(fam.buckets))
                fam.histograms[key] = hist
            index = bisect.bisect_left(fam.buckets, value)
            if index < len(hist.counts):
                hist.counts[index] += 1
            hist.total += value
            hist.count += 1

    def value(self, name: str, **label_values: str) -> float:
        """Current value of one counter/gauge series (0 when never touched)."""
        with self._lock:
            return self._families[name].values.get(labels(**label_values), 0.0)

    def total(self, name: str) -> float:
        """Sum over every label set of a counter."""
        with self._lock:
            return sum(self._families[name].values.values())

    def by_label(self, name: str, label: str) -> dict[str, float]:
        """A counter summed per value of one label (`reason` -> count): a summary whose size
        is the label's values, not the series'."""
        out: dict[str, float] = {}
        with self._lock:
            for key, value in self._families[name].values.items():
                for k, v in key:
                    if k == label:
                        out[v] = out.get(v, 0.0) + value
        return out

    def forget(self, names: Iterable[str], **label_values: str) -> int:
        """Remove every series of `names` whose labels include `label_values` (a robot that
        was forgotten must not keep its series forever); returns how many went."""
        wanted = set(label_values.items())
        removed = 0
        with self._lock:
            for name in names:
                fam = self._families[name]
                for key in [k for k in fam.values if wanted <= set(k)]:
                    del fam.values[key]
                    removed += 1
        return removed

    def render(self) -> str:
        with self._lock:
            families = [
                (f.name, f.kind, f.help, f.collector, dict(f.values), _copy_hists(f))
                for f in self._families.values()
            ]
        lines: list[str] = []
        for name, kind, help_text, collector, values, hists in families:
            lines.append(f"# HELP {name} {_escape_help(help_text)}")
            lines.append(f"# TYPE {name} {kind}")
            if collector is not None:
                values.update(collector())
            for key, value in sorted(values.items()):
                lines.append(f"{name}{_fmt_labels(key)} {_fmt_value(value)}")
            for key, hist in sorted(hists.items()):
                cumulative = 0
                for bound, count in zip(hist.buckets, hist.counts, strict=True):
                    cumulative += count
                    le = (*key, ("le", _fmt_value(bound)))
                    lines.append(f"{name}_bucket{_fmt_labels(le)} {cumulative}")
                inf = (*key, ("le", "+Inf"))
                lines.append(f"{name}_bucket{_fmt_labels(inf)} {hist.count}")
                lines.append(f"{name}_sum{_fmt_labels(key)} {_fmt_value(hist.total)}")
                lines.append(f"{name}_count{_fmt_labels(key)} {hist.count}")
        return "\n".join(lines) + "\n"


def _copy_hists(fam: _Family) -> dict[Labels, _Histogram]:
    return {
        k: _Histogram(h.buckets, list(h.counts), h.total, h.count)
        for k, h in fam.histograms.items()
    }


def _escape_help(text: str) -> str:
    return text.replace("\\", "\\\\").replace("\n", "\\n")


def _escape_label(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _fmt_labels(key: Labels) -> str:
    if not key:
        return ""
    inner = ",".join(f'{k}="{_escape_label(v)}"' for k, v in key)
    return "{" + inner + "}"


def _fmt_value(value: float) -> str:
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    if value == int(value) and abs(value) < 1e15:
        return str(int(value))
    return repr(float(value))


def parse_text(text: str) -> dict[str, float]:
    """Parse our own exposition back into `{'name{labels}': value}` (used by tests and tools)."""
    out: dict[str, float] = {}
    for line in text.splitlines():
        if not line or line.startswith("#"):
            continue
        series, _, value = line.rpartition(" ")
        out[series] = float(value)
    return out
