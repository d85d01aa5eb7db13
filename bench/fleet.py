"""Section 5: a fleet on one box. N robots × 40 Hz from the load generator (its own process) into
one `mapping-service serve --mapper-processes K`, and the fan-out benchmark.

- Capacity: N = 10, 25, 40 (full mode). Beside each point: dropped, p50/p99 scan→pose, the
  service's CPU (its process tree: mapper processes included), the machine's CPU and its load
  average, since this machine is shared and a busy neighbour moves every figure.
- Fan-out: 10 robots × 40 Hz, alone and with 1,000 SSE streams and 50 Zenoh pose subscribers
  (`bench.fanout_clients`, one process; the subscribers behind one Zenoh router in that
  process, as docs/architecture.md lays out a site, so the service sends each pose once and
  the router makes the 50 copies), run alternately so that the pairs share the machine's
  conditions. Judged on the service's per-scan time (`mapping_scan_processing_seconds`: decode,
  record, estimate, publish), the p99 scan→pose and drops.

The measuring machinery (processes, subscriber, analysis) is bench/scale.py's `run_point`.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench.common import BenchError, Target
from bench.scale import RATE_HZ, ScaleConfig, run_point

log = logging.getLogger(__name__)

TARGET_ROBOTS = 25
TARGET_P99_MS = 20.0
FANOUT_ROBOTS = 10
FANOUT_SSE = 1000
FANOUT_ZENOH = 50
FANOUT_TOLERANCE = 0.20  # per-scan time and p99 within 20 % of the run without subscribers


def _point(cfg: ScaleConfig, work_dir: Path) -> dict[str, Any]:
    try:
        return run_point(cfg, work_dir)
    except BenchError as err:
        log.error("fleet run (%d robots) failed: %s", cfg.robots, err)
        return {"robots": cfg.robots, "mapper_processes": cfg.mapper_processes, "error": str(err)}


def _ok(p: dict[str, Any]) -> bool:
    return "error" not in p


def fleet_targets(
    capacity: Sequence[dict[str, Any]], fanout: Sequence[dict[str, Any]]
) -> list[Target]:
    targets: list[Target] = []
    at = [p for p in capacity if p["robots"] == TARGET_ROBOTS]
    name = f"{TARGET_ROBOTS} robots × 40 Hz on one box: 0 dropped, p99 ≤ {TARGET_P99_MS:g} ms"
    goal = f"0 dropped, p99 ≤ {TARGET_P99_MS:g} ms"
    if not at:
        targets.append(Target(name, goal, "not run", None))
    elif not _ok(at[0]):
        targets.append(Target(name, goal, at[0]["error"], False))
    else:
        p = at[0]
        passed = p["dropped"] == 0 and p["latency_p99_ms"] <= TARGET_P99_MS
        measured = (
            f"{p['dropped']} dropped of {p['scans_published']}, p99 {p['latency_p99_ms']:.1f} ms "
            f"(load average {p.get('loadavg_before', [math.nan])[0]:.1f})"
        )
        targets.append(Target(name, goal, measured, passed))
    name = (
        f"fan-out: {FANOUT_SSE} SSE + {FANOUT_ZENOH} Zenoh subscribers, {FANOUT_ROBOTS} robots: "
        f"per-scan time and p99 within {FANOUT_TOLERANCE:.0%}, 0 dropped"
    )
    goal = f"ratios ≤ {1 + FANOUT_TOLERANCE:.2f}, 0 dropped"
    pairs = fanout_pairs(fanout)
    if not pairs:
        targets.append(Target(name, goal, "not run", None))
    else:
        scan_ratio = _median([r["scan_ratio"] for r in pairs])
        p99_ratio = _median([r["p99_ratio"] for r in pairs])
        dropped = sum(r["dropped_with"] for r in pairs)
        passed = (
            scan_ratio <= 1 + FANOUT_TOLERANCE and p99_ratio <= 1 + FANOUT_TOLERANCE and not dropped
        )
        measured = (
            f"per-scan ×{scan_ratio:.2f}, p99 ×{p99_ratio:.2f}, {dropped} dropped with "
            f"subscribers (median of {len(pairs)} pair(s))"
        )
        targets.append(Target(name, goal, measured, passed))
    return targets


def _median(values: Sequence[float]) -> float:
    ordered = sorted(values)
    if not ordered:
        return math.nan
    mid = len(ordered) // 2
    return ordered[mid] if len(ordered) % 2 else (ordered[mid - 1] + ordered[mid]) / 2


def fanout_pairs(fanout: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """(without, with) runs in the order they ran, as ratios."""
    out = []
    for i in range(0, len(fanout) - 1, 2):
        base, loaded = fanout[i], fanout[i + 1]
        if not (_ok(base) and _ok(loaded)):
            continue
        out.append(
            {
                "scan_ms_without": base["scan_processing_ms_mean"],
                "scan_ms_with": loaded["scan_processing_ms_mean"],
                "scan_ratio": loaded["scan_processing_ms_mean"] / base["scan_processing_ms_mean"],
                "p99_without": base["latency_p99_ms"],
                "p99_with": loaded["latency_p99_ms"],
                "p99_ratio": loaded["latency_p99_ms"] / base["latency_p99_ms"],
                "dropped_without": base["dropped"],
                "dropped_with": loaded["dropped"],
            }
        )
    return out


def run_fleet(
    robot_counts: Sequence[int],
    *,
    mapper_processes: int,
    warmup_s: float,
    measure_s: float,
    work_dir: Path,
    fanout_pairs_count: int = 1,
    drain_s: float = 2.0,
) -> dict[str, Any]:
    capacity = []
    for n in robot_counts:
        log.info("fleet: %d robots × %g Hz, %d mapper processes", n, RATE_HZ, mapper_processes)
        cfg = ScaleConfig(n, "loadgen", mapper_processes, warmup_s, measure_s, drain_s)
        capacity.append(_point(cfg, work_dir / f"capacity-{n}"))
    fanout = []
    for rep in range(fanout_pairs_count):
        for sse, zs in ((0, 0), (FANOUT_SSE, FANOUT_ZENOH)):
            log.info(
                "fleet: fan-out %d robots, %d SSE, %d Zenoh subscribers", FANOUT_ROBOTS, sse, zs
            )
            cfg = ScaleConfig(
                FANOUT_ROBOTS,
                "loadgen",
                mapper_processes,
                warmup_s,
                measure_s,
                drain_s,
                sse_clients=sse,
                zenoh_pose_subscribers=zs,
            )
            point = _point(cfg, work_dir / f"fanout-{rep}-{sse}")
            point.update(sse_clients=sse, zenoh_pose_subscribers=zs)
            fanout.append(point)
    return {
        "rate_hz": RATE_HZ,
        "mapper_processes": mapper_processes,
        "warmup_s": warmup_s,
        "measure_s": measure_s,
        "cores": os.cpu_count() or 1,
        "capacity": capacity,
        "fanout": fanout,
        "fanout_pairs": fanout_pairs(fanout),
        "targets": [t.as_dict() for t in fleet_targets(capacity, fanout)],
    }
