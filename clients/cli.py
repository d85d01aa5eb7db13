"""`mapctl`: control and watch a mapping service from the command line."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final, TextIO

from clients.fleet import FleetView, query_fleet
from clients.http import (
    DEFAULT_TIMEOUT_S,
    MapFormat,
    MappingClient,
    MappingConnectionError,
    MappingError,
    MappingProtocolError,
    PoseView,
    SavedMap,
    Session,
)
from clients.keyexpr import DEFAULT_PREFIX

EXIT_OK: Final = 0
EXIT_REFUSED: Final = 1  # the service answered 4xx
EXIT_USAGE: Final = 2  # bad command line (argparse's own code)
EXIT_UNAVAILABLE: Final = 3  # cannot connect, timeout, 5xx, unreadable answer
EXIT_INTERRUPTED: Final = 130

DEFAULT_SERVER: Final = "http://127.0.0.1:8000"

EPILOG: Final = f"""\
exit codes:
  {EXIT_OK}    success
  {EXIT_REFUSED}    the service refused the request (4xx: unknown session, bad token, bad input)
  {EXIT_USAGE}    usage error (bad command line)
  {EXIT_UNAVAILABLE}    cannot reach the service, it failed (5xx), or its answer was unreadable
  {EXIT_INTERRUPTED}  interrupted (Ctrl-C)

environment:
  MAPPING_SERVER  default for --server (else {DEFAULT_SERVER})
  MAPPING_TOKEN   default for --token (safer than the flag: not visible in `ps`)
  MAPPING_TOKEN_FILE  default for --token-file

examples:
  mapctl start amr-07
  mapctl sessions --json | jq '.[].id'
  mapctl pose SESSION --follow
  mapctl map SESSION --out map.png
  mapctl maps get MAP_ID --version 2 --out map.pgm
  mapctl watch
  mapctl fleet --zenoh-connect tcp/router:7447
