"""Main-process CPU per scan of the service's per-scan path, in one process, without the estimator.

`python -m bench.mainpath [--mapper-processes K] [--robots N] [--scans M]`

A `MappingRuntime` (isolated Zenoh session) with a null estimator is fed wire payloads through
`Ingest.submit` (what the Zenoh callback calls) at full speed, with N robots interleaved; the
CPU time of this process (every thread) per accepted scan is what the service's own process
spends per scan apart from the estimator: decode, record, the pipe to mapper processes, pose
encode and publish. With K > 0 the null estimator runs in the mapper processes.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import psutil

from clients.keyexpr import scan_key
from clients.zenoh_config import build_zenoh_config
from service.app.mapper import Engine
from service.app.runtime import MappingRuntime
from service.app.settings import IngestSettings, ServiceSettings, StorageSettings
from service.core.types import LaserScan, Pose2D, PoseEstimate


class NullEstimator:
    def process(self, scan: LaserScan) -> PoseEstimate:
        return PoseEstimate(stamp_ns=scan.stamp_ns, pose=Pose2D(0.0, 0.0, 0.0), quality=1.0)

    def reset(self) -> None:
        pass


def null_estimator(use_odometry: bool) -> NullEstimator:
    return NullEstimator()


def main(argv: Sequence[str] | None = None) -> int:
    from bench.loadgen import path_scans, pingpong_index
    from clients.wire import Scan, encode_scan

    parser = argparse.ArgumentParser(prog="python -m bench.mainpath", description=__doc__)
    parser.add_argument("--mapper-processes", type=int, default=2)
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--scans", type=int, default=4000)
    args = parser.parse_args(argv)
    src = path_scans(1, 100, 0.025)
    robots = [f"r{i:02d}" for i in range(args.robots)]
    with tempfile.TemporaryDirectory() as tmp:
        settings = ServiceSettings(
            storage=StorageSettings(data_dir=Path(tmp), fsync_interval_s=1.0),
            ingest=IngestSettings(mapper_processes=args.mapper_processes),
        )
        engine = Engine(make_estimator=null_estimator)  # type: ignore[arg-type]
        with MappingRuntime(settings, engine=engine, zenoh_config=build_zenoh_config()) as rt:
            for r in robots:
                rt.sessions.create(r, 0.05, True)
            payloads = []
            for k in range(args.scans):
                s = src[pingpong_index(k, len(src))]
                r = robots[k % len(robots)]
                payloads.append(
                    (
                        scan_key(r),
                        encode_scan(
                            Scan(
                                r,
                                k,
                                k,
                                time.time_ns(),
                                s.angle_min_rad,
                                s.angle_increment_rad,
                                s.range_min_m,
                                s.range_max_m,
                                s.ranges_m,
                            )
                        ),
                    )
                )
            me = psutil.Process()
            t0, c0 = time.perf_counter(), me.cpu_times()
            for key, payload in payloads:
                while rt.ingest.pending() > 16 * len(robots):
                    time.sleep(0.0005)
                rt.ingest.submit(key, payload)
            while rt.ingest.pending():
                time.sleep(0.001)
            t1, c1 = time.perf_counter(), me.cpu_times()
            n = sum(s.scans_accepted for s in rt.sessions.list())
            user = (c1.user - c0.user) * 1000 / n
            system = (c1.system - c0.system) * 1000 / n
            print(
                f"K={args.mapper_processes} robots={args.robots}: {n} scans, main CPU/scan "
                f"{user + system:.3f} ms (user {user:.3f}, system {system:.3f}), "
                f"wall/scan {(t1 - t0) * 1000 / n:.3f} ms"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
