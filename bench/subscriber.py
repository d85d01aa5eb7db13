"""Measuring subscriber for the scale benchmark (a process of its own).

`python -m bench.subscriber --listen EP --connect SERVICE_EP --out FILE.npz`

Agents connect to this process as well as to the service, so it sees every published scan
(their `host_stamp_ns`, the agent's publish time) and, from the service, every pose (whose
`stamp_ns` is the scan's stamp). It records the arrival time of each and writes them out when it
reads `stop` on stdin. Only the stamp is read from a scan (raw msgpack), to keep this cheap.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import msgpack
import numpy as np
import zenoh

from clients.keyexpr import DEFAULT_PREFIX, pose_wildcard, robot_id_from_key, scan_wildcard
from clients.wire import DecodeError, decode_pose
from clients.zenoh_config import build_zenoh_config

log = logging.getLogger(__name__)


class Recorder:
    """Appends (robot index, stamp_ns, arrival_ns) rows from Zenoh callback threads."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.robots: dict[str, int] = {}
        self.scans: list[tuple[int, int, int]] = []
        self.poses: list[tuple[int, int, int]] = []
        self.bad = 0
        self._lock = threading.Lock()

    def _robot(self, robot_id: str) -> int:
        with self._lock:
            return self.robots.setdefault(robot_id, len(self.robots))

    def on_scan(self, sample: zenoh.Sample) -> None:
        now_ns = time.time_ns()
        robot_id = robot_id_from_key(str(sample.key_expr), self.prefix)
        try:
            stamp_ns = int(msgpack.unpackb(sample.payload.to_bytes())["host_stamp_ns"])
        except Exception:  # anything unreadable is counted, never raised into Zenoh
            self.bad += 1
            return
        if robot_id is not None:
            self.scans.append((self._robot(robot_id), stamp_ns, now_ns))

    def on_pose(self, sample: zenoh.Sample) -> None:
        now_ns = time.time_ns()
        try:
            pose = decode_pose(sample.payload.to_bytes())
        except DecodeError:
            self.bad += 1
            return
        self.poses.append((self._robot(pose.robot_id), pose.stamp_ns, now_ns))

    def save(self, path: Path) -> None:
        names = sorted(self.robots, key=self.robots.__getitem__)
        np.savez(
            path,
            robots=np.array(names, dtype=str),
            scans=np.array(self.scans, dtype=np.int64).reshape(-1, 3),
            poses=np.array(self.poses, dtype=np.int64).reshape(-1, 3),
            bad=np.array(self.bad),
        )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.subscriber")
    parser.add_argument("--listen", action="append", default=[])
    parser.add_argument("--connect", action="append", default=[])
    parser.add_argument("--prefix", default=DEFAULT_PREFIX)
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--max-duration", type=float, default=900.0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    rec = Recorder(args.prefix)
    conf = build_zenoh_config(listen=args.listen, connect=args.connect)
    with zenoh.open(conf) as session:
        # Callback subscribers live until the session closes (end of the `with` block).
        session.declare_subscriber(scan_wildcard(args.prefix), rec.on_scan)
        session.declare_subscriber(pose_wildcard(args.prefix), rec.on_pose)
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        stop = threading.Event()

        def wait_stdin() -> None:
            for line in sys.stdin:
                if line.strip() == "stop":
                    break
            stop.set()

        threading.Thread(target=wait_stdin, daemon=True).start()
        stop.wait(args.max_duration)
    rec.save(args.out)
    sys.stdout.write(f"done {len(rec.scans)} scans {len(rec.poses)} poses\n")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