"""

# ANSI sequences for `watch` on a terminal.
_HOME_CLEAR: Final = "\x1b[H\x1b[2J"
_BOLD: Final = "\x1b[1m"
_DIM: Final = "\x1b[2m"
_RESET: Final = "\x1b[0m"
_GREEN: Final = "\x1b[32m"
_YELLOW: Final = "\x1b[33m"
_RED: Final = "\x1b[31m"


# ---------------------------------------------------------------------------------------------
# Command line


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mapctl",
        description="Control and watch a mapping service.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--server",
        default=os.environ.get("MAPPING_SERVER") or DEFAULT_SERVER,
        help="service base URL (env MAPPING_SERVER; default %(default)s)",
    )
    tokens = parser.add_mutually_exclusive_group()
    tokens.add_argument(
        "--token",
        default=None,
        help="bearer token: the control token, or the read token for reads only; visible "
        "in `ps`, so prefer env MAPPING_TOKEN or --token-file",
    )
    tokens.add_argument(
        "--token-file",
        default=None,
        metavar="FILE",
        help="read the token from FILE (its first line; env MAPPING_TOKEN_FILE)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        metavar="S",
        help="HTTP timeout in seconds (default %(default)s)",
    )
    parser.add_argument("--json", action="store_true", help="machine-readable JSON output")

    # `--json` is accepted after the subcommand too; SUPPRESS keeps the global value otherwise.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--json", action="store_true", default=argparse.SUPPRESS, help="JSON output"
    )

    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add(name: str, help_text: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[common], help=help_text, description=help_text)

    add("sessions", "list the mapping sessions")
    p = add("show", "show one session")
    p.add_argument("session_id", metavar="ID")

    p = add("start", "start mapping a robot (creates a session)")
    p.add_argument("robot_id", metavar="ROBOT")
    p.add_argument("--resolution", type=float, default=None, metavar="M", help="cell size (m)")
    odo = p.add_mutually_exclusive_group()
    odo.add_argument("--odometry", dest="use_odometry", action="store_true", default=None)
    odo.add_argument("--no-odometry", dest="use_odometry", action="store_false")

    for name, text in (
        ("stop", "stop a session (its map is kept)"),
        ("reset", "clear a session's map and trajectory"),
        ("save", "save a versioned snapshot of a session's map"),
        ("delete", "delete a session"),
    ):
        p = add(name, text)
        p.add_argument("session_id", metavar="ID")

    p = add("pose", "print a session's latest pose")
    p.add_argument("session_id", metavar="ID")
    p.add_argument("--follow", "-f", action="store_true", help="keep printing poses live")
    p.add_argument("--count", type=int, default=None, metavar="N", help="stop after N poses")

    p = add("map", "download a session's live map")
    p.add_argument("session_id", metavar="ID")
    p.add_argument("--out", required=True, metavar="FILE", help=".png, .pgm or .yaml")
    p.add_argument("--format", choices=("png", "pgm", "yaml"), default=None, help="default: --out")
    p.add_argument("--no-trajectory", action="store_true", help="PNG without the trajectory")
    p.add_argument("--no-robot", action="store_true", help="PNG without the robot marker")

    p = add("trajectory", "print or save a session's trajectory")
    p.add_argument("session_id", metavar="ID")
    p.add_argument("--format", choices=("tum", "json"), default="tum", help="default: tum")
    p.add_argument("--out", default=None, metavar="FILE", help="write to FILE, not stdout")
    p.add_argument(
        "--every",
        type=int,
        default=1,
        metavar="N",
        help="only every N-th pose (sequences that are multiples of N; default: all). The "
        "trajectory is fetched page by page whatever its length",
    )

    p = add("maps", "list saved maps, or download one (`maps get`)")
    maps_sub = p.add_subparsers(dest="maps_command", metavar="{get}")
    g = maps_sub.add_parser(
        "get",
        parents=[common],
        help="download a saved map version",
        description="Download one file of a saved map: the latest version, or --version N.",
    )
    g.add_argument("map_id", metavar="MAP_ID", help="a map id from `mapctl maps`")
    g.add_argument("--version", type=int, default=None, metavar="N", help="default: the latest")
    g.add_argument("--out", required=True, metavar="FILE", help=".png, .pgm or .yaml")
    g.add_argument("--format", choices=("png", "pgm", "yaml"), default=None, help="default: --out")
    add("health", "show the service's health")

    p = add(
        "fleet",
        "every mapping-service instance on the Zenoh network: robots, sessions, conflicts",
    )
    p.add_argument(
        "--zenoh-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="ask Zenoh directly (a router or an instance, e.g. tcp/127.0.0.1:7447; "
        "repeatable); without it, ask --server's GET /fleet",
    )
    p.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix (default %(default)s)")
    p.add_argument(
        "--query-timeout", type=float, default=2.0, metavar="S", help="Zenoh query timeout"
    )

    p = add("watch", "live table of sessions: robots, poses, quality, scan rate")
    p.add_argument("--interval", type=float, default=1.0, metavar="S", help="refresh period")
    p.add_argument("--count", type=int, default=None, metavar="N", help="stop after N refreshes")
    return parser


def _token(args: argparse.Namespace) -> str | None:
    """--token, --token-file, MAPPING_TOKEN, MAPPING_TOKEN_FILE: the first one given."""
    if args.token:
        return str(args.token)
    path = args.token_file
    if path is None:
        if os.environ.get("MAPPING_TOKEN"):
            return os.environ["MAPPING_TOKEN"]
        path = os.environ.get("MAPPING_TOKEN_FILE") or None
    if path is None:
        return None
    lines = Path(path).read_text(encoding="utf-8").strip().splitlines()
    if not lines or not lines[0].strip():
        raise OSError(f"{path} is empty")
    return lines[0].strip()


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "fleet" and args.zenoh_connect:
        return _cmd_fleet_zenoh(args, sys.stdout)
    try:
        token = _token(args)
    except (OSError, UnicodeDecodeError) as err:
        _err(f"cannot read the token file: {err}")
        return EXIT_USAGE
    try:
        with MappingClient(args.server, token=token, timeout_s=args.timeout) as client:
            return int(_COMMANDS[args.command](client, args, sys.stdout))
    except MappingError as err:
        return _report(err, args.server, token_given=token is not None)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # Output piped into `head` and closed: not an error for a CLI.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except OSError as err:  # e.g. cannot write --out
        _err(str(err))
        return EXIT_REFUSED


def _err(message: str) -> None:
    """One clear line on stderr; the exit code carries the category."""
    sys.stderr.write(f"mapctl: {message}\n")


def _report(err: MappingError, server: str, *, token_given: bool = False) -> int:
    if isinstance(err, MappingConnectionError):
        _err(err.reason)
        return EXIT_UNAVAILABLE
    if isinstance(err, MappingProtocolError):
        _err(f"unexpected answer from {server}: {err.reason}")
        return EXIT_UNAVAILABLE
    status = err.status
    if status == 401 and not token_given:
        # The service's reason names the HTTP header; a CLI user needs mapctl's own options.
        _err(
            f"{server} needs a token for this (HTTP 401): pass it with --token-file FILE "
            "(or env MAPPING_TOKEN_FILE, or MAPPING_TOKEN)"
        )
        return EXIT_REFUSED
    _err(f"{err.reason} (HTTP {status})")
    if status is not None and 400 <= status < 500:
        return EXIT_REFUSED
    return EXIT_UNAVAILABLE


# ---------------------------------------------------------------------------------------------
# Commands

Command = Callable[[MappingClient, argparse.Namespace, TextIO], int]


def _cmd_sessions(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    sessions = client.list_sessions()
    if args.json:
        _dump([s.to_json() for s in sessions], out)
    elif not sessions:
        out.write("no sessions\n")
    else:
        out.write(_session_table(sessions, {}) + "\n")
    return EXIT_OK


def _cmd_show(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    _print_session(client.get_session(args.session_id), args, out)
    return EXIT_OK


def _cmd_start(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    session = client.create_session(
        args.robot_id, resolution_m=args.resolution, use_odometry=args.use_odometry
    )
    if args.json:
        _dump(session.to_json(), out)
    else:
        out.write(f"started session {session.id} for robot {session.robot_id}\n")
    return EXIT_OK


def _session_action(action: str) -> Command:
    def run(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
        method = {
            "stop": client.stop_session,
            "reset": client.reset_session,
        }[action]
        session = method(args.session_id)
        if args.json:
            _dump(session.to_json(), out)
        else:
            out.write(f"{action}: session {session.id} is {session.state}\n")
        return EXIT_OK

    return run


def _cmd_delete(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    client.delete_session(args.session_id)
    if args.json:
        _dump({"deleted": args.session_id}, out)
    else:
        out.write(f"deleted session {args.session_id}\n")
    return EXIT_OK


def _cmd_save(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    saved = client.save_session(args.session_id)
    if args.json:
        _dump(saved.to_json(), out)
    else:
        out.write(
            f"saved map {saved.map_id} version {saved.version}\n"
            f"  png  {client.base_url}{saved.urls.png}\n"
            f"  pgm  {client.base_url}{saved.urls.pgm}\n"
            f"  yaml {client.base_url}{saved.urls.yaml}\n"
        )
    return EXIT_OK


def _cmd_pose(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    if args.count is not None and args.count < 1:
        _err("--count must be at least 1")
        return EXIT_USAGE
    if not args.follow:
        _print_pose(client.get_pose(args.session_id), args.json, out)
        return EXIT_OK
    seen = 0
    stream = client.stream_poses(args.session_id)
    try:
        for pose in stream:
            _print_pose(pose, args.json, out)
            out.flush()
            seen += 1
            if args.count is not None and seen >= args.count:
                break
    finally:
        stream.close()
    if args.count is not None and seen >= args.count:
        return EXIT_OK
    # The server ended the stream: it is shutting down, or the session went away.
    _err(f"the pose stream ended after {seen} poses: the service stopped or the session ended")
    return EXIT_UNAVAILABLE


def _cmd_map(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    path = Path(args.out)
    fmt: MapFormat
    chosen = args.format or path.suffix.lower().lstrip(".")
    if chosen == "png":
        fmt = "png"
        data = client.get_map_png(
            args.session_id, trajectory=not args.no_trajectory, robot=not args.no_robot
        )
    elif chosen == "pgm":
        fmt = "pgm"
        data = client.get_map_pgm(args.session_id)
    elif chosen == "yaml":
        fmt = "yaml"
        data = client.get_map_yaml(args.session_id).encode()
    else:
        _err(f"cannot tell the format of {path.name!r}: use .png, .pgm, .yaml or --format")
        return EXIT_USAGE
    path.write_bytes(data)
    if args.json:
        _dump({"path": str(path), "format": fmt, "bytes": len(data)}, out)
    else:
        out.write(f"wrote {path} ({fmt}, {len(data)} bytes)\n")
    return EXIT_OK


def _cmd_trajectory(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    if args.format == "tum":
        text = client.get_trajectory_tum(args.session_id, every=args.every)
    else:
        poses = client.get_trajectory(args.session_id, every=args.every)
        text = json.dumps(
            {"session_id": args.session_id, "poses": [p.to_json() for p in poses]}, indent=2
        )
        text += "\n"
    if args.out is None:
        out.write(text)
    else:
        Path(args.out).write_text(text)
        lines = text.count("\n")
        sys.stderr.write(f"wrote {args.out} ({args.format}, {lines} lines)\n")
    return EXIT_OK


def _cmd_maps(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    if getattr(args, "maps_command", None) == "get":
        return _cmd_maps_get(client, args, out)
    maps = client.list_maps()
    if args.json:
        _dump([m.to_json() for m in maps], out)
    elif not maps:
        out.write("no saved maps\n")
    else:
        out.write(_maps_table(maps) + "\n")
    return EXIT_OK


def _cmd_maps_get(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    path = Path(args.out)
    chosen = args.format or path.suffix.lower().lstrip(".")
    if chosen not in ("png", "pgm", "yaml"):
        _err(f"cannot tell the format of {path.name!r}: use .png, .pgm, .yaml or --format")
        return EXIT_USAGE
    fmt: MapFormat = chosen  # type: ignore[assignment]  # checked just above
    versions = sorted(m.version for m in client.list_maps() if m.map_id == args.map_id)
    if not versions:
        _err(f"no saved map {args.map_id!r} (see `mapctl maps`)")
        return EXIT_REFUSED
    version = versions[-1] if args.version is None else args.version
    if version not in versions:
        _err(f"map {args.map_id} has no version {version} (versions: {versions})")
        return EXIT_REFUSED
    data = client.download_map(args.map_id, version, fmt)
    path.write_bytes(data)
    if args.json:
        _dump(
            {"path": str(path), "map_id": args.map_id, "version": version, "format": fmt,
             "bytes": len(data)},
            out,
        )  # fmt: skip
    else:
        out.write(f"wrote {path} (map {args.map_id} v{version}, {fmt}, {len(data)} bytes)\n")
    return EXIT_OK


def _cmd_health(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    health = client.health()
    if args.json:
        _dump(dict(health.details), out)
    else:
        out.write(f"{client.base_url}: {health.status}\n")
        for key, value in health.details.items():
            if key != "status":
                out.write(f"  {key}: {json.dumps(value)}\n")
    return EXIT_OK if health.ok else EXIT_UNAVAILABLE


def _cmd_fleet(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    try:
        view = FleetView.from_json(client.fleet_json())
    except ValueError as err:
        raise MappingProtocolError(None, f"fleet: {err}") from err
    return _print_fleet(view, args, out)


def _cmd_fleet_zenoh(args: argparse.Namespace, out: TextIO) -> int:
    import zenoh  # noqa: PLC0415 (only this command needs Zenoh)

    from clients.zenoh_config import build_zenoh_config  # noqa: PLC0415

    try:
        conf = build_zenoh_config(mode="client", connect=args.zenoh_connect)
        with zenoh.open(conf) as session:
            view = query_fleet(session, args.prefix, args.query_timeout)
    except zenoh.ZError as err:
        _err(f"cannot reach Zenoh at {', '.join(args.zenoh_connect)}: {err}")
        return EXIT_UNAVAILABLE
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    return _print_fleet(view, args, out)


def _print_fleet(view: FleetView, args: argparse.Namespace, out: TextIO) -> int:
    """One row per session (an instance without sessions gets a row of its own)."""
    if args.json:
        _dump(view.to_json(), out)
        return EXIT_OK
    headers = ["INSTANCE", "ROBOTS", "SESSION", "ROBOT", "STATE", "SCANS"]
    rows: list[list[str]] = []
    for inst in view.instances:
        patterns = " ".join(inst.patterns)
        if not inst.sessions:
            rows.append([inst.instance_id, patterns, "-", "-", "-", "-"])
        for s in sorted(inst.sessions, key=lambda s: (s.robot_id, s.session_id)):
            rows.append(
                [
                    inst.instance_id,
                    patterns,
                    s.session_id,
                    s.robot_id,
                    s.state,
                    str(s.scans_accepted),
                ]
            )
    if rows:
        out.write(_table(headers, rows, right={5}) + "\n")
    else:
        out.write("no mapping-service instance answered\n")
    for instance_id in view.alive_without_answer:
        out.write(f"{instance_id}: alive but did not answer in time\n")
    for conflict in view.conflicts:
        out.write(f"CONFLICT: {conflict.describe()}\n")
    return EXIT_OK


def _cmd_watch(client: MappingClient, args: argparse.Namespace, out: TextIO) -> int:
    if args.interval <= 0:
        _err("--interval must be positive")
        return EXIT_USAGE
    tty = out.isatty()
    # Previous (scans_accepted, monotonic time) per session, for the scans/s column.
    previous: dict[str, tuple[int, float]] = {}
    refreshes = 0
    last_error: MappingError | None = None
    while True:
        now = time.monotonic()
        idle: list[str] = []
        try:
            sessions = client.list_sessions()
            idle = _idle_robots(client)
            last_error = None
        except (MappingConnectionError, MappingProtocolError) as err:
            sessions, last_error = [], err
        except MappingError as err:
            if err.status is not None and err.status < 500:
                raise  # e.g. 401: retrying will not help
            sessions, last_error = [], err
        rates: dict[str, float] = {}
        for s in sessions:
            if s.id in previous:
                count0, t0 = previous[s.id]
                if now > t0:
                    rates[s.id] = max(0.0, (s.scans_accepted - count0) / (now - t0))
            previous[s.id] = (s.scans_accepted, now)
        if args.json:
            _dump_line(
                {
                    "time": time.time(),
                    "error": None if last_error is None else last_error.reason,
                    "sessions": [{**s.to_json(), "scans_per_s": rates.get(s.id)} for s in sessions],
                    "robots_without_session": idle,
                },
                out,
            )
        else:
            header = f"mapctl watch  {client.base_url}  {time.strftime('%H:%M:%S')}"
            if last_error is not None:
                body = f"service unavailable: {last_error.reason}"
            elif not sessions:
                body = "no sessions"
            else:
                body = _session_table(sessions, rates, color=tty)
            if last_error is None and idle:
                body += f"\n\nrobots without a session: {', '.join(idle)}"
            screen = f"{_BOLD}{header}{_RESET}\n\n{body}\n" if tty else f"{header}\n{body}\n"
            out.write((_HOME_CLEAR + screen) if tty else screen + "\n")
        out.flush()
        refreshes += 1
        if args.count is not None and refreshes >= args.count:
            return EXIT_OK if last_error is None else EXIT_UNAVAILABLE
        time.sleep(args.interval)


def _idle_robots(client: MappingClient) -> list[str]:
    """Robots the service hears from (or sees alive) that have no active session."""
    robots = client.health().details.get("robots")
    if not isinstance(robots, list):
        return []
    return sorted(
        str(r["robot_id"])
        for r in robots
        if isinstance(r, dict) and "robot_id" in r and r.get("session_id") is None
    )


_COMMANDS: Final[dict[str, Command]] = {
    "sessions": _cmd_sessions,
    "fleet": _cmd_fleet,
    "show": _cmd_show,
    "start": _cmd_start,
    "stop": _session_action("stop"),
    "reset": _session_action("reset"),
    "delete": _cmd_delete,
    "save": _cmd_save,
    "pose": _cmd_pose,
    "map": _cmd_map,
    "trajectory": _cmd_trajectory,
    "maps": _cmd_maps,
    "health": _cmd_health,
    "watch": _cmd_watch,
}


# ---------------------------------------------------------------------------------------------
# Formatting


def _dump(value: Any, out: TextIO) -> None:
    out.write(json.dumps(value, indent=2) + "\n")


def _dump_line(value: Any, out: TextIO) -> None:
    out.write(json.dumps(value) + "\n")


def _print_session(session: Session, args: argparse.Namespace, out: TextIO) -> None:
    if args.json:
        _dump(session.to_json(), out)
        return
    created = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(session.created_ns / 1e9))
    lines = [
        f"session     {session.id}",
        f"robot       {session.robot_id}",
        f"state       {session.state}",
        f"created     {created}",
        f"scans       {session.scans_accepted}",
        f"poses       {session.poses}",
        f"resolution  {session.resolution_m:g} m",
        f"odometry    {'yes' if session.use_odometry else 'no'}",
        f"last pose   {_pose_text(session.last_pose) if session.last_pose else '-'}",
    ]
    out.write("\n".join(lines) + "\n")


def _print_pose(pose: PoseView, as_json: bool, out: TextIO) -> None:
    if as_json:
        _dump_line(pose.to_json(), out)
    else:
        out.write(_pose_text(pose) + "\n")


def _pose_text(pose: PoseView) -> str:
    flags = f"  [{', '.join(pose.flags)}]" if pose.flags else ""
    return (
        f"#{pose.sequence}  x {pose.x_m:+.3f} m  y {pose.y_m:+.3f} m  "
        f"θ {math.degrees(pose.theta_rad):+7.2f}°  quality {pose.quality:.2f}{flags}"
    )


def _quality_cell(quality: float, color: bool) -> str:
    # A 10-character bar reads faster than a number when watching many robots.
    filled = max(0, min(10, round(quality * 10)))
    bar = "█" * filled + "·" * (10 - filled)
    text = f"{bar} {quality:.2f}"
    if not color:
        return text
    tint = _GREEN if quality >= 0.6 else _YELLOW if quality >= 0.3 else _RED
    return f"{tint}{text}{_RESET}"


def _session_table(
    sessions: Sequence[Session], rates: dict[str, float], color: bool = False
) -> str:
    headers = ["SESSION", "ROBOT", "STATE", "SCANS", "SCANS/S", "X (m)", "Y (m)", "θ (°)"]
    headers += ["QUALITY", "FLAGS"]
    rows: list[list[str]] = []
    for s in sessions:
        p = s.last_pose
        rate = rates.get(s.id)
        rows.append(
            [
                s.id,
                s.robot_id,
                s.state,
                str(s.scans_accepted),
                "-" if rate is None else f"{rate:.1f}",
                "-" if p is None else f"{p.x_m:+.2f}",
                "-" if p is None else f"{p.y_m:+.2f}",
                "-" if p is None else f"{math.degrees(p.theta_rad):+.1f}",
                "-" if p is None else _quality_cell(p.quality, color),
                "-" if p is None or not p.flags else ",".join(p.flags),
            ]
        )
    return _table(headers, rows, right={3, 4, 5, 6, 7}, color=color)


def _maps_table(maps: Sequence[SavedMap]) -> str:
    headers = ["MAP", "VERSION", "SESSION", "ROBOT", "SAVED", "PNG"]
    rows = [
        [
            m.map_id,
            str(m.version),
            m.session_id,
            m.robot_id,
            time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(m.saved_ns / 1e9)),
            m.urls.png,
        ]
        for m in maps
    ]
    return _table(headers, rows, right={1})


def _visible_len(text: str) -> int:
    # Width without ANSI colour sequences.
    length, i = 0, 0
    while i < len(text):
        if text[i] == "\x1b":
            end = text.find("m", i)
            i = len(text) if end < 0 else end + 1
            continue
        length += 1
        i += 1
    return length


def _table(
    headers: Sequence[str], rows: Sequence[Sequence[str]], right: set[int], color: bool = False
) -> str:
    widths = [len(h) for h in headers]
    for row in rows:
        for i, cell in enumerate(row):
            widths[i] = max(widths[i], _visible_len(cell))

    def fmt(row: Sequence[str]) -> str:
        cells = []
        for i, cell in enumerate(row):
            pad = " " * (widths[i] - _visible_len(cell))
            cells.append(pad + cell if i in right else cell + pad)
        return "  ".join(cells).rstrip()

    head = fmt(headers)
    if color:
        head = f"{_DIM}{head}{_RESET}"
    return "\n".join([head, *(fmt(r) for r in rows)])


if __name__ == "__main__":
    sys.exit(main())
