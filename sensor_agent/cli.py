"""`sensor-agent`: publish laser scans from a UTM-30LX, its emulator, or a log over Zenoh."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from clients.keyexpr import DEFAULT_PREFIX


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sensor-agent",
        description="Read a Hokuyo UTM-30LX (SCIP 2.0), its emulator, or a recording, and publish "
        "every scan on <prefix>/<robot-id>/scan over Zenoh.",
    )
    parser.add_argument("--robot-id", required=True, help="this robot's id, e.g. amr-07")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--device",
        metavar="PORT_OR_URL",
        help="serial port or pyserial URL: /dev/ttyACM0, socket://192.168.0.10:10940",
    )
    src.add_argument("--emulate", action="store_true", help="run the built-in UTM-30LX emulator")
    src.add_argument("--replay", metavar="FILE", help="ROS 1/2 bag or .mrec recording to replay")
    parser.add_argument("--world-seed", type=int, default=1, help="emulated building (default: 1)")
    parser.add_argument(
        "--rate",
        type=float,
        default=1.0,
        help="replay speed factor; 0 = as fast as possible (default: %(default)s)",
    )
    parser.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT")
    parser.add_argument("--zenoh-listen", action="append", default=[], metavar="ENDPOINT")
    parser.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file")
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help="default: %(default)s")
    parser.add_argument("-v", "--verbose", action="count", default=0)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    build_parser().parse_args(argv)
    return 2


if __name__ == "__main__":
    sys.exit(main())
