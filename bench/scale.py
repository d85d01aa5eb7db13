"""Section 2: end to end and scale. N robots at 40 Hz through Zenoh into one service process.

Processes of one run, all on this machine:

- `mapping-service serve` (the process measured: CPU and RSS with psutil);
- the measuring subscriber (`bench.subscriber`): every scan's stamp and every pose's arrival;
- the load: N `sensor-agent --emulate` processes (the real agent path: emulated UTM-30LX on a
  pty, driver, publisher), or one `bench.loadgen` process publishing pre-simulated scans.

Scan→pose latency is the pose's arrival at the subscriber minus the scan's `host_stamp_ns` (the
agent's clock when it read the scan, just before publishing); both are this machine's wall clock.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import httpx
import numpy as np
import psutil

from bench.common import BenchError, Target
from bench.cpu_budget import (
    process_tree_cpu,
    python_thread_names,
    stage_shares,
    start_pyspy,
    thread_cpu,
    thread_split,
)
from bench.profiling import pyspy_profile

log = logging.getLogger(__name__)

RATE_HZ = 40.0
TARGET_ROBOTS = 10
TARGET_P99_MS = 50.0
QUEUE_DEPTH_METRIC = "mapping_ingest_queue_depth"  # the service's per-robot queue gauge
BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def service_command(
    http_port: int,
    data_dir: Path,
    zenoh_endpoint: str,
    mapper_processes: int,
    loop_closure: bool = True,
) -> list[str]:
    return [
        str(BIN / "mapping-service"),
        "serve",
        "--http-port",
        str(http_port),
        "--data-dir",
        str(data_dir),
        "--zenoh-listen",
        zenoh_endpoint,
        "--mapper-processes",
        str(mapper_processes),
        *([] if loop_closure else ["--no-loop-closure"]),
    ]


@dataclass(frozen=True, slots=True)
class ScaleConfig:
    robots: int
    load: str  # "agents" (N sensor-agent processes) or "loadgen" (one process)
    mapper_processes: int  # the service's `--mapper-processes` (0: estimators in its process)
    warmup_s: float
    measure_s: float
    drain_s: float = 2.0  # after the load stops and the queues are empty
    max_drain_s: float = 60.0
    startup_timeout_s: float = 180.0
    profile_s: float = 0.0  # >0: py-spy the service for this long inside the window
    path_scans: int = 400  # scans the load generator simulates once and drives back and forth
    sse_clients: int = (
        0  # browser-like pose streams held open during the run (bench.fanout_clients)
    )
    zenoh_pose_subscribers: int = 0  # Zenoh sessions subscribed to every pose, same process
    zenoh_via_router: bool = True  # the subscribers behind one router (in that process)
    stage_profile: bool = False  # py-spy each service process on its own (bench.cpu_budget)
    loop_closure: bool = True  # False: `serve --no-loop-closure` (the front end alone)


@dataclass(slots=True)
class Procs:
    """Every process this run started, to stop them all (and only them) at the end."""

    items: list[tuple[str, subprocess.Popen[str]]] = field(default_factory=list)
    logs: list[IO[str]] = field(default_factory=list)

    def start(
        self, name: str, cmd: Sequence[str], log_dir: Path, **kw: Any
    ) -> subprocess.Popen[str]:
        log_file = (log_dir / f"{name}.log").open("w")
        self.logs.append(log_file)
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        proc = subprocess.Popen(
            list(cmd), stderr=log_file, text=True, env=env, cwd=kw.pop("cwd", None), **kw
        )
        self.items.append((name, proc))
        return proc

    def stop_all(self) -> None:
        for _name, proc in reversed(self.items):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 10.0
        for name, proc in reversed(self.items):
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s (pid %d) did not stop on SIGINT; killing it", name, proc.pid)
                proc.kill()
                proc.wait(timeout=10)
        for f in self.logs:
            f.close()


def _wait_line(proc: subprocess.Popen[str], expected: str, timeout_s: float, what: str) -> None:
    """Wait for `expected` on the process's stdout, with a deadline (a reader thread)."""
    assert proc.stdout is not None
    got = threading.Event()
    stream = proc.stdout

    def read() -> None:
        for line in stream:
            if line.strip() == expected:
                got.set()
                return

    threading.Thread(target=read, daemon=True).start()
    if not got.wait(timeout_s):
        raise BenchError(f"{what} did not become ready within {timeout_s:.0f} s")


