"""The Foxglove live view's cost: 10 robots at 40 Hz, one viewer connected vs none, side by side.

`python -m bench.foxglove_cost [--robots 10] [--window 20] [--pairs 2] [--out FILE.json]`

One `mapping-service serve --foxglove-port P --mapper-processes 2` (the configuration that meets
the scale target, docs/service.md), one `bench.loadgen` publishing every robot's scans at 40 Hz
to the service and to the measuring subscriber (`bench.subscriber`: scan->pose latency on the
Zenoh pose path). Windows alternate without and with a viewer (this module's `viewer` mode, a
process of its own speaking the Foxglove WebSocket protocol and subscribing to every channel),
so that both see the same machine load. Per window: the service's CPU (its process tree, the
mapper processes included), the worker time per scan (`mapping_scan_processing_seconds`),
scans dropped, scan->pose latency p50/p99, and what the viewer received.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil

from bench.common import BenchError, machine_info
from bench.scale import (
    BIN,
    Procs,
    _proc_tree_cpu_s,
    _scrape,
    _wait_line,
    _wait_until,
    analyze,
    free_port,
    metrics_delta,
)

log = logging.getLogger(__name__)

SUBPROTOCOL = "foxglove.sdk.v1"


# ---------------------------------------------------------------------------------------------
# The viewer (a process of its own)


async def _view(url: str, seconds: float, out: Path) -> None:
    import websockets  # a dev dependency, only the viewer needs it

    counts: dict[str, int] = {}
    sizes: dict[str, int] = {}
    topics: dict[int, str] = {}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as ws:  # type: ignore[list-item]
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        deadline = time.monotonic() + seconds
        next_sub = 1
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                frame = await asyncio.wait_for(ws.recv(), remaining)
            except TimeoutError:
                break
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    subs = []
                    for channel in msg["channels"]:
                        topics[next_sub] = channel["topic"]
                        subs.append({"id": next_sub, "channelId": channel["id"]})
                        next_sub += 1
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                continue
            if frame[0] == 1:
                sub_id = int.from_bytes(frame[1:5], "little")
                kind = topics.get(sub_id, "?").rsplit("/", 1)[-1]
                counts[kind] = counts.get(kind, 0) + 1
                sizes[kind] = sizes.get(kind, 0) + len(frame)
    out.write_text(json.dumps({"messages": counts, "bytes": sizes, "seconds": seconds}))


def viewer_main(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.foxglove_cost viewer")
    p.add_argument("--url", required=True)
    p.add_argument("--seconds", type=float, required=True)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    asyncio.run(_view(args.url, args.seconds, args.out))
    return 0


# ---------------------------------------------------------------------------------------------
# The measurement


def _histogram_p99_s(delta_buckets: dict[float, float]) -> float:
    """The upper bound of the bucket holding the 99th percentile (cumulative bucket deltas)."""
    if not delta_buckets:
        return math.nan
    total = max(delta_buckets.values())
    for le in sorted(delta_buckets):
        if delta_buckets[le] >= 0.99 * total:
            return le
    return math.inf


def _buckets(metrics: dict[str, float], name: str) -> dict[float, float]:
    out: dict[float, float] = {}
    for key, value in metrics.items():
        if key.startswith(name + "_bucket{"):
            le = key.split('le="', 1)[1].split('"', 1)[0]
            bound = math.inf if le == "+Inf" else float(le)
            out[bound] = out.get(bound, 0.0) + value
    return out


def run(
    robots: int,
    window_s: float,
    pairs: int,
    warmup_s: float,
    work_dir: Path,
    *,
    mapper_processes: int = 2,
) -> dict[str, Any]:
    work_dir.mkdir(parents=True, exist_ok=True)
    http_port, zenoh_port, sub_port, fox_port = free_port(), free_port(), free_port(), free_port()
    service_ep = f"tcp/127.0.0.1:{zenoh_port}"
    sub_ep = f"tcp/127.0.0.1:{sub_port}"
    base = f"http://127.0.0.1:{http_port}"
    ids = [f"fox-r{i:02d}" for i in range(robots)]
    data_dir = Path(tempfile.mkdtemp(prefix="bench-foxglove-", dir=work_dir))
    rec_path = work_dir / "foxglove-rec.npz"
    procs = Procs()
    windows: list[dict[str, Any]] = []
    try:
        service = procs.start(
            "service",
            [
                str(BIN / "mapping-service"), "serve", "--http-port", str(http_port),
                "--data-dir", str(data_dir), "--zenoh-listen", service_ep,
                "--mapper-processes", str(mapper_processes), "--foxglove-port", str(fox_port),
            ],
            work_dir,
            stdout=subprocess.DEVNULL,
        )  # fmt: skip
        client = httpx.Client(base_url=base, timeout=20.0)

        def healthy() -> bool:
            if service.poll() is not None:
                raise BenchError(f"the service exited with {service.returncode}")
            try:
                return client.get("/health").status_code == 200
            except httpx.HTTPError:
                return False

        _wait_until(healthy, 60.0, "the service did not answer /health")
        for r in ids:
            resp = client.post("/sessions", json={"robot_id": r})
            if resp.status_code != 201:
                raise BenchError(f"POST /sessions: {resp.status_code} {resp.text[:200]}")
        sub = procs.start(
            "subscriber",
            [sys.executable, "-m", "bench.subscriber", "--listen", sub_ep, "--connect",
             service_ep, "--out", str(rec_path)],
            work_dir, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        )  # fmt: skip
        _wait_line(sub, "ready", 60.0, "the measuring subscriber")
        gen = procs.start(
            "loadgen",
            [sys.executable, "-m", "bench.loadgen", "--robots", ",".join(ids), "--connect",
             service_ep, "--connect", sub_ep, "--rate", "40", "--out",
             str(work_dir / "foxglove-loadgen.json")],
            work_dir, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        )  # fmt: skip
        _wait_line(gen, "ready", 120.0, "the load generator")

        def all_mapping() -> bool:
            try:
                sessions = client.get("/sessions").json()["sessions"]
            except (httpx.HTTPError, ValueError, KeyError):
                return False
            return all(int(s.get("poses", 0)) > 0 for s in sessions)

        _wait_until(all_mapping, 120.0, "not every session got poses", 0.5)
        time.sleep(warmup_s)
        svc = psutil.Process(service.pid)
        for index in range(2 * pairs):
            with_viewer = index % 2 == 1
            viewer = None
            viewer_out = work_dir / f"viewer-{index}.json"
            if with_viewer:
                viewer = procs.start(
                    f"viewer-{index}",
                    [sys.executable, "-m", "bench.foxglove_cost", "viewer", "--url",
                     f"ws://127.0.0.1:{fox_port}", "--seconds", str(window_s + 4.0), "--out",
                     str(viewer_out)],
                    work_dir, stdout=subprocess.PIPE,
                )  # fmt: skip
                _wait_line(viewer, "ready", 30.0, "the viewer")
                time.sleep(2.0)  # subscribed, and the first map sent, before the window
            m0 = _scrape(client)
            c0, w0 = _proc_tree_cpu_s([svc]), time.monotonic()
            t0_ns = time.time_ns()
            time.sleep(window_s)
            t1_ns = time.time_ns()
            c1, w1 = _proc_tree_cpu_s([svc]), time.monotonic()
            m1 = _scrape(client)
            delta = metrics_delta(m0, m1)
            b0 = _buckets(m0, "mapping_scan_processing_seconds")
            b1 = _buckets(m1, "mapping_scan_processing_seconds")
            count = delta.get("mapping_scan_processing_seconds_count", 0.0)
            window: dict[str, Any] = {
                "viewer": with_viewer,
                "t0_ns": t0_ns,
                "t1_ns": t1_ns,
                "service_cpu_pct": 100.0 * (c1 - c0) / max(w1 - w0, 1e-9),
                "scans_accepted": delta.get("mapping_scans_accepted_total", 0.0),
                "scans_dropped": delta.get("mapping_scans_dropped_total", 0.0),
                "worker_ms_per_scan_mean": 1000.0
                * delta.get("mapping_scan_processing_seconds_sum", 0.0)
                / max(count, 1.0),
                "worker_ms_per_scan_p99_bucket": 1000.0
                * _histogram_p99_s({k: b1.get(k, 0.0) - b0.get(k, 0.0) for k in b1}),
            }
            if viewer is not None:
                viewer.wait(timeout=60)
                window["viewer_received"] = json.loads(viewer_out.read_text())
            windows.append(window)
            log.info("window %d: %s", index, {k: v for k, v in window.items() if "t" not in k[:2]})
        assert gen.stdin is not None
        gen.stdin.write("stop\n")
        gen.stdin.flush()
        gen.wait(timeout=60)
        time.sleep(2.0)
        assert sub.stdin is not None
        sub.stdin.write("stop\n")
        sub.stdin.flush()
        sub.wait(timeout=60)
        data = np.load(rec_path)
        names = [str(x) for x in data["robots"]]
        for window in windows:
            window.update(
                analyze(
                    names, data["scans"], data["poses"], window["t0_ns"], window["t1_ns"],
                    expected=robots,
                )
            )  # fmt: skip
    finally:
        procs.stop_all()
        shutil.rmtree(data_dir, ignore_errors=True)
    return {
        "robots": robots,
        "mapper_processes": mapper_processes,
        "window_s": window_s,
        "windows": windows,
        "machine": machine_info(),
    }


def summary(result: dict[str, Any]) -> dict[str, dict[str, float]]:
    keys = (
        "service_cpu_pct",
        "worker_ms_per_scan_mean",
        "sustained_scans_per_s",
        "dropped",
        "latency_p50_ms",
        "latency_p99_ms",
    )
    out: dict[str, dict[str, float]] = {}
    for label, flag in (("none", False), ("one viewer", True)):
        rows = [w for w in result["windows"] if w["viewer"] == flag]
        out[label] = {k: float(np.mean([w[k] for w in rows])) for k in keys}
    return out


KEEP = "foxglove-cost"


def _block(result: dict[str, Any]) -> list[str]:
    """One run: how it was made, its windows, and the means."""
    m = result["machine"]
    rows = []
    for w in result["windows"]:
        got = w.get("viewer_received") or {}
        sent = got.get("messages", {})
        mib = sum(got.get("bytes", {}).values()) / 2**20 / max(float(got.get("seconds", 1)), 1e-9)
        rows.append(
            "| {} | {:.0f} | {:.2f} | {:.0f} | {:.0f} of {:.0f} | {:.1f} | {:.1f} | {} |".format(
                "one viewer" if w["viewer"] else "none",
                w["service_cpu_pct"],
                w["worker_ms_per_scan_mean"],
                w["sustained_scans_per_s"],
                w["dropped"],
                w["scans_published"],
                w["latency_p50_ms"],
                w["latency_p99_ms"],
                ", ".join(f"{k} {v}" for k, v in sorted(sent.items())) + f" ({mib:.2f} MiB/s)"
                if sent
                else "–",
            )
        )
    summ = result["summary"]
    none, one = summ["none"], summ["one viewer"]

    def ratio(key: str) -> str:
        return f"{one[key] / none[key]:.2f}×" if none[key] else "–"

    n, win = result["robots"], f"{result['window_s']:g}"
    k = result.get("mapper_processes", 2)
    commit, load = m.get("git_commit", "?"), m.get("load_average_at_start", "?")
    intro = (
        f"`python -m bench.foxglove_cost --robots {n} --window {win} --mapper-processes {k} "
        f"--doc docs/benchmarks.md` at commit `{commit}` (load average at start {load}): one "
        f"`mapping-service serve --mapper-processes {k} --foxglove-port P`, the one-process load "
        f"generator publishing {n} robots at 40 Hz, windows of {win} s alternating without and "
        "with one viewer (a Foxglove-protocol client subscribed to every channel of every "
        "robot). Columns as in section 2; *viewer got* is what the viewer received in its "
        "window."
    )
    cpu0, cpu1 = none["service_cpu_pct"], one["service_cpu_pct"]
    ms0, ms1 = none["worker_ms_per_scan_mean"], one["worker_ms_per_scan_mean"]
    p99_0, p99_1 = none["latency_p99_ms"], one["latency_p99_ms"]
    means = (
        f"Means: service CPU {cpu0:.0f} % without a viewer, {cpu1:.0f} % with one "
        f"({ratio('service_cpu_pct')}); worker time per scan {ms0:.2f} → {ms1:.2f} ms "
        f"({ratio('worker_ms_per_scan_mean')}); scan→pose p99 {p99_0:.1f} → {p99_1:.1f} ms; "
        f"dropped {none['dropped']:.0f} → {one['dropped']:.0f} per window."
    )
    return [
        intro,
        "",
        (
            "| viewer | service CPU % | service ms/scan | poses/s | dropped | p50 ms | p99 ms "
            "| viewer got |"
        ),
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        means,
        "",
    ]


def render_section(results: Sequence[dict[str, Any]]) -> str:
    """The section of docs/benchmarks.md, between markers that `bench.report` keeps."""
    lines = ["", f"<!-- keep:{KEEP} -->", "## Foxglove live view", ""]
    lines += [
        (
            "What one Foxglove viewer costs the service (`service/app/foxglove.py`: nothing is "
            "encoded for a channel without a subscriber; the ingest workers only hand the "
            "latest scan and pose over). The machine is shared with other jobs (load averages "
            "below), so compare the windows of one table with each other: they alternate under "
            "the same load."
        ),
        "",
    ]
    for result in results:
        lines += _block(result)
    lines += [f"<!-- /keep:{KEEP} -->", ""]
    return "\n".join(lines)


def write_section(doc: Path, section: str) -> None:
    text = doc.read_text() if doc.exists() else ""
    begin, end = f"\n<!-- keep:{KEEP} -->\n", f"\n<!-- /keep:{KEEP} -->\n"
    if begin in text and end in text:
        start = text.index(begin)
        stop = text.index(end, start) + len(end)
        text = text[:start] + text[stop:]
    doc.write_text(text.rstrip("\n") + "\n" + section)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["viewer"]:
        return viewer_main(argv[1:])
    p = argparse.ArgumentParser(prog="python -m bench.foxglove_cost")
    p.add_argument("--robots", type=int, default=10)
    p.add_argument("--window", type=float, default=20.0, help="seconds per window")
    p.add_argument("--pairs", type=int, default=2, help="(none, viewer) window pairs")
    p.add_argument("--warmup", type=float, default=10.0)
    p.add_argument("--mapper-processes", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path("bench/out/foxglove_cost.json"))
    p.add_argument("--doc", type=Path, default=None, help="write the section into this file")
    p.add_argument(
        "--from-json",
        type=Path,
        action="append",
        default=[],
        help="render previous runs' JSON instead of measuring (repeatable: one table each)",
    )
    args = p.parse_args(argv)
    if args.from_json:
        results = [json.loads(path.read_text()) for path in args.from_json]
        if args.doc is not None:
            write_section(args.doc, render_section(results))
        print(render_section(results))
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    work = Path(tempfile.mkdtemp(prefix="bench-foxglove-work-"))
    try:
        result = run(
            args.robots,
            args.window,
            args.pairs,
            args.warmup,
            work,
            mapper_processes=args.mapper_processes,
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result["summary"] = summary(result)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2, default=str))
    if args.doc is not None:
        write_section(args.doc, render_section([result]))
    print(json.dumps(result["summary"], indent=2))
    for w in result["windows"]:
        print(json.dumps({k: v for k, v in w.items() if k not in ("t0_ns", "t1_ns")}))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
