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


# Another process's series: name -> (values, histograms as (counts, total, count)).
Snapshot = dict[str, tuple[dict[Labels, float], dict[Labels, tuple[list[int], float, int]]]]


class Metrics:
    """Counters and histograms updated from any thread; `render()` for `GET /metrics`.

    Series of other processes (mapper processes that ingest scans themselves) are added to
    ours by name: each sends its `export()` now and then and `set_external` keeps the latest;
    a process that restarted starts from zero, so its previous counts are kept as a base."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._families: dict[str, _Family] = {}
        self._external: dict[str, tuple[int, Snapshot]] = {}  # source -> (generation, snap)
        self._retired: Snapshot = {}  # counters and histograms of sources that restarted

    def export(self) -> Snapshot:
        """Counters, histograms and collected gauges, for another process's `set_external`."""
        with self._lock:
            families = list(self._families.values())
            out: Snapshot = {}
            for f in families:
                if f.kind == "gauge" and f.collector is None:
                    continue  # set by hand (limits): each process would add its own
                hists = {k: (list(h.counts), h.total, h.count) for k, h in f.histograms.items()}
                out[f.name] = (dict(f.values) if f.kind != "gauge" else {}, hists)
        for f in families:
            if f.collector is not None:
                out[f.name] = (dict(f.collector()), {})
        return out

    def set_external(self, source: str, generation: int, snap: Snapshot) -> None:
        """The latest series of `source`; a new `generation` keeps the old counts as a base."""
        with self._lock:
            old = self._external.get(source)
            if old is not None and old[0] != generation:
                for name, (values, hists) in old[1].items():
                    fam = self._families.get(name)
                    if fam is None or fam.kind == "gauge":
                        continue
                    base_values, base_hists = self._retired.setdefault(name, ({}, {}))
                    for k, v in values.items():
                        base_values[k] = base_values.get(k, 0.0) + v
                    for k, (counts, total, count) in hists.items():
                        b = base_hists.get(k)
                        base_hists[k] = (
                            (counts, total, count)
                            if b is None
                            else ([x + y for x, y in zip(b[0], counts, strict=True)],
                                  b[1] + total, b[2] + count)
                        )  # fmt: skip
            self._external[source] = (generation, snap)

    def _merged(self, fam: _Family) -> tuple[dict[Labels, float], dict[Labels, _Histogram]]:
        """Our series of `fam` plus every other process's (lock held)."""
        values = dict(fam.values)
        hists = _copy_hists(fam)
        sources = [self._retired, *(snap for _, snap in self._external.values())]
        for snap in sources:
            entry = snap.get(fam.name)
            if entry is None:
                continue
            for k, v in entry[0].items():
                values[k] = values.get(k, 0.0) + v
            for k, (counts, total, count) in entry[1].items():
                h = hists.get(k)
                if h is None:
                    hists[k] = _Histogram(fam.buckets, list(counts), total, count)
                else:
                    h.counts = [x + y for x, y in zip(h.counts, counts, strict=True)]
                    h.total += total
                    h.count += count
        return values, hists

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
            values, _ = self._merged(self._families[name])
            return values.get(labels(**label_values), 0.0)

    def total(self, name: str) -> float:
        """Sum over every label set of a counter."""
        with self._lock:
            values, _ = self._merged(self._families[name])
            return sum(values.values())

    def by_label(self, name: str, label: str) -> dict[str, float]:
        """A counter summed per value of one label (`reason` -> count): a summary whose size
        is the label's values, not the series'."""
        out: dict[str, float] = {}
        with self._lock:
            values, _ = self._merged(self._families[name])
            for key, value in values.items():
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
                (f.name, f.kind, f.help, f.collector, *self._merged(f))
                for f in self._families.values()
            ]
        lines: list[str] = []
        for name, kind, help_text, collector, values, hists in families:
            lines.append(f"# HELP {name} {_escape_help(help_text)}")
            lines.append(f"# TYPE {name} {kind}")
            if collector is not None:
                for key, value in collector():
                    values[key] = values.get(key, 0.0) + value
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
