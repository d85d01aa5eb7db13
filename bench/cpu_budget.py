"""CPU per scan, per process of the service, per thread, and per stage of the per-scan path.

`python -m bench.cpu_budget --robots 10,25 [--mapper-processes 2] [--measure-s 15] [--profile]`

CPU time (user + system, from /proc via psutil) per scan is far less sensitive to other load on
a shared machine than wall time: a process waiting for a core accrues none. Each point is one
`bench.scale.run_point` run (load generator, 40 Hz per robot); the service's main process and
each of its children (the mapper processes) are read separately, and divided by the scans the
service accepted in the window; so is each of their threads (`thread_cpu`: exact, from
/proc/<pid>/task; Python threads named by `py-spy dump`, Zenoh's runtime threads as one).
With `--profile`, py-spy samples each of those processes on its own (non-blocking) and each
sample is charged to one stage of the path by the frames on its stack (`STAGES`, first match
wins); a stage's CPU-ms per scan is its share of the samples times the process's CPU-ms per
scan. That split is approximate: py-spy counts a thread blocked on a read or a lock as busy
(it gave a mapper's back-end thread 38 % of the samples where /proc says 5-8 % of the CPU), so
read it within a thread, beside the exact per-thread figures.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import re
import subprocess
import sys
import tempfile
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import psutil

from bench.profiling import _frame_name, pyspy_available

log = logging.getLogger(__name__)

# (stage, substrings of a frame `func (path/of/module.py)`): the innermost frame of a sample that
# matches a stage decides (checked in this order at each frame).
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("estimator (front end)", ("service/core/frontend/",)),
    ("grid", ("service/core/maps/",)),
    ("back end", ("service/core/backend/", "service/app/backend.py", "gtsam")),
    ("zenoh callback", ("on_sample (service/app/ingest.py)", "_on_scan (service/app/runtime.py)")),
    ("fsync", ("sync (service/app/store.py)", "_sync_loop (service/app/runtime.py)")),
    ("record (append)", ("clients/recording.py",)),
    ("decode + validate", ("decode_scan (clients/wire.py)", "scan_to_laser", "bridge.py")),
    ("pose encode", ("encode_pose (clients/wire.py)",)),
    ("pose publish (Zenoh put)", ("publish (service/app/fanout.py)",)),
    (
        "pipe (pickle, send, recv)",
        ("multiprocessing/connection.py", "reduction.py", "pickle"),
    ),
    ("fan-out (SSE)", ("service/app/fanout.py", "sse_pose_frame", "frames (service/app/api")),
    ("HTTP / event loop", ("uvicorn/", "asyncio/", "starlette/", "fastapi/", "h11/", "anyio/")),
    ("metrics", ("service/app/metrics.py",)),
    ("session bookkeeping", ("service/app/sessions.py", "service/app/mapper.py")),
    ("ingest scheduling", ("service/app/ingest.py", "threading.py")),
)
OTHER = "other"


def process_tree_cpu(pid: int) -> dict[str, float]:
    """CPU seconds (user + system) of the process `pid` ("main") and of each child."""
    out: dict[str, float] = {}
    with contextlib.suppress(psutil.Error):
        root = psutil.Process(pid)
        t = root.cpu_times()
        out["main"] = t.user + t.system
        for child in sorted(root.children(recursive=True), key=lambda c: c.pid):
            with contextlib.suppress(psutil.Error):
                ct = child.cpu_times()
                out[_child_label(child)] = ct.user + ct.system
    return out


# Zenoh's own threads (its Rust runtime: rx-N, tx-N, acc-N, app-N, net-N), not Python's.
_ZENOH_THREADS = ("rx-", "tx-", "acc-", "app-", "net-")
_PYSPY_THREAD = re.compile(r'^Thread (\d+) \([^)]*\): "(.*)"$')


def thread_cpu(pid: int) -> dict[int, tuple[str, float]]:
    """Per thread of the process `pid`, by native id: (its OS name, CPU seconds, user +
    system). Exact, unlike a sampler's guess of which thread was on a CPU."""
    out: dict[int, tuple[str, float]] = {}
    with contextlib.suppress(psutil.Error):
        for t in psutil.Process(pid).threads():
            try:
                comm = Path(f"/proc/{pid}/task/{t.id}/comm").read_text().strip()
            except OSError:
                comm = "?"
            out[t.id] = (comm, t.user_time + t.system_time)
    return out


def python_thread_names(pid: int) -> dict[int, str]:
    """The Python threads' names (`threading.Thread.name`) by native id, from `py-spy dump`;
    empty without py-spy. The OS names them all "python"."""
    exe = pyspy_available()
    if exe is None:
        return {}
    try:
        dump = subprocess.run(
            [exe, "dump", "--pid", str(pid), "--nonblocking"],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        ).stdout
    except (OSError, subprocess.TimeoutExpired):
        return {}
    names = {}
    for line in dump.splitlines():
        m = _PYSPY_THREAD.match(line.strip())
        if m:
            names[int(m.group(1))] = m.group(2)
    return names