def _wait_until(cond: Callable[[], bool], timeout_s: float, what: str, poll_s: float = 0.2) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(poll_s)
    raise BenchError(f"{what} (waited {timeout_s:.0f} s)")


def parse_prometheus(text: str) -> dict[str, float]:
    """`name{labels} value` lines into a dict (comments and odd lines skipped)."""
    out: dict[str, float] = {}
    for line in text.splitlines():
        if not line or line.startswith("#"):
            continue
        name, _, value = line.rpartition(" ")
        with contextlib.suppress(ValueError):
            out[name.strip()] = float(value)
    return out


def metrics_delta(before: dict[str, float], after: dict[str, float]) -> dict[str, float]:
    """Change of every counter (`*_total`) and histogram sum/count, summed over labels."""
    out: dict[str, float] = {}
    for key, value in after.items():
        name = key.split("{", 1)[0]
        if name.endswith(("_total", "_sum", "_count")):
            out[name] = out.get(name, 0.0) + value - before.get(key, 0.0)
    return {k: v for k, v in sorted(out.items()) if v != 0.0}


def analyze(
    robots: Sequence[str],
    scans: np.ndarray,
    poses: np.ndarray,
    t0_ns: int,
    t1_ns: int,
    *,
    expected: int = 0,
) -> dict[str, Any]:
    """Throughput, drops and latency of scans stamped inside [t0, t1).

    `scans` and `poses` are (K, 3) int64 rows of (robot index, stamp_ns, arrival_ns); a scan
    is answered when a pose with the same robot and stamp arrived (at any time before the
    recording stopped).
    """
    window_s = (t1_ns - t0_ns) / 1e9
    in_win = (scans[:, 1] >= t0_ns) & (scans[:, 1] < t1_ns)
    s = scans[in_win]
    scan_keys = {(int(r), int(st)) for r, st, _ in s}
    first_pose: dict[tuple[int, int], int] = {}
    for r, st, arr in poses:
        key = (int(r), int(st))
        if key in scan_keys and key not in first_pose:
            first_pose[key] = int(arr)
    lat_ms = np.array([(first_pose[k] - k[1]) / 1e6 for k in first_pose], dtype=np.float64)
    # Throughput: poses delivered during the window, whatever scan they answer.
    pose_in_win = (poses[:, 2] >= t0_ns) & (poses[:, 2] < t1_ns) if poses.size else np.zeros(0)
    published = len(scan_keys)
    answered = len(first_pose)
    # Robots that published nothing in the window count as zero.
    per_robot_pub = np.bincount(s[:, 0].astype(np.int64), minlength=max(len(robots), expected))
    return {
        "window_s": window_s,
        "scans_published": published,
        "publish_rate_per_robot_hz": float(per_robot_pub.mean() / window_s)
        if per_robot_pub.size
        else 0.0,
        "publish_rate_min_robot_hz": float(per_robot_pub.min() / window_s)
        if per_robot_pub.size
        else 0.0,
        "poses_received": answered,
        "poses_delivered_in_window": int(np.count_nonzero(pose_in_win)),
        "sustained_scans_per_s": int(np.count_nonzero(pose_in_win)) / window_s,
        "dropped": published - answered,
        "dropped_share": (published - answered) / published if published else math.nan,
        "latency_p50_ms": float(np.percentile(lat_ms, 50)) if lat_ms.size else math.nan,
        "latency_p99_ms": float(np.percentile(lat_ms, 99)) if lat_ms.size else math.nan,
        "latency_max_ms": float(lat_ms.max()) if lat_ms.size else math.nan,
    }


