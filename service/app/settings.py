"""The service's settings: one object, built once at start-up from the CLI and the environment.

Precedence: command-line flags, then `MAPPING_*` environment variables, then defaults. Tuning
knobs that have no flag (queue depths, fsync interval, ...) are read from the environment only.
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import re
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError

from clients.fleet import InvalidInstanceIdError, check_instance_id
from clients.keyexpr import DEFAULT_PREFIX, InvalidPrefixError, check_prefix, scan_wildcard
from service.app.errors import SettingsError
from service.app.limits import default_max_robots

log = logging.getLogger(__name__)

ENV_PREFIX = "MAPPING_"


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class HttpSettings(_Frozen):
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535)
    max_body_bytes: int = Field(default=64 * 1024, ge=1024, description="request bodies above: 413")
    sse_queue_depth: int = Field(default=64, ge=1, description="poses buffered per browser stream")
    # The Foxglove WebSocket live view binds the HTTP host; 0 leaves it off.
    foxglove_port: int = Field(default=0, ge=0, le=65535, description="0: no Foxglove view")
    # Poses that arrive within this interval go to a browser in one write: with 1,000 streams
    # the event loop makes at most 1,000 writes per interval, however fast the robots are.
    sse_interval_s: float = Field(
        default=0.2, ge=0.0, le=5.0, description="shortest time between two writes to a stream"
    )
    # All streams together: with more streams than this × the interval, each writes less
    # often (1,000 streams: once a second), so the event loop's writes stay bounded.
    sse_max_writes_per_s: float = Field(
        default=1000.0, ge=0.0, description="writes to all browser streams per second (0: no bound)"
    )


class ZenohSettings(_Frozen):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    config_file: Path | None = None
    prefix: str = DEFAULT_PREFIX


class StorageSettings(_Frozen):
    data_dir: Path = Path("./data")
    fsync_interval_s: float = Field(
        default=1.0,
        ge=0.0,
        description="0 = fsync every append; otherwise group commit on this period",
    )
    retain_recordings_days: float | None = Field(
        default=None,
        ge=0.0,
        description="prune the scans of recording segments older than this that checkpoints "
        "cover (poses stay); None = keep everything",
    )


class IngestSettings(_Frozen):
    # 32 scans = 0.8 s of a 40 Hz sensor: absorbs bursts without letting an overloaded worker
    # fall seconds behind real time (the oldest scans are dropped, and counted, instead).
    queue_depth: int = Field(default=32, ge=1, description="scans buffered per robot (drop oldest)")
    # Default: what fits under the descriptor limit (service/app/limits.py), at most 1024.
    max_robots: int = Field(
        default_factory=default_max_robots,
        ge=1,
        description="robots tracked at once (queues, workers) and active sessions",
    )
    max_payload_bytes: int = Field(default=1 << 20, ge=1024)
    # A robot without an active session that sends nothing for this long is forgotten (its
    # queue, its metrics series), so made-up robot ids cannot fill `max_robots` for good.
    robot_idle_s: float = Field(
        default=60.0, gt=0.0, description="forget a silent robot without a session after (s)"
    )
    # A scan's host stamp further than this after its robot's previous one is mapped but
    # counted and logged as `stamp_gap` (docs/wire-format.md, "Time").
    max_stamp_gap_s: float = Field(
        default=10.0, gt=0.0, description="forward stamp jump flagged as a gap (s)"
    )
    # Processes that run the estimators and grids (0: in the service's process). One process
    # estimates on one core, however many threads it has (see service/app/mapper.py).
    mapper_processes: int = Field(
        default=0, ge=0, le=64, description="mapper worker processes (0: in-process)"
    )
    # Threads that process scans, round-robin over robots. In-process one is fastest: the work
    # holds the GIL, and more threads only trade it back and forth (see service/app/ingest.py).
    # With mapper processes a thread waits for its process without the GIL; two per process
    # keep every process busy when two ready robots live in the same one.
    workers: int | None = Field(
        default=None, ge=1, le=64, description="ingest threads (default: 1, or 2 per process)"
    )
    # The back end (loop search, pose graph) beside every session's front end, in a background
    # thread of the process that runs the estimator (docs/backend.md, "Live").
    loop_closure: bool = Field(default=True, description="close loops (False: the front end alone)")
    # The front end of every new session's core (`service.core.slam.make_frontend`), as
    # `mapping-service map --front-end`. A session keeps the one it was created with (its
    # `session.json`), so a restart with another setting restores it as it was.
    front_end: Literal["matcher"] = Field(
        default="matcher", description="front end of new sessions: matcher (the only live one)"
    )
    # With mapper processes: each process subscribes to its share of the scan keys itself and
    # runs the whole per-scan path (decode, validate, record, map, publish); the service's
    # process only routes Zenoh, serves HTTP and does control (service/app/mapper.py).
    # None (the default): on whenever K > 0 and the processes have an endpoint to connect to
    # (`scans_in_mappers`); False keeps the older layout (scans through the service's process).
    ingest_in_mappers: bool | None = Field(
        default=None, description="scans go straight to the mapper processes (default: K > 0)"
    )

    @property
    def newcomer_depth(self) -> int:
        """Payloads of robots not tracked yet, waiting to be validated (one shared queue,
        drop oldest): what a flood of made-up robot ids can occupy."""
        return max(self.queue_depth, 128)

    def scans_in_mappers(self, has_endpoint: bool) -> bool:
        """Whether the mapper processes take the scans in: asked for, or by default when there
        are any and the service has a Zenoh endpoint they can connect to (`has_endpoint`)."""
        if not self.mapper_processes or self.ingest_in_mappers is False:
            return False
        return self.ingest_in_mappers is True or has_endpoint

    @property
    def worker_threads(self) -> int:
        if self.workers is not None:
            return self.workers
        return 2 * self.mapper_processes if self.mapper_processes else 1


class FleetSettings(_Frozen):
    # Robot-id patterns this instance maps (`warehouse-a-*`; `*` = every robot). Instances that
    # split a fleet give each a disjoint set; an overlap is reported as a conflict.
    robots: tuple[str, ...] = ("*",)
    # The instance's name on Zenoh (`<prefix>/_instances/<id>`); default: host name and port.
    instance_id: str | None = None
    poll_s: float = Field(default=1.0, gt=0.0, description="period of the fleet conflict check")

    def effective_instance_id(self, http_port: int) -> str:
        if self.instance_id is not None:
            return self.instance_id
        host = re.sub(r"[^A-Za-z0-9_.\-]", "-", socket.gethostname()).lstrip("_.-") or "host"
        return f"{host[:50]}-{http_port}"


class SecuritySettings(_Frozen):
    # Two scopes: the control token may do everything, the read token may only read.
    token: SecretStr | None = None
    read_token: SecretStr | None = None
    public_reads: bool = False
    allow_insecure_bind: bool = False


class ServiceSettings(_Frozen):
    http: HttpSettings = Field(default_factory=HttpSettings)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    storage: StorageSettings = Field(default_factory=StorageSettings)
    ingest: IngestSettings = Field(default_factory=IngestSettings)
    security: SecuritySettings = Field(default_factory=SecuritySettings)
    fleet: FleetSettings = Field(default_factory=FleetSettings)

    @property
    def token(self) -> str | None:
        """The control token (create, stop, reset, save, delete; also reads)."""
        if self.security.token is None:
            return None
        return self.security.token.get_secret_value() or None

    @property
    def read_token(self) -> str | None:
        """The read token: when set, every read needs it (or the control token)."""
        if self.security.read_token is None:
            return None
        return self.security.read_token.get_secret_value() or None

    def check(self) -> None:
        """Refuse settings that are unsafe or unusable; raises `SettingsError` with the reason."""
        try:
            check_prefix(self.zenoh.prefix)
            for pattern in self.fleet.robots:
                scan_wildcard(self.zenoh.prefix, pattern)
            check_instance_id(self.fleet.effective_instance_id(self.http.port))
        except (InvalidPrefixError, InvalidInstanceIdError) as err:
            raise SettingsError(str(err)) from err
        if self.ingest.ingest_in_mappers is True:
            if not self.ingest.mapper_processes:
                raise SettingsError("--ingest-in-mappers needs --mapper-processes K > 0")
            z = self.zenoh
            if not (z.listen or z.connect):
                raise SettingsError(
                    "--ingest-in-mappers: the mapper processes connect to the service's Zenoh "
                    "endpoints; give --zenoh-listen (or --zenoh-connect)"
                )
        for name, value in (("token", self.token), ("read token", self.read_token)):
            if value is not None:
                check_token_text(value, name)
        if self.read_token is not None:
            if self.token is None:
                raise SettingsError(
                    "a read token without a control token would leave control open while "
                    "reads are closed: pass --token (or --token-file) too"
                )
            if self.read_token == self.token:
                raise SettingsError("the read token must differ from the control token")
            if self.security.public_reads:
                raise SettingsError("--public-reads and a read token contradict each other")
            if self.http.foxglove_port:
                raise SettingsError(
                    "the Foxglove view checks no token and would show every map to anyone who "
                    "reaches it: with a read token, leave --foxglove-port off"
                )
        if is_loopback_host(self.http.host):
            return
        if self.token is None:
            if not self.security.allow_insecure_bind:
                raise SettingsError(
                    f"refusing to bind HTTP to non-loopback address {self.http.host!r} without a "
                    "token: pass --token-file (or set MAPPING_TOKEN), or --allow-insecure-bind"
                )
            log.warning(
                "HTTP bound to %s without a token: anyone who can reach it controls sessions",
                self.http.host,
            )
        elif self.read_token is None and not self.security.public_reads:
            if not self.security.allow_insecure_bind:
                raise SettingsError(
                    f"refusing to bind HTTP to non-loopback address {self.http.host!r} with "
                    "public reads (maps and robot tracks): pass --read-token-file (or set "
                    "MAPPING_READ_TOKEN), or --public-reads if they may be public"
                )
            log.warning(
                "HTTP bound to %s without a read token: anyone who can reach it reads every "
                "map and trajectory",
                self.http.host,
            )

    def describe(self) -> dict[str, Any]:
        """The effective settings for the start-up log, with the tokens redacted."""
        data = self.model_dump(mode="json")
        data["security"]["token"] = "<set>" if self.token else None
        data["security"]["read_token"] = "<set>" if self.read_token else None
        return data


_TOKEN_MIN_CHARS = 16


def check_token_text(token: str, name: str) -> None:
    """A token must fit in an HTTP header: visible ASCII, no spaces. Short ones are warned."""
    if not token.isascii() or not token.isprintable() or " " in token:
        raise SettingsError(f"the {name} must be visible ASCII without spaces")
    if len(token) < _TOKEN_MIN_CHARS:
        log.warning(
            "the %s has %d characters: use at least %d random ones (e.g. `openssl rand -hex 24`)",
            name,
            len(token),
            _TOKEN_MIN_CHARS,
        )


def read_token_file(path: str | Path, name: str) -> str:
    """The token in `path`: its first line, surrounding whitespace removed."""
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
        mode = file.stat().st_mode
    except (OSError, UnicodeDecodeError) as err:
        raise SettingsError(f"cannot read the {name} file {str(path)!r}: {err}") from err
    lines = text.strip().splitlines()
    token = lines[0].strip() if lines else ""
    if not token:
        raise SettingsError(f"the {name} file {str(path)!r} is empty")
    if mode & 0o077:
        log.warning("the %s file %s is readable by other users (chmod 600 it)", name, path)
    return token


def _token_from(
    flag_value: str | None,
    flag_file: str | None,
    env: Mapping[str, str],
    env_name: str,
    name: str,
) -> str | None:
    """One token from its flag, its file flag, `MAPPING_<X>` or `MAPPING_<X>_FILE`, in order."""
    if flag_value is not None and flag_file is not None:
        raise SettingsError(f"give the {name} once: either its flag or its file, not both")
    if flag_file is not None:
        return read_token_file(flag_file, name)
    if flag_value is not None:
        return flag_value
    if (value := _env(env, env_name)) is not None:
        return value
    if (file := _env(env, env_name + "_FILE")) is not None:
        return read_token_file(file, name)
    return None


def is_loopback_host(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _env(env: Mapping[str, str], name: str) -> str | None:
    value = env.get(ENV_PREFIX + name)
    return value if value not in (None, "") else None


def build_settings(
    args: argparse.Namespace, env: Mapping[str, str] | None = None
) -> ServiceSettings:
    """Settings for `serve` from parsed arguments plus `MAPPING_*` variables."""
    env = os.environ if env is None else env

    def from_env(**names: str) -> dict[str, str]:
        """Only the variables that are set, so that unset ones keep the model's defaults."""
        return {field: v for field, name in names.items() if (v := _env(env, name)) is not None}

    raw: dict[str, Any] = {
        "http": {
            "host": args.http_host,
            "port": args.http_port,
            "foxglove_port": getattr(args, "foxglove_port", None) or 0,
            **from_env(
                max_body_bytes="MAX_BODY_BYTES",
                sse_queue_depth="SSE_QUEUE_DEPTH",
                sse_interval_s="SSE_INTERVAL_S",
                sse_max_writes_per_s="SSE_MAX_WRITES_PER_S",
            ),
        },
        "zenoh": {
            "listen": tuple(getattr(args, "zenoh_listen", None) or ()),
            "connect": tuple(getattr(args, "zenoh_connect", None) or ()),
            "config_file": getattr(args, "zenoh_config", None),
            "prefix": getattr(args, "prefix", DEFAULT_PREFIX),
            **from_env(mode="ZENOH_MODE"),
        },
        "storage": {
            "data_dir": args.data_dir,
            **from_env(fsync_interval_s="FSYNC_INTERVAL_S"),
            **(
                {"retain_recordings_days": args.retain_recordings}
                if getattr(args, "retain_recordings", None) is not None
                else from_env(retain_recordings_days="RETAIN_RECORDINGS_DAYS")
            ),
        },
        "ingest": from_env(
            queue_depth="QUEUE_DEPTH",
            max_robots="MAX_ROBOTS",
            max_payload_bytes="MAX_PAYLOAD_BYTES",
            workers="INGEST_WORKERS",
            robot_idle_s="ROBOT_IDLE_S",
            max_stamp_gap_s="MAX_STAMP_GAP_S",
        )
        | (
            {"mapper_processes": args.mapper_processes}
            if getattr(args, "mapper_processes", None) is not None
            else from_env(mapper_processes="MAPPER_PROCESSES")
        )
        | ({"loop_closure": False} if getattr(args, "no_loop_closure", False) else {})
        | (
            {"front_end": args.front_end}
            if getattr(args, "front_end", None) is not None
            else from_env(front_end="FRONT_END")
        )
        | (
            {"ingest_in_mappers": args.ingest_in_mappers}
            if getattr(args, "ingest_in_mappers", None) is not None
            else from_env(ingest_in_mappers="INGEST_IN_MAPPERS")
        ),
        "fleet": {
            **({"robots": tuple(args.robots)} if getattr(args, "robots", None) else {}),
            **(
                {"instance_id": args.instance_id}
                if getattr(args, "instance_id", None)
                else from_env(instance_id="INSTANCE_ID")
            ),
            **from_env(poll_s="FLEET_POLL_S"),
        },
        "security": {
            "token": _token_from(
                getattr(args, "token", None),
                getattr(args, "token_file", None),
                env,
                "TOKEN",
                "token",
            ),
            "read_token": _token_from(
                getattr(args, "read_token", None),
                getattr(args, "read_token_file", None),
                env,
                "READ_TOKEN",
                "read token",
            ),
            "public_reads": bool(getattr(args, "public_reads", False)),
            "allow_insecure_bind": bool(getattr(args, "allow_insecure_bind", False)),
        },
    }
    try:
        settings = ServiceSettings.model_validate(raw)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise SettingsError(f"invalid setting {where}: {first['msg']}") from err
    settings.check()
    return settings
