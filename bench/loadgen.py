"""A light load generator: N robots' scans at 40 Hz each, from one process (scale benchmark).

`python -m bench.loadgen --robots r0,r1 --connect EP [--connect EP2] --out FILE.json`

The real agent path (emulated UTM-30LX on a pty, driver, publisher) costs one Python process per
robot; on a small machine N of them compete with the service for the CPU. This generator
pre-simulates the scans once and publishes them for every robot on the wire, each robot at its own
phase of the 25 ms period, so that the service's own capacity can be measured. Every robot drives
the first metres of the simulator's robot motion (about 0.7 m/s) back and forth, without jumps,
from its own starting point. It stops on `stop` on stdin.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import zenoh

from bench.common import simulate_scans
from clients.keyexpr import DEFAULT_PREFIX, scan_key
from clients.wire import Scan, encode_scan
from clients.zenoh_config import build_zenoh_config
from service.core.types import LaserScan

log = logging.getLogger(__name__)


def pingpong_index(k: int, n: int) -> int:
    """0, 1, ..., n-1, n-2, ..., 1, 0, 1, ... for a path of `n` poses driven back and forth."""
    if n <= 1:
        return 0
    period = 2 * (n - 1)
    k %= period
    return k if k < n else period - k


def path_scans(seed: int, count: int, period_s: float) -> list[LaserScan]:
    """`count` scans along the simulator's continuous robot motion, one every `period_s`."""
    from sensor_agent.sim import world as sim

    building = sim.generate_building(seed)
    t_s = np.arange(count, dtype=np.float64) * period_s
    poses = sim.RobotMotion(building, seed).poses_at(t_s)
    stamps_ns = np.rint(t_s * 1e9).astype(np.int64)
    return simulate_scans(building, poses, stamps_ns, seed)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.loadgen")
    parser.add_argument("--robots", required=True, help="comma-separated robot ids")
    parser.add_argument("--connect", action="append", default=[])
    parser.add_argument("--prefix", default=DEFAULT_PREFIX)
    parser.add_argument("--rate", type=float, default=40.0, help="scans/s per robot")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--path-scans", type=int, default=400, help="scans simulated once")
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--max-duration", type=float, default=900.0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    robots = [r for r in args.robots.split(",") if r]
    period_s = 1.0 / args.rate
    scans = path_scans(args.seed, args.path_scans, period_s)
    n_path = len(scans)
    stop = threading.Event()

    def wait_stdin() -> None:
        for line in sys.stdin:
            if line.strip() == "stop":
                break
        stop.set()

    threading.Thread(target=wait_stdin, daemon=True).start()
    published = dict.fromkeys(robots, 0)
    late = 0
    conf = build_zenoh_config(connect=args.connect)
    with zenoh.open(conf) as session:
        pubs = {r: session.declare_publisher(scan_key(r, args.prefix)) for r in robots}
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        start = time.monotonic() + 0.2
        deadline = start + args.max_duration
        # Every robot publishes at its own phase; offsets along the path differ per robot.
        phases = [i / len(robots) * period_s for i in range(len(robots))]
        offsets = [(i * 37) % n_path for i in range(len(robots))]
        tick = 0
        while not stop.is_set() and time.monotonic() < deadline:
            for i, robot_id in enumerate(robots):
                due = start + tick * period_s + phases[i]
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                elif delay < -period_s:
                    late += 1
                src = scans[pingpong_index(tick + offsets[i], n_path)]
                now_ns = time.time_ns()
                scan = Scan(
                    robot_id=robot_id,
                    seq=tick,
                    sensor_stamp_ns=now_ns,
                    host_stamp_ns=now_ns,
                    angle_min_rad=src.angle_min_rad,
                    angle_increment_rad=src.angle_increment_rad,
                    range_min_m=src.range_min_m,
                    range_max_m=src.range_max_m,
                    ranges_m=src.ranges_m,
                )
                pubs[robot_id].put(encode_scan(scan))
                published[robot_id] += 1
            tick += 1
        elapsed = time.monotonic() - start
    summary = {
        "robots": robots,
        "published": published,
        "late_more_than_one_period": late,
        "elapsed_s": elapsed,
        "rate_per_robot_hz": float(np.mean(list(published.values()))) / max(elapsed, 1e-9),
    }
    args.out.write_text(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