def _proc_tree_cpu_s(procs: Sequence[psutil.Process]) -> float:
    total = 0.0
    for p in procs:
        with contextlib.suppress(psutil.Error):
            t = p.cpu_times()
            total += t.user + t.system
            for c in p.children(recursive=True):
                with contextlib.suppress(psutil.Error):
                    ct = c.cpu_times()
                    total += ct.user + ct.system
    return total


def _cpu_snapshot(
    service: psutil.Process, load: Sequence[psutil.Process], subscriber: Sequence[psutil.Process]
) -> dict[str, tuple[float, float]]:
    """CPU seconds used so far, each with the monotonic time it was read at.

    Reading 25 process trees takes a while on a loaded machine; timing each read keeps every
    percentage on its own interval.
    """
    snap: dict[str, tuple[float, float]] = {}
    snap["service"] = (_proc_tree_cpu_s([service]), time.monotonic())
    snap["load"] = (_proc_tree_cpu_s(load), time.monotonic())
    snap["subscriber"] = (_proc_tree_cpu_s(subscriber), time.monotonic())
    snap["machine"] = (_machine_busy_s(), time.monotonic())
    return snap


def _scrape(client: httpx.Client) -> dict[str, float]:
    """`GET /metrics`, or {} when an overloaded service does not answer in time."""
    try:
        return parse_prometheus(client.get("/metrics", timeout=30.0).text)
    except httpx.HTTPError as err:
        log.warning("GET /metrics failed: %s", err)
        return {}


def _stop_load(load_procs: Sequence[subprocess.Popen[str]]) -> None:
    """`stop` on stdin for the load generator, SIGINT for agents; wait for them to exit."""
    for p in load_procs:
        if p.poll() is not None:
            continue
        if p.stdin is not None:
            with contextlib.suppress(OSError):
                p.stdin.write("stop\n")
                p.stdin.flush()
        else:
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + 30.0
    for p in load_procs:
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=max(0.1, deadline - time.monotonic()))


def _queued(client: httpx.Client) -> float | None:
    """Scans waiting in the service's ingest queues (None if the gauge is not available)."""
    metrics = _scrape(client)
    depths = [v for k, v in metrics.items() if k.split("{", 1)[0] == QUEUE_DEPTH_METRIC]
    return sum(depths) if metrics and depths else (0.0 if metrics else None)


