"""Host-to-sensor SCIP 2.0 commands: `Command` values and their builders.

A command line is `<name><parameters>[;<string>]` followed by LF (we send LF only, like every
peer driver). The optional string (at most 16 characters) comes back in the echo.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Final

from sensor_agent.scip.errors import CommandError

MAX_TAG_CHARS: Final = 16
_TAG_PATTERN: Final = re.compile(r"^[A-Za-z0-9 ._+@]*$")
MAX_STEP: Final = 9999


@dataclass(frozen=True, slots=True)
class ScanRequest:
    """The parameters of GD/MD/ME: absolute steps, cluster count, skipped scans, scan count."""

    start_step: int
    end_step: int
    cluster: int = 1
    interval: int = 0  # scans skipped between transmitted scans
    nscans: int = 0  # 0 = unlimited (until QT)

    @property
    def effective_cluster(self) -> int:
        """Clusters 0 and 1 are the same: one value per step."""
        return max(1, self.cluster)

    @property
    def value_count(self) -> int:
        """Number of values per scan: ceil((end - start + 1) / cluster)."""
        span = self.end_step - self.start_step + 1
        return -(-span // self.effective_cluster)


@dataclass(frozen=True, slots=True)
class Command:
    """One command. `name` is the family used for status tables ("MD", "TM", ...)."""

    name: str
    line: bytes  # the command line without the LF, exactly as echoed by the sensor
    scan: ScanRequest | None = None
    tag: str = ""

    def encode(self) -> bytes:
        return self.line + b"\n"

    @property
    def is_stream(self) -> bool:
        return self.name in ("MD", "ME")

    @property
    def chars_per_step(self) -> int:
        """Characters per step in a scan reply: 3 (GD/MD) or 6 (ME: distance + intensity)."""
        return 6 if self.name == "ME" else 3


def _tagged(body: str, tag: str) -> bytes:
    if len(tag) > MAX_TAG_CHARS or _TAG_PATTERN.fullmatch(tag) is None:
        raise CommandError(f"string {tag!r}: at most 16 of [A-Za-z0-9 ._+@]")
    return (body + (";" + tag if tag else "")).encode("ascii")


def _simple(name: str, tag: str) -> Command:
    return Command(name=name[:2], line=_tagged(name, tag), tag=tag)


def vv(tag: str = "") -> Command:
    """Version information (vendor, product, firmware, protocol, serial number)."""
    return _simple("VV", tag)


def pp(tag: str = "") -> Command:
    """Sensor parameters (model, DMIN, DMAX, ARES, AMIN, AMAX, AFRT, SCAN)."""
    return _simple("PP", tag)


def ii(tag: str = "") -> Command:
    """Sensor state (laser, motor speed, measurement mode, bit rate, time, status)."""
    return _simple("II", tag)


def bm(tag: str = "") -> Command:
    """Laser on."""
    return _simple("BM", tag)


def qt(tag: str = "") -> Command:
    """Laser off; stops any MD/ME stream."""
    return _simple("QT", tag)


def rs(tag: str = "") -> Command:
    """Reset: laser off, motor speed and bit rate to defaults, timestamp counter to 0."""
    return _simple("RS", tag)


def rt(tag: str = "") -> Command:
    """Partial reset (SCIP 2.x; not in the UTM-30LX SCIP 2.0 specification)."""
    return _simple("RT", tag)


def tm(mode: int, tag: str = "") -> Command:
    """Time adjust: 0 = enter adjust mode, 1 = read the timestamp, 2 = leave adjust mode."""
    if mode not in (0, 1, 2):
        raise CommandError(f"TM control code must be 0, 1 or 2, not {mode}")
    return Command(name="TM", line=_tagged(f"TM{mode}", tag), tag=tag)


def _check_scan(req: ScanRequest) -> None:
    if not 0 <= req.start_step <= req.end_step <= MAX_STEP:
        raise CommandError(f"need 0 <= start <= end <= 9999, got {req.start_step}..{req.end_step}")
    if not 0 <= req.cluster <= 99:
        raise CommandError(f"cluster count {req.cluster} outside 0..99")
    if not 0 <= req.interval <= 9:
        raise CommandError(f"scan interval {req.interval} outside 0..9")
    if not 0 <= req.nscans <= 99:
        raise CommandError(f"number of scans {req.nscans} outside 0..99 (0 = unlimited)")


def gd(start_step: int, end_step: int, cluster: int = 1, tag: str = "") -> Command:
    """One scan of 3-character distances; the laser must already be on."""
    req = ScanRequest(start_step, end_step, cluster)
    _check_scan(req)
    body = f"GD{start_step:04d}{end_step:04d}{cluster:02d}"
    return Command(name="GD", line=_tagged(body, tag), scan=req, tag=tag)


def _stream(
    name: str,
    start_step: int,
    end_step: int,
    cluster: int,
    *,
    interval: int,
    nscans: int,
    tag: str,
) -> Command:
    req = ScanRequest(start_step, end_step, cluster, interval, nscans)
    _check_scan(req)
    body = f"{name}{start_step:04d}{end_step:04d}{cluster:02d}{interval:01d}{nscans:02d}"
    return Command(name=name, line=_tagged(body, tag), scan=req, tag=tag)


def md(
    start_step: int,
    end_step: int,
    cluster: int = 1,
    *,
    interval: int = 0,
    nscans: int = 0,
    tag: str = "",
) -> Command:
    """Stream 3-character distances (nscans 0 = until QT)."""
    return _stream("MD", start_step, end_step, cluster, interval=interval, nscans=nscans, tag=tag)


def me(
    start_step: int,
    end_step: int,
    cluster: int = 1,
    *,
    interval: int = 0,
    nscans: int = 0,
    tag: str = "",
) -> Command:
    """Stream distance and intensity, 3 characters each."""
    return _stream("ME", start_step, end_step, cluster, interval=interval, nscans=nscans, tag=tag)


def raw(line: bytes) -> Command:
    """An arbitrary command line (for tests and unknown commands); echo matching is exact."""
    return Command(name=line[:2].decode("ascii", "replace"), line=line)


__all__ = [
    "MAX_TAG_CHARS",
    "Command",
    "ScanRequest",
    "bm",
    "gd",
    "ii",
    "md",
    "me",
    "pp",
    "qt",
    "raw",
    "rs",
    "rt",
    "tm",
    "vv",
]
