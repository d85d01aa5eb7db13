"""Where the time goes: cProfile for in-process code, py-spy for a running service process."""

from __future__ import annotations

import cProfile
import logging
import pstats
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ProfileRow:
    """One function: self (own) and inclusive share of the profiled time."""

    function: str
    self_share: float  # 0..1
    inclusive_share: float  # 0..1
    calls: int | None = None  # cProfile only

    def as_dict(self) -> dict[str, Any]:
        return {
            "function": self.function,
            "self_share": self.self_share,
            "inclusive_share": self.inclusive_share,
            "calls": self.calls,
        }


@dataclass(frozen=True, slots=True)
class Profile:
    tool: str
    what: str
    rows: list[ProfileRow]

    def as_dict(self) -> dict[str, Any]:
        return {"tool": self.tool, "what": self.what, "rows": [r.as_dict() for r in self.rows]}


def _short_path(filename: str) -> str:
    """Keep the part of a path that names the module: `service/core/heading.py`."""
    p = filename.replace("\\", "/")
    for marker in ("/site-packages/", "/work/main/", "/lib/python3."):
        if marker in p:
            p = p.split(marker, 1)[1]
            if marker == "/lib/python3.":
                p = p.split("/", 1)[-1]
            break
    return p


def profile_calls(
    fn: Callable[[Any], object], items: Iterable[Any], what: str, top: int = 12
) -> Profile:
    """Run `fn(item)` for every item under cProfile; the top functions by own time."""
    prof = cProfile.Profile()
    prof.enable()
    for item in items:
        fn(item)
    prof.disable()
    stats = pstats.Stats(prof)
    raw: dict[tuple[str, int, str], tuple[int, int, float, float, Any]] = stats.stats  # type: ignore[attr-defined]
    total = sum(v[2] for v in raw.values()) or 1.0
    ranked = sorted(raw.items(), key=lambda kv: kv[1][2], reverse=True)[:top]
    rows = []
    for (filename, line, func), (_cc, ncalls, tottime, cumtime, _callers) in ranked:
        name = f"{func} ({_short_path(filename)}:{line})" if filename != "~" else func
        rows.append(ProfileRow(name, tottime / total, min(cumtime / total, 1.0), ncalls))
    return Profile("cProfile", what, rows)


def pyspy_available() -> str | None:
    """Path of the py-spy executable next to this interpreter, or on PATH."""
    beside = Path(sys.executable).with_name("py-spy")
    if beside.exists():
        return str(beside)
    return shutil.which("py-spy")


def pyspy_profile(pid: int, duration_s: float, what: str, top: int = 12) -> Profile | None:
    """Sample a running process and its children with py-spy (100 Hz, active threads only);
    None if it fails."""
    exe = pyspy_available()
    if exe is None:
        log.warning("py-spy is not installed; no profile of the service")
        return None
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "stacks.txt"
        cmd = [exe, "record", "-p", str(pid), "-d", str(max(1, round(duration_s)))]
        cmd += ["-r", "100", "-f", "raw", "-o", str(out), "--subprocesses"]
        try:
            subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=duration_s + 60)
        except (OSError, subprocess.SubprocessError) as err:
            log.warning("py-spy failed: %s", err)
            return None
        return collapse_stacks(out.read_text(), "py-spy", what, top)


def collapse_stacks(text: str, tool: str, what: str, top: int = 12) -> Profile:
    """Own and inclusive shares per function from collapsed stacks (`a;b;c 12` lines)."""
    own: Counter[str] = Counter()
    inclusive: Counter[str] = Counter()
    total = 0
    for line in text.splitlines():
        stack, _, count_text = line.rpartition(" ")
        if not stack or not count_text.isdigit():
            continue
        count = int(count_text)
        frames = [_frame_name(f) for f in stack.split(";") if f]
        if not frames:
            continue
        total += count
        own[frames[-1]] += count
        for name in set(frames):
            inclusive[name] += count
    denom = float(total or 1)
    rows = [
        ProfileRow(name, n / denom, inclusive[name] / denom) for name, n in own.most_common(top)
    ]
    return Profile(tool, what, rows)


def _frame_name(frame: str) -> str:
    """`func (path/to/file.py:123)` → `func (file module path)` without the line number."""
    func, _, where = frame.partition(" (")
    if not where:
        return func
    path = where.rstrip(")").rsplit(":", 1)[0]
    return f"{func} ({_short_path(path)})"
