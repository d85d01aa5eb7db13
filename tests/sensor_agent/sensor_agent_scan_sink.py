"""A separate subscriber process for the end-to-end tests (not collected by pytest).

    python sensor_agent_scan_sink.py --listen ENDPOINT --out FILE --ready FILE [--prefix robots]

Listens on ENDPOINT, subscribes to `<prefix>/*/scan` and `<prefix>/*/alive` (liveliness), and
appends one record per event to FILE (flushed at once), so that the test can follow along:

    b"S" seq:u64 sensor_stamp_ns:i64 host_stamp_ns:i64 arrival_monotonic_ns:i64 n:u32 ranges:u16[n]
    b"A" / b"D" arrival_monotonic_ns:i64 len:u16 key   (liveliness token appeared / vanished)
    b"E" arrival_monotonic_ns:i64 len:u16 reason       (a payload that did not decode)

Writes FILE --ready once the subscriptions are declared; exits on SIGTERM, closing the session.
"""

from __future__ import annotations

import argparse
import signal
import struct
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from clients.keyexpr import alive_wildcard, scan_wildcard
from clients.wire import DecodeError, decode_scan
from clients.zenoh_config import build_zenoh_config

SCAN_HEAD = struct.Struct("<QqqqI")
EVENT_HEAD = struct.Struct("<qH")


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--listen", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--ready", required=True)
    p.add_argument("--prefix", default="robots")
    args = p.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    lock = threading.Lock()
    out = open(args.out, "wb")  # noqa: SIM115

    def write(data: bytes) -> None:
        with lock:
            out.write(data)
            out.flush()

    def on_scan(sample: zenoh.Sample) -> None:
        now = time.monotonic_ns()
        try:
            scan = decode_scan(sample.payload.to_bytes())
        except DecodeError as err:
            reason = err.reason.encode()
            write(b"E" + EVENT_HEAD.pack(now, len(reason)) + reason)
            return
        mm = np.rint(scan.ranges_m * 1000.0).astype("<u2")
        head = SCAN_HEAD.pack(scan.seq, scan.sensor_stamp_ns, scan.host_stamp_ns, now, mm.size)
        write(b"S" + head + mm.tobytes())

    def on_alive(sample: zenoh.Sample) -> None:
        now = time.monotonic_ns()
        kind = b"A" if sample.kind == zenoh.SampleKind.PUT else b"D"
        key = str(sample.key_expr).encode()
        write(kind + EVENT_HEAD.pack(now, len(key)) + key)

    conf = build_zenoh_config(listen=[args.listen])
    with zenoh.open(conf) as session:
        scans = session.declare_subscriber(scan_wildcard(args.prefix), on_scan)
        alive = session.liveliness().declare_subscriber(
            alive_wildcard(args.prefix), on_alive, history=True
        )
        Path(args.ready).write_text("ready\n")
        stop.wait()
        scans.undeclare()
        alive.undeclare()
    out.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