def _drain(client: httpx.Client, settle_s: float, max_s: float) -> float:
    """Wait until the service's queues are empty (at most `max_s`), then `settle_s` more."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < max_s:
        queued = _queued(client)
        if queued is None or queued == 0:
            break
        time.sleep(0.25)
    time.sleep(settle_s)  # the scan in hand and the last poses on the wire
    return time.monotonic() - t0


def _machine_busy_s() -> float:
    t = psutil.cpu_times()
    return float(t.user + t.system + t.nice + getattr(t, "irq", 0.0) + getattr(t, "softirq", 0.0))


@contextlib.contextmanager
def _rss_sampler(proc: psutil.Process, period_s: float = 0.5) -> Iterator[list[int]]:
    samples: list[int] = []
    stop = threading.Event()

    def run() -> None:
        while not stop.is_set():
            with contextlib.suppress(psutil.Error):
                tree = [proc, *proc.children(recursive=True)]  # with its mapper processes
                samples.append(sum(p.memory_info().rss for p in tree))
            stop.wait(period_s)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield samples
    finally:
        stop.set()
        t.join(timeout=5)


def run_point(cfg: ScaleConfig, work_dir: Path, seed: int = 1) -> dict[str, Any]:
    """One measured run: start everything, warm up, measure, stop everything."""
    work_dir.mkdir(parents=True, exist_ok=True)
    http_port, zenoh_port, sub_port = free_port(), free_port(), free_port()
    service_ep = f"tcp/127.0.0.1:{zenoh_port}"
    sub_ep = f"tcp/127.0.0.1:{sub_port}"
    base = f"http://127.0.0.1:{http_port}"
    robots = [f"bench-r{i:02d}" for i in range(cfg.robots)]
    procs = Procs()
    data_dir = Path(tempfile.mkdtemp(prefix="bench-service-", dir=work_dir))
    name = f"{cfg.load}-{cfg.robots}-k{cfg.mapper_processes}"
    rec_path = work_dir / f"{name}-rec.npz"
    loadgen_out = work_dir / f"{name}-loadgen.json"
    result: dict[str, Any] = {
        "robots": cfg.robots,
        "load": cfg.load,
        "mapper_processes": cfg.mapper_processes,
    }
    try:
        service = procs.start(
            "service",
            service_command(
                http_port, data_dir, service_ep, cfg.mapper_processes, cfg.loop_closure
            ),
            work_dir,
            stdout=subprocess.DEVNULL,
        )
        client = httpx.Client(base_url=base, timeout=20.0)

        def healthy() -> bool:
            if service.poll() is not None:
                raise BenchError(f"the service exited with {service.returncode}; see its log")
            try:
                return client.get("/health").status_code == 200
            except httpx.HTTPError:
                return False

        _wait_until(healthy, 60.0, "the service did not answer /health")
        log.debug("service healthy")
        sessions = {}
        for r in robots:
            resp = client.post("/sessions", json={"robot_id": r})
            if resp.status_code != 201:
                raise BenchError(f"POST /sessions for {r}: {resp.status_code} {resp.text[:200]}")
            sessions[r] = resp.json()["id"]
        fan = None
        fanout_out = work_dir / f"{name}-fanout.json"
        if cfg.sse_clients or cfg.zenoh_pose_subscribers:
            fan = procs.start(
                "fanout-clients",
                [
                    sys.executable,
                    "-m",
                    "bench.fanout_clients",
                    "--server",
                    base,
                    "--sessions",
                    ",".join(sessions.values()),
                    "--sse",
                    str(cfg.sse_clients),
                    "--zenoh-connect",
                    service_ep,
                    "--zenoh-subscribers",
                    str(cfg.zenoh_pose_subscribers),
                    "--out",
                    str(fanout_out),
                    *(
                        ["--via-router", f"tcp/127.0.0.1:{free_port()}"]
                        if cfg.zenoh_via_router
                        else []
                    ),
                ],
                work_dir,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
            )
            _wait_line(fan, "ready", 180.0, "the fan-out clients")
            log.debug("fan-out clients ready")
        sub = procs.start(
            "subscriber",
            [
                sys.executable,
                "-m",
                "bench.subscriber",
                "--listen",
                sub_ep,
                "--connect",
                service_ep,
                "--out",
                str(rec_path),
            ],
            work_dir,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        _wait_line(sub, "ready", 60.0, "the measuring subscriber")
        log.debug("subscriber ready")
        load_procs: list[subprocess.Popen[str]] = []
        if cfg.load == "agents":
            for r in robots:
                load_procs.append(
                    procs.start(
                        f"agent-{r}",
                        [
                            str(BIN / "sensor-agent"),
                            "--robot-id",
                            r,
                            "--emulate",
                            "--world-seed",
                            str(seed),
                            "--zenoh-connect",
                            service_ep,
                            "--zenoh-connect",
                            sub_ep,
                        ],
                        work_dir,
                        stdout=subprocess.DEVNULL,
                    )
                )
        elif cfg.load == "loadgen":
            gen = procs.start(
                "loadgen",
                [
                    sys.executable,
                    "-m",
                    "bench.loadgen",
                    "--robots",
                    ",".join(robots),
                    "--connect",
                    service_ep,
                    "--connect",
                    sub_ep,
                    "--rate",
                    str(RATE_HZ),
                    "--seed",
                    str(seed),
                    "--out",
                    str(loadgen_out),
                    "--path-scans",
                    str(cfg.path_scans),
                ],
                work_dir,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
            )
            _wait_line(gen, "ready", 120.0, "the load generator")
            log.debug("load generator ready")
            load_procs.append(gen)
        else:
            raise BenchError(f"unknown load {cfg.load!r}")

        def all_mapping() -> bool:
            for p in load_procs:
                if p.poll() is not None:
                    raise BenchError(f"a load process exited with {p.returncode}; see its log")
            if service.poll() is not None:
                raise BenchError(f"the service exited with {service.returncode}; see its log")
            try:
                resp = client.get("/sessions")
            except httpx.HTTPError:
                return False  # busy; ask again
            if resp.status_code != 200:
                return False
            return all(int(s.get("poses", 0)) > 0 for s in resp.json()["sessions"])

        t_start = time.monotonic()
        _wait_until(all_mapping, cfg.startup_timeout_s, "not every session got poses", 0.5)
        result["startup_s"] = time.monotonic() - t_start
        log.debug("every session has poses after %.1f s", result["startup_s"])
        time.sleep(cfg.warmup_s)  # let start-up transients (imports, first keyframes) settle

        svc = psutil.Process(service.pid)
        load_ps = [psutil.Process(p.pid) for p in load_procs]
        # The fan-out clients count as subscribers: CPU on the same cores, not the service's.
        sub_ps = [psutil.Process(sub.pid)] + ([psutil.Process(fan.pid)] if fan else [])
        metrics0 = _scrape(client)
        result["loadavg_before"] = list(os.getloadavg())
        cpu0 = _cpu_snapshot(svc, load_ps, sub_ps)
        by_proc0 = process_tree_cpu(svc.pid), time.monotonic()
        pids = {
            label: svc.pid if label == "main" else int(label.rsplit("-", 1)[1])
            for label in by_proc0[0]
            if not label.startswith("tracker")
        }
        threads0 = {label: thread_cpu(pid) for label, pid in pids.items()}
        t0_ns, w0 = time.time_ns(), time.monotonic()
        profile = None
        spies: dict[str, tuple[subprocess.Popen[bytes], Path]] = {}
        if cfg.stage_profile:
            for label, pid in pids.items():
                out = work_dir / f"{name}-{label}.stacks"
                spy = start_pyspy(pid, min(cfg.profile_s, cfg.measure_s), out)
                if spy is not None:
                    spies[label] = (spy, out)
        with _rss_sampler(svc) as rss:
            if cfg.profile_s > 0 and not cfg.stage_profile:
                profile = pyspy_profile(
                    service.pid,
                    min(cfg.profile_s, cfg.measure_s),
                    f"the service process under {cfg.robots} robots "
                    f"({config_label(cfg.load, cfg.mapper_processes)})",
                )
            time.sleep(max(0.0, cfg.measure_s - (time.monotonic() - w0)))
        t1_ns = time.time_ns()
        cpu1 = _cpu_snapshot(svc, load_ps, sub_ps)
        by_proc1 = process_tree_cpu(svc.pid), time.monotonic()
        threads1 = {label: thread_cpu(pid) for label, pid in pids.items()}
        thread_names = {label: python_thread_names(pid) for label, pid in pids.items()}
        result["loadavg_after"] = list(os.getloadavg())
        metrics1 = _scrape(client)

        # Stop the load, then let the service work off its queues, so that every scan of the
        # window ends up either answered (however late) or discarded.
        _stop_load(load_procs)
        result["drain_s"] = _drain(client, cfg.drain_s, cfg.max_drain_s)
        assert sub.stdin is not None
        sub.stdin.write("stop\n")
        sub.stdin.flush()
        sub.wait(timeout=60)
        if fan is not None and fan.stdin is not None:
            fan.stdin.write("stop\n")
            fan.stdin.flush()
            fan.wait(timeout=60)
            if fanout_out.exists():
                result["fanout"] = json.loads(fanout_out.read_text())
        data = np.load(rec_path)
        names = [str(x) for x in data["robots"]]
        # The subscriber numbers robots in order of appearance; only our robots count.
        result.update(
            analyze(names, data["scans"], data["poses"], t0_ns, t1_ns, expected=len(robots))
        )
        result["subscriber_undecodable"] = int(data["bad"])
        cores = os.cpu_count() or 1

        def pct(name: str) -> float:
            (c0, w0_), (c1, w1_) = cpu0[name], cpu1[name]
            return 100.0 * (c1 - c0) / max(w1_ - w0_, 1e-9)

        result.update(
            {
                "service_cpu_pct": pct("service"),
                "load_cpu_pct": pct("load"),
                "subscriber_cpu_pct": pct("subscriber"),
                "machine_busy_pct": pct("machine") / cores,
                "cores": cores,
                "service_rss_mib_max": max(rss) / 2**20 if rss else math.nan,
                "service_rss_mib_end": rss[-1] / 2**20 if rss else math.nan,
                "metrics_scraped": bool(metrics0) and bool(metrics1),
                "metrics_delta": metrics_delta(metrics0, metrics1),
            }
        )
        delta = result["metrics_delta"]
        count = delta.get("mapping_scan_processing_seconds_count", 0.0)
        result["scan_processing_ms_mean"] = (
            1000.0 * delta.get("mapping_scan_processing_seconds_sum", 0.0) / count
            if count
            else math.nan
        )
        result["stream_poses_dropped"] = delta.get("mapping_pose_stream_dropped_total", 0.0)
        accepted = delta.get("mapping_scans_accepted_total", 0.0)
        span_s = max(by_proc1[1] - by_proc0[1], 1e-9)
        used = {
            k: by_proc1[0][k] - by_proc0[0][k]
            for k in by_proc1[0]
            if k in by_proc0[0] and not k.startswith("tracker")
        }
        result["scans_accepted_in_window"] = accepted
        result["cpu_pct_by_process"] = {k: 100.0 * v / span_s for k, v in used.items()}
        result["cpu_ms_per_scan_by_process"] = {
            k: 1000.0 * v / accepted if accepted else math.nan for k, v in used.items()
        }
        result["cpu_ms_per_scan_by_thread"] = {
            label: {
                t: 1000.0 * v / accepted if accepted else math.nan
                for t, v in thread_split(
                    threads0[label], threads1[label], thread_names[label]
                ).items()
            }
            for label in pids
            if label in threads1
        }
        shares = {}
        for label, (spy, out) in spies.items():
            with contextlib.suppress(subprocess.TimeoutExpired):
                spy.wait(timeout=60)
            if out.exists():
                shares[label] = stage_shares(out.read_text())
        if shares:
            result["stage_shares"] = shares
        result["loop_closures"] = {
            kind: sum(
                v
                for k, v in (metrics1 or {}).items()
                if k.startswith(f"mapping_loop_closures_{kind}")
            )
            for kind in ("accepted", "rejected")
        }
        if profile is not None:
            result["profile"] = profile.as_dict()
    finally:
        log.debug("stopping")
        procs.stop_all()
        log.debug("stopped")
        shutil.rmtree(data_dir, ignore_errors=True)
    if loadgen_out.exists():
        result["loadgen"] = json.loads(loadgen_out.read_text())
    return result


def meets_target(p: dict[str, Any]) -> bool:
    """Zero drops, p99 within the target, and the load really ran at (nearly) 40 Hz."""
    return (
        "error" not in p
        and p["dropped"] == 0
        and p["latency_p99_ms"] <= TARGET_P99_MS
        and p["publish_rate_min_robot_hz"] >= 0.95 * RATE_HZ
    )


def config_label(load: str, mapper_processes: int) -> str:
    """How the report names one (load, service configuration) pair."""
    who = "emulated agents" if load == "agents" else "one-process load generator"
    if mapper_processes:
        return f"{who}; service with {mapper_processes} mapper processes"
    return f"{who}; estimators in the service's process"


def scale_targets(points: Sequence[dict[str, Any]]) -> list[Target]:
    """The issue's target, judged on each load and service configuration at N ≥ 10 robots."""
    targets: list[Target] = []
    configs = sorted({(p["load"], p["mapper_processes"]) for p in points}, key=_config_order)
    for load, k in configs:
        mine = [p for p in points if (p["load"], p["mapper_processes"]) == (load, k)]
        big = [p for p in mine if p["robots"] >= TARGET_ROBOTS]
        label = config_label(load, k)
        name = f"≥ {TARGET_ROBOTS} robots × 40 Hz, zero drops, p99 ≤ {TARGET_P99_MS:g} ms ({label})"
        target = f"{TARGET_ROBOTS} robots: 0 dropped, p99 ≤ {TARGET_P99_MS:g} ms"
        passing = [p["robots"] for p in mine if meets_target(p)]
        best = f"; met up to N={max(passing)}" if passing else "; met at no N measured"
        if not big:
            n_max = max(p["robots"] for p in mine)
            targets.append(Target(name, target, f"not run (N ≤ {n_max}){best}", None))
            continue
        p = min(big, key=lambda q: q["robots"])
        if "error" in p:
            targets.append(Target(name, target, f"N={p['robots']}: {p['error']}", False))
            continue
        measured = (
            f"N={p['robots']}: {p['dropped']} dropped of {p['scans_published']}, "
            f"p99 {p['latency_p99_ms']:.1f} ms, load at "
            f"{p['publish_rate_per_robot_hz']:.1f} Hz/robot{best}"
        )
        targets.append(Target(name, target, measured, meets_target(p)))
    return targets