def thread_split(
    before: dict[int, tuple[str, float]],
    after: dict[int, tuple[str, float]],
    names: dict[int, str],
) -> dict[str, float]:
    """CPU seconds per thread label between two `thread_cpu` snapshots (a thread born between
    them counts whole): Python threads by name, Zenoh's runtime as one, others by OS name."""
    used: Counter[str] = Counter()
    for tid, (comm, cpu_s) in after.items():
        if tid in names:
            label = names[tid]
        elif comm.startswith(_ZENOH_THREADS):
            label = "zenoh (native)"
        else:
            label = comm
        used[label] += cpu_s - before.get(tid, (comm, 0.0))[1]
    return dict(used.most_common())


def _child_label(child: psutil.Process) -> str:
    try:
        cmd = " ".join(child.cmdline())
    except psutil.Error:
        cmd = ""
    kind = "tracker" if "resource_tracker" in cmd else "mapper"
    return f"{kind}-{child.pid}"


def classify(stack: Sequence[str]) -> str:
    """The stage of one sampled stack (frames outermost first)."""
    for raw in reversed(stack):  # the innermost frame that names a stage decides
        frame = _frame_name(raw)
        for stage, needles in STAGES:
            if any(n in frame for n in needles):
                return stage
    return OTHER


def stage_shares(collapsed: str) -> dict[str, float]:
    """Share of samples per stage, from py-spy's raw (collapsed stack) output."""
    counts: Counter[str] = Counter()
    for line in collapsed.splitlines():
        stack, _, n = line.rpartition(" ")
        if not stack or not n.isdigit():
            continue
        counts[classify(stack.split(";"))] += int(n)
    total = sum(counts.values()) or 1
    return {k: v / total for k, v in counts.most_common()}


def start_pyspy(pid: int, duration_s: float, out: Path) -> subprocess.Popen[bytes] | None:
    exe = pyspy_available()
    if exe is None:
        log.warning("py-spy is not installed: no stage split")
        return None
    cmd = [exe, "record", "-p", str(pid), "-d", str(max(1, round(duration_s))), "-r", "200"]
    cmd += ["-f", "raw", "-o", str(out), "--nonblocking"]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def budget_rows(point: dict[str, Any]) -> list[list[str]]:
    """Markdown rows: process, CPU %, CPU-ms per scan, then its stages."""
    rows = []
    per_proc = point.get("cpu_ms_per_scan_by_process") or {}
    shares = point.get("stage_shares") or {}
    for name, ms in per_proc.items():
        pct = point["cpu_pct_by_process"][name]
        split = shares.get(name) or {}
        stages = ", ".join(
            f"{stage} {ms * share:.3f}" for stage, share in split.items() if ms * share >= 0.005
        )
        rows.append([str(point["robots"]), name, f"{pct:.0f}", f"{ms:.3f}", stages or "-"])
    total = sum(per_proc.values())
    rows.append([str(point["robots"]), "**service total**", "", f"**{total:.3f}**", ""])
    return rows


def thread_rows(point: dict[str, Any]) -> list[list[str]]:
    """Markdown rows: process, then its threads' CPU-ms per scan (exact, from /proc)."""
    rows = []
    for name, threads in (point.get("cpu_ms_per_scan_by_thread") or {}).items():
        split = ", ".join(f"{t} {ms:.3f}" for t, ms in threads.items() if ms >= 0.005)
        rows.append([str(point["robots"]), name, split or "-"])
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    from bench.scale import ScaleConfig, run_point

    parser = argparse.ArgumentParser(prog="python -m bench.cpu_budget", description=__doc__)
    parser.add_argument("--robots", default="10,25", help="comma-separated robot counts")
    parser.add_argument("--mapper-processes", type=int, default=2)
    parser.add_argument("--warmup-s", type=float, default=4.0)
    parser.add_argument("--measure-s", type=float, default=15.0)
    parser.add_argument("--profile", action="store_true", help="py-spy stage split")
    parser.add_argument("--out", type=Path, default=Path("bench/out/cpu_budget.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    points = []
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="cpu-budget-", dir=args.out.parent) as tmp:
        for n in (int(x) for x in args.robots.split(",") if x):
            cfg = ScaleConfig(
                n,
                "loadgen",
                args.mapper_processes,
                args.warmup_s,
                args.measure_s,
                profile_s=args.measure_s if args.profile else 0.0,
                stage_profile=args.profile,
            )
            point = run_point(cfg, Path(tmp) / f"n{n}")
            point.pop("metrics_delta", None)
            points.append(point)
            for stacks in Path(tmp).glob(f"n{n}/*.stacks"):  # kept for a closer look
                stacks.replace(args.out.with_name(f"{args.out.stem}-n{n}-{stacks.name}"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(points, indent=1))
    print("| robots | process | CPU % | CPU-ms/scan | stages (CPU-ms/scan) |")
    print("|---|---|---|---|---|")
    for p in points:
        for row in budget_rows(p):
            print("| " + " | ".join(row) + " |")
        print(
            f"<!-- {p['robots']} robots: dropped {p['dropped']} of {p['scans_published']}, "
            f"p50 {p['latency_p50_ms']:.1f} ms, p99 {p['latency_p99_ms']:.1f} ms, "
            f"machine busy {p['machine_busy_pct']:.0f} %, load {p['loadavg_before'][0]:.1f} -->"
        )
    print()
    print("| robots | process | threads (CPU-ms/scan, exact) |")
    print("|---|---|---|")
    for p in points:
        for row in thread_rows(p):
            print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
