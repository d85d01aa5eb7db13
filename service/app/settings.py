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


class IngestSettings(_Frozen):
    # 32 scans = 0.8 s of a 40 Hz sensor: absorbs bursts without letting an overloaded worker
    # fall seconds behind real time (the oldest scans are dropped, and counted, instead).
    queue_depth: int = Field(default=32, ge=1, description="scans buffered per robot (drop oldest)")
    max_robots: int = Field(
        default=1024, ge=1, description="robots tracked at once (queues, workers)"
    )
    max_payload_bytes: int = Field(default=1 << 20, ge=1024)
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
    token: SecretStr | None = None
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
        if self.security.token is None:
            return None
        return self.security.token.get_secret_value() or None

    def check(self) -> None:
        """Refuse settings that are unsafe or unusable; raises `SettingsError` with the reason."""
        try:
            check_prefix(self.zenoh.prefix)
            for pattern in self.fleet.robots:
                scan_wildcard(self.zenoh.prefix, pattern)
            check_instance_id(self.fleet.effective_instance_id(self.http.port))
        except (InvalidPrefixError, InvalidInstanceIdError) as err:
            raise SettingsError(str(err)) from err
        if not is_loopback_host(self.http.host) and self.token is None:
            if not self.security.allow_insecure_bind:
                raise SettingsError(
                    f"refusing to bind HTTP to non-loopback address {self.http.host!r} without a "
                    "token: pass --token (or set MAPPING_TOKEN), or --allow-insecure-bind"
                )
            log.warning(
                "HTTP bound to %s without a token: anyone who can reach it controls sessions",
                self.http.host,
            )

    def describe(self) -> dict[str, Any]:
        """The effective settings for the start-up log, with the token redacted."""
        data = self.model_dump(mode="json")
        data["security"]["token"] = "<set>" if self.token else None
        return data


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
        },
        "ingest": from_env(
            queue_depth="QUEUE_DEPTH",
            max_robots="MAX_ROBOTS",
            max_payload_bytes="MAX_PAYLOAD_BYTES",
            workers="INGEST_WORKERS",
        )
        | (
            {"mapper_processes": args.mapper_processes}
            if getattr(args, "mapper_processes", None) is not None
            else from_env(mapper_processes="MAPPER_PROCESSES")
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
            "token": getattr(args, "token", None) or _env(env, "TOKEN"),
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