def _config_order(config: tuple[str, int]) -> tuple[int, int]:
    load, k = config
    return (0 if load == "agents" else 1, -k)


def run_scale(
    robot_counts: Sequence[int],
    loads: Sequence[str],
    *,
    mapper_processes: int,
    in_process_counts: Sequence[int],
    warmup_s: float,
    measure_s: float,
    work_dir: Path,
    drain_s: float = 2.0,
    profile_on_miss: bool = True,
) -> dict[str, Any]:
    """Every load at every N with `mapper_processes`, then the load generator at
    `in_process_counts` with the estimators in the service's process, for comparison."""
    configs = [(load, n, mapper_processes) for load in loads for n in robot_counts]
    if mapper_processes:
        configs += [("loadgen", n, 0) for n in in_process_counts]
    points: list[dict[str, Any]] = []
    for load, n, k in configs:
        cfg = ScaleConfig(n, load, k, warmup_s, measure_s, drain_s)
        log.info("scale: %d robots, %s, %d mapper processes, %.0f s window", n, load, k, measure_s)
        try:
            points.append(run_point(cfg, work_dir / f"{load}-{n}-k{k}"))
        except BenchError as err:
            log.error("scale run %d robots (%s, k=%d) failed: %s", n, load, k, err)
            points.append({"robots": n, "load": load, "mapper_processes": k, "error": str(err)})
    targets = scale_targets(points)
    result: dict[str, Any] = {
        "rate_hz": RATE_HZ,
        "warmup_s": warmup_s,
        "measure_s": measure_s,
        "drain_s": drain_s,
        "mapper_processes": mapper_processes,
        "points": points,
        "targets": [t.as_dict() for t in targets],
    }
    missed = [
        p
        for p in points
        if "error" not in p and p["robots"] >= TARGET_ROBOTS and not meets_target(p)
    ]
    if profile_on_miss and missed:
        # Profile the service in a run of its own (py-spy slows the process it samples), with
        # the lighter load, at the smallest N that missed, in the configuration that missed.
        worst = min(missed, key=lambda p: (p["robots"], -p["mapper_processes"]))
        n, k = worst["robots"], worst["mapper_processes"]
        cfg = ScaleConfig(n, "loadgen", k, warmup_s, max(measure_s, 10.0), drain_s, profile_s=10.0)
        try:
            prof_run = run_point(cfg, work_dir / f"profile-{n}-k{k}")
            result["profile"] = prof_run.get("profile")
        except BenchError as err:
            log.error("profiling run failed: %s", err)
    return result
