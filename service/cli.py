"""`mapping-service`: the service's command line (composition root for each subcommand)."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from typing import Any, Final

from clients.keyexpr import DEFAULT_PREFIX

log = logging.getLogger("mapping-service")

# `service.core.slam.FRONT_ENDS` and `DEFAULT_FRONT_END` (its first), spelt out so that the CLI
# and the benchmarks start without importing the core (tests/service/test_offline_cli.py checks).
FRONT_END_CHOICES = ("matcher", "paper")
# The front ends a live session can run (`service.app.store.SESSION_FRONT_ENDS`).
SERVE_FRONT_END_CHOICES = ("matcher",)
DEFAULT_FRONT_END: Final = "matcher"


def _add_zenoh_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument(
        "--zenoh-listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    g.add_argument(
        "--zenoh-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint of a router or peer to connect to (repeatable)",
    )
    g.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="Zenoh JSON5 config file, passed through (TLS, user/password: docs/service.md); "
        "--zenoh-listen replaces its listen endpoints",
    )
    g.add_argument(
        "--prefix",
        default=DEFAULT_PREFIX,
        help="key-expression prefix: scans on <prefix>/<robot>/scan (default: %(default)s)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mapping-service",
        description=(
            "Map buildings from 2D laser scans. `serve` runs the networked service, `map` maps a "
            "recording offline, `export` writes one as MCAP, `demo` runs the service with a "
            "simulated robot, `fsck` checks a data directory."
        ),
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add_command(name: str, **kwargs: Any) -> argparse.ArgumentParser:
        # `-v` after the command too (`serve -v`, as the docs show it): its own dest, because a
        # subparser's default would overwrite the count given before the command.
        p = sub.add_parser(name, **kwargs)
        p.add_argument(
            "-v",
            "--verbose",
            dest="verbose_after",
            action="count",
            default=0,
            help="more log output (-vv: debug)",
        )
        return p

    p_map = add_command(
        "map",
        help="map a ROS 1/2 bag, an MCAP file or a recording offline",
        description="Map a ROS 1 bag, a ROS 2 bag (SQLite or MCAP storage), an MCAP file or one "
        "of our recordings; write trajectory, map and report.",
    )
    p_map.add_argument(
        "input",
        metavar="INPUT",
        help="ROS 1 bag, ROS 2 bag folder, .mcap file (ROS 2 messages), or .mrec file",
    )
    p_map.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p_map.add_argument(
        "--scan-topic", default="/scan", help="LaserScan topic (default: %(default)s)"
    )
    p_map.add_argument(
        "--odom-topic", default="/odom", help="Odometry topic (default: %(default)s)"
    )
    p_map.add_argument("--no-odom", action="store_true", help="ignore odometry even if present")
    p_map.add_argument(
        "--no-loop-closure",
        action="store_true",
        help="the front end alone: no loop search, no pose graph (for comparison)",
    )
    p_map.add_argument(
        "--front-end",
        choices=FRONT_END_CHOICES,
        default=DEFAULT_FRONT_END,
        help="matcher: one scan-to-submap match with the walls' heading as a prior "
        "(docs/estimator.md); paper: the IROS 2010 method as stated, no odometry "
        "(docs/paper-frontend.md) (default: %(default)s)",
    )
    p_map.add_argument(
        "--resolution", type=float, default=0.05, metavar="M", help="map cell size (default: 0.05)"
    )
    p_map.add_argument("--no-progress", action="store_true", help="no progress bar")
    p_map.set_defaults(handler="service.offline:run_map")

    p_export = add_command(
        "export",
        help="write a session or a recording as MCAP (ROS 2 messages)",
        description="Write a session's recording (or a .mrec file) as MCAP with ROS 2 schemas: "
        "/scan sensor_msgs/msg/LaserScan, /pose geometry_msgs/msg/PoseStamped, /tf "
        "tf2_msgs/msg/TFMessage, /map nav_msgs/msg/OccupancyGrid (the final map), stamped "
        "with the scans' stamps. Streams: memory does not grow with the recording's length.",
    )
    p_export.add_argument(
        "source",
        metavar="SESSION_OR_RECORDING",
        help="a session id in --data-dir, or a .mrec recording file",
    )
    p_export.add_argument("--mcap", required=True, metavar="OUT", help="MCAP file to write")
    p_export.add_argument(
        "--data-dir", default="./data", help="the service's state directory (default: %(default)s)"
    )
    p_export.set_defaults(handler="service.export:run_export")

    p_serve = add_command(
        "serve",
        help="run the mapping service (Zenoh ingest + HTTP API)",
        description="Subscribe to robot scans over Zenoh, map them per session, serve HTTP.",
    )
    p_serve.add_argument("--http-host", default="127.0.0.1", help="default: %(default)s")
    p_serve.add_argument("--http-port", type=int, default=8000, help="default: %(default)s")
    p_serve.add_argument(
        "--data-dir", default="./data", help="state directory (default: %(default)s)"
    )
    sec = p_serve.add_argument_group(
        "access",
        "Two scopes: the control token may create, stop, reset, save and delete sessions (and "
        "read); the read token may only read (sessions, poses, trajectories, maps, the pose "
        "stream, /metrics and the full /health). A token on the command line is visible to "
        "every user in `ps`: prefer MAPPING_TOKEN / MAPPING_READ_TOKEN in the environment, or "
        "a token file (MAPPING_TOKEN_FILE / MAPPING_READ_TOKEN_FILE also work).",
    )
    sec.add_argument(
        "--token",
        default=None,
        help="control token (visible in `ps`: prefer env MAPPING_TOKEN or --token-file)",
    )
    sec.add_argument(
        "--token-file",
        default=None,
        metavar="FILE",
        help="read the control token from FILE (its first line; chmod 600)",
    )
    sec.add_argument(
        "--read-token",
        default=None,
        help="read token: every read needs it or the control token (visible in `ps`: prefer "
        "env MAPPING_READ_TOKEN or --read-token-file)",
    )
    sec.add_argument(
        "--read-token-file",
        default=None,
        metavar="FILE",
        help="read the read token from FILE (its first line; chmod 600)",
    )
    sec.add_argument(
        "--public-reads",
        action="store_true",
        help="allow a non-loopback HTTP bind with a control token but no read token: every "
        "map and robot track is then readable by anyone who reaches the port",
    )
    sec.add_argument(
        "--allow-insecure-bind",
        action="store_true",
        help="allow a non-loopback HTTP bind without any token (logged as a warning)",
    )
    p_serve.add_argument(
        "--mapper-processes",
        type=int,
        default=None,
        metavar="K",
        help="run the per-scan path in K worker processes, to use K cores with many robots: "
        "each subscribes to its share of the robots' scans and decodes, records, maps and "
        "publishes them; the service's process keeps HTTP and control (they connect to "
        "--zenoh-listen or --zenoh-connect: without either the scans go through the service's "
        "process; or env MAPPING_MAPPER_PROCESSES; default: 0, all in the service's process)",
    )
    p_serve.add_argument(
        "--ingest-in-mappers",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="with --mapper-processes K > 0: scans straight to the mapper processes (the "
        "default); --no-ingest-in-mappers: the older layout, scans taken in and validated "
        "by the service's process, which forwards them to the mapper processes (or env "
        "MAPPING_INGEST_IN_MAPPERS=0/1)",
    )
    p_serve.add_argument(
        "--no-loop-closure",
        action="store_true",
        help="run the front end alone: no pose graph, no loop closure, poses final once "
        "published (default: loop closure on, in the background; docs/backend.md)",
    )
    p_serve.add_argument(
        "--front-end",
        choices=SERVE_FRONT_END_CHOICES,
        default=None,
        help="the front end of new sessions, as `map --front-end` (or env MAPPING_FRONT_END; "
        "default: matcher); a session keeps the one it was created with",
    )
    p_serve.add_argument(
        "--foxglove-port",
        type=int,
        default=0,
        metavar="PORT",
        help="serve the Foxglove WebSocket live view on the HTTP host at PORT "
        "(e.g. 8765; default 0: off; same loopback/token rule as HTTP)",
    )
    g = p_serve.add_argument_group("fleet (several instances on one Zenoh network)")
    g.add_argument(
        "--robots",
        action="append",
        default=None,
        metavar="PATTERN",
        help="map only robots whose id matches PATTERN, e.g. 'warehouse-a-*' ('*' matches any "
        "run of id characters; repeatable; default: every robot)",
    )
    g.add_argument(
        "--instance-id",
        default=None,
        metavar="ID",
        help="this instance's name on Zenoh, <prefix>/_instances/<ID> (or env "
        "MAPPING_INSTANCE_ID; default: <hostname>-<http port>)",
    )
    p_serve.add_argument(
        "--retain-recordings",
        type=float,
        default=None,
        metavar="DAYS",
        help="prune the scans of recording segments older than DAYS (fractions allowed) once "
        "two checkpoints cover them; their poses stay, so trajectories are kept whole "
        "(or env MAPPING_RETAIN_RECORDINGS_DAYS; default: keep everything)",
    )
    _add_zenoh_args(p_serve)
    p_serve.set_defaults(handler="service.app.main:run_serve")

    p_fsck = add_command(
        "fsck",
        help="check a data directory for damaged sessions (and repair what is provable)",
        description=(
            "Check every session of a data directory: session.json, each recording segment "
            "(damaged records, torn tails) and each checkpoint (checksum). Without --repair "
            "nothing is written. With --repair, a damaged recording segment is rewritten with "
            "its intact records only (the original is kept as <file>.bak-<time>) and a "
            "checkpoint that fails its checksum is moved aside; a torn tail is reported (the "
            "service cuts it when it appends again); nothing is guessed: "
            "a session.json that cannot be read is reported, not rewritten. Run it while the "
            "service is stopped (it takes the data directory's lock)."
        ),
        epilog="Exit codes: 0 nothing damaged; 1 damage found (and not all of it repaired); "
        "2 usage error or the directory is in use; 3 damage found and all of it repaired.",
    )
    p_fsck.add_argument("data_dir", metavar="DATA_DIR", help="the service's --data-dir")
    p_fsck.add_argument("--repair", action="store_true", help="repair what can be proven")
    p_fsck.add_argument("--json", action="store_true", help="print the report as JSON")
    p_fsck.set_defaults(handler="service.fsck:run_fsck")

    p_demo = add_command(
        "demo",
        help="service + simulated UTM-30LX robot; open the printed URL",
        description=(
            "Run the service with an embedded Zenoh session and a simulated robot whose emulated "
            "UTM-30LX speaks SCIP 2.0 over a pty, start a session and print the live map URL."
        ),
    )
    p_demo.add_argument("--http-host", default="127.0.0.1", help="default: %(default)s")
    p_demo.add_argument("--http-port", type=int, default=8000, help="default: %(default)s")
    p_demo.add_argument(
        "--data-dir",
        default=None,
        help="state directory, kept after the demo (default: "
        "$XDG_DATA_HOME/manhattan-mapper/demo, i.e. ~/.local/share/manhattan-mapper/demo)",
    )
    p_demo.add_argument(
        "--foxglove-port",
        type=int,
        default=8765,
        metavar="PORT",
        help="Foxglove WebSocket live view port (default: %(default)s; 0: off)",
    )
    p_demo.add_argument("--world-seed", type=int, default=1, help="simulated building (default: 1)")
    p_demo.add_argument("--robots", type=int, default=1, help="number of simulated robots")
    p_demo.add_argument(
        "--no-loop-closure",
        action="store_true",
        help="the front end alone, as `serve --no-loop-closure` (default: loops closed)",
    )
    p_demo.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    p_demo.set_defaults(handler="service.demo:run_demo")
    return parser


def configure_logging(verbosity: int) -> None:
    level = logging.DEBUG if verbosity > 1 else logging.INFO if verbosity == 1 else logging.WARNING
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s", stream=sys.stderr
    )
    from service.app.limits import RepeatFilter  # noqa: PLC0415  # keeps `--help` light

    repeat = RepeatFilter()
    for handler in logging.getLogger().handlers:
        handler.addFilter(repeat)  # e.g. asyncio's accept() storm at the descriptor limit


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.verbose += args.verbose_after  # `-v serve -v` counts both
    configure_logging(args.verbose if args.command != "demo" else max(args.verbose, 1))
    module_name, func_name = args.handler.split(":")
    handler = getattr(importlib.import_module(module_name), func_name)
    try:
        return int(handler(args))
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
