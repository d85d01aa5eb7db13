"""`python -m bench.live_backend`: the live back end's cost, loop closure on and off side by side.

1. Front end per scan at 40 Hz (in-process `LocalMapper`, paced on a 25 ms clock so the back
   end's thread runs beside it as it does live): one loop of synthetic building 1 at 2 m/s
   (the closures come back at the start), off / on / off / on, median and p99 of `map_scan`.
2. scan→pose with 10 robots (`bench.scale.run_point`, the load generator driving each robot back
   and forth over the same path, so closures are searched all the time): p50/p99 and drops,
   `serve --no-loop-closure` against `serve`, with the closures searched and accepted; with
   `--mapper-processes K`, the service runs its estimators and back ends in K processes.

Writes bench/out/live_backend.json and prints a summary. A benchmark, not a test: the numbers
depend on the machine and what else runs on it.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("bench.live_backend")


def frontend_run(loop_closure: bool, scans: list[Any]) -> dict[str, Any]:
    from service.app.mapper import Engine, LocalMapper

    mapper = LocalMapper(Engine(loop_closure=loop_closure), False, 0.05)
    times: list[float] = []
    start = time.perf_counter()
    for i, scan in enumerate(scans):
        due = start + i * 0.025
        wait = due - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        t0 = time.perf_counter()
        mapper.map_scan(scan, None, i)
        times.append(time.perf_counter() - t0)
    mapper.wait_backend(120)
    graph = mapper.graph()
    mapper.close()
    ms = np.asarray(times) * 1e3
    return {
        "loop_closure": loop_closure,
        "scans": len(scans),
        "median_ms": round(float(np.median(ms)), 3),
        "p99_ms": round(float(np.percentile(ms, 99)), 3),
        "max_ms": round(float(ms.max()), 3),
        "closures_accepted": graph.accepted if graph is not None else None,
        "closures_rejected": dict(graph.rejected) if graph is not None else None,
        "map_chunk_bytes": graph.map_bytes if graph is not None else None,
    }


def loop_scans(seed: int = 1, speed_mps: float = 2.0) -> list[Any]:
    from bench.common import REPO_ROOT  # noqa: F401  # the repo on the path
    from clients.wire import Scan
    from sensor_agent.sim import LaserModel, RobotMotion, generate_building, simulate_scan

    world = generate_building(seed, "small")
    motion = RobotMotion(world, seed, speed_mps=speed_mps)
    model = LaserModel.utm30lx()
    rng = np.random.default_rng(seed)
    n = int(motion.loop_period_s / 0.025) + 40
    out = []
    for k in range(n):
        sample = simulate_scan(world, motion.pose_at(k * 0.025), model, rng)
        out.append(
            Scan(
                robot_id="bench",
                seq=k,
                sensor_stamp_ns=k * 25_000_000,
                host_stamp_ns=k * 25_000_000,
                angle_min_rad=model.angle_min_rad,
                angle_increment_rad=model.angle_increment_rad,
                range_min_m=model.range_min_m,
                range_max_m=model.range_max_m,
                ranges_m=np.nan_to_num(sample.ranges_m, nan=0.0),
            )
        )
    return out


def fleet_run(  # noqa: PLR0917 - one benchmark point's settings
    loop_closure: bool,
    robots: int,
    work_dir: Path,
    warmup_s: float,
    measure_s: float,
    mapper_processes: int = 0,
) -> dict[str, Any]:
    from bench.scale import ScaleConfig, run_point

    cfg = ScaleConfig(
        robots, "loadgen", mapper_processes, warmup_s, measure_s, loop_closure=loop_closure
    )
    name = f"{'lc-on' if loop_closure else 'lc-off'}-k{mapper_processes}"
    point = run_point(cfg, work_dir / name)
    keys = (
        "scans_published",
        "dropped",
        "latency_p50_ms",
        "latency_p99_ms",
        "loop_closures",
        "service_cpu_pct",
        "machine_busy_pct",
    )
    return {
        "loop_closure": loop_closure,
        "mapper_processes": mapper_processes,
        **{k: point.get(k) for k in keys},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.live_backend", description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("bench/out"))
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--measure-s", type=float, default=20.0)
    parser.add_argument(
        "--warmup-s",
        type=float,
        default=40.0,
        help="before measuring: the robots' graphs need ~60 nodes before the search starts",
    )
    parser.add_argument(
        "--mapper-processes",
        type=int,
        default=0,
        help="the service's --mapper-processes for the fleet part (0: estimators in its process)",
    )
    parser.add_argument("--pairs", type=int, default=3, help="front-end runs off/on, alternated")
    parser.add_argument("--skip-fleet", action="store_true", help="the front-end part only")
    parser.add_argument("--skip-frontend", action="store_true", help="the fleet part only")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {}
    out = args.out / "live_backend.json"
    if not args.skip_frontend:
        scans = loop_scans()
        frontend = [frontend_run(on, scans) for _ in range(args.pairs) for on in (False, True)]
        for r in frontend:
            log.info("front end at 40 Hz: %s", r)
        off = float(np.median([r["median_ms"] for r in frontend if not r["loop_closure"]]))
        on = float(np.median([r["median_ms"] for r in frontend if r["loop_closure"]]))
        result["frontend_40hz"] = frontend
        result["frontend_median_ratio_on_off"] = round(on / off, 3)
        out.write_text(json.dumps(result, indent=2) + "\n")  # kept if the fleet part fails
    if not args.skip_fleet:
        result["fleet"] = [
            fleet_run(
                on,
                args.robots,
                args.out / "live_backend",
                args.warmup_s,
                args.measure_s,
                args.mapper_processes,
            )
            for on in (False, True)
        ]
        for r in result["fleet"]:
            log.info("%d robots: %s", args.robots, r)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))  # a command's output
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
