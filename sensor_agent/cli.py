"""`sensor-agent`: publish laser scans from a UTM-30LX, its emulator, or a log over Zenoh.

    sensor-agent --robot-id ID (--device PORT_OR_URL | --emulate [--world-seed N]
                 | --replay FILE [--rate X]) [--zenoh-connect ENDPOINT]...
                 [--zenoh-listen ENDPOINT]... [--zenoh-config FILE] [--prefix robots]

Exit codes: 0 after a clean stop (SIGINT/SIGTERM, or the end of a replay), 1 when the source
or Zenoh cannot be started (one line on stderr says why), 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType

from clients.keyexpr import DEFAULT_PREFIX, InvalidPrefixError, check_prefix
from clients.wire import InvalidRobotIdError, check_robot_id
from sensor_agent.errors import SensorAgentError

log = logging.getLogger("sensor_agent")


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
    src.add_argument(
        "--replay",
        metavar="FILE",
        help="ROS 1 bag, ROS 2 bag folder (SQLite or MCAP storage), .mcap file or .mrec "
        "recording to replay",
    )
    parser.add_argument("--world-seed", type=int, default=1, help="emulated building (default: 1)")
    parser.add_argument(
        "--rate",
        type=float,
        default=1.0,
        help="replay speed factor; 0 = as fast as possible (default: %(default)s)",
    )
    parser.add_argument(
        "--zenoh-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh router or service to connect to, e.g. tcp/server:7447 (repeatable)",
    )
    parser.add_argument(
        "--zenoh-listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to accept Zenoh peers on, e.g. tcp/0.0.0.0:7448 (repeatable)",
    )
    parser.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="Zenoh JSON5 config file, e.g. TLS and user/password (docs/service.md, "
        "'Securing Zenoh')",
    )
    parser.add_argument(
        "--zenoh-mode",
        choices=("peer", "client", "router"),
        default="peer",
        help="Zenoh mode without --zenoh-config (default: %(default)s)",
    )
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help="default: %(default)s")
    parser.add_argument(
        "--intensity", action="store_true", help="device/emulator: stream ME (with intensities)"
    )
    parser.add_argument(
        "--stats-interval",
        type=float,
        default=10.0,
        metavar="S",
        help="seconds between summary lines; 0 = none (default: %(default)s)",
    )
    faults = parser.add_argument_group("emulator faults (with --emulate)")
    faults.add_argument(
        "--fault-corrupt-lines",
        type=float,
        default=0.0,
        metavar="P",
        help="probability that a line's checksum is corrupted",
    )
    faults.add_argument(
        "--fault-garbage",
        type=float,
        default=0.0,
        metavar="P",
        help="probability of random bytes before a scan",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0)
    return parser


def _validate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    try:
        check_robot_id(args.robot_id)
        check_prefix(args.prefix)
    except (InvalidRobotIdError, InvalidPrefixError) as err:
        parser.error(str(err))
    if args.rate < 0:
        parser.error("--rate must be >= 0 (0 = as fast as possible)")
    for name in ("fault_corrupt_lines", "fault_garbage"):
        value = getattr(args, name)
        if not 0.0 <= value <= 1.0:
            parser.error(f"--{name.replace('_', '-')} must be within [0, 1]")
        if value and not args.emulate:
            parser.error(f"--{name.replace('_', '-')} needs --emulate")


def _configure_logging(verbose: int) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def _fail(message: str) -> int:
    sys.stderr.write(f"sensor-agent: error: {message}\n")
    return 1


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _validate(parser, args)
    _configure_logging(args.verbose)

    # Imported here so that `--help` and argument errors stay fast.
    import zenoh  # noqa: PLC0415

    from clients.zenoh_config import build_zenoh_config  # noqa: PLC0415
    from sensor_agent.agent import Agent  # noqa: PLC0415
    from sensor_agent.driver import DriverConfig  # noqa: PLC0415
    from sensor_agent.emulator import FaultConfig  # noqa: PLC0415
    from sensor_agent.publisher import ScanPublisher  # noqa: PLC0415
    from sensor_agent.sources import (  # noqa: PLC0415
        DeviceSource,
        EmulatorSource,
        ReplaySource,
        ScanSource,
    )

    try:
        driver_config = DriverConfig(intensity=args.intensity)
        source: ScanSource
        if args.device:
            source = DeviceSource(args.device, args.robot_id, driver_config)
        elif args.emulate:
            faults = FaultConfig(args.fault_corrupt_lines, args.fault_garbage, seed=args.world_seed)
            source = EmulatorSource(
                args.robot_id, world_seed=args.world_seed, faults=faults, config=driver_config
            )
        else:
            source = ReplaySource(args.replay, args.robot_id, rate=args.rate)
        conf = build_zenoh_config(
            mode=args.zenoh_mode,
            listen=args.zenoh_listen,
            connect=args.zenoh_connect,
            config_file=args.zenoh_config,
        )
    except SensorAgentError as err:
        return _fail(str(err))
    except (zenoh.ZError, OSError, ValueError) as err:
        return _fail(f"zenoh configuration: {err}")

    stop = threading.Event()

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        log.info("%s: stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        source.open()  # before Zenoh: a wrong port fails at once with one line
        with (
            zenoh.open(conf) as session,
            ScanPublisher(session, args.robot_id, args.prefix) as publisher,
        ):
            Agent(source, publisher, stats_interval_s=args.stats_interval).run(stop)
    except SensorAgentError as err:
        return _fail(str(err))
    except zenoh.ZError as err:
        return _fail(f"zenoh: {err}")
    finally:
        source.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
