"""`MappingClient`: a typed, synchronous HTTP client for the mapping service (httpx).

Every operation of the service's HTTP API (see docs/architecture.md) has one method. Answers are
parsed strictly into frozen dataclasses; anything that goes wrong (an HTTP error status, a
connection failure, an answer that does not have the documented shape) raises `MappingError` or
one of its subclasses, so callers need a single `except` clause.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Generator, Iterator, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Final, Literal, Self
from urllib.parse import quote

import httpx

from clients.wire import PoseFlag

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT_S: Final = 10.0
SessionState = Literal["active", "stopped"]
MapFormat = Literal["png", "pgm", "yaml"]
_SESSION_STATES: Final = ("active", "stopped")


# ---------------------------------------------------------------------------------------------
# Errors


class MappingError(Exception):
    """The service said no, could not be reached, or answered something unreadable.

    `status` is the HTTP status code, or None when no HTTP answer was received.
    `reason` is the service's one-line `detail`, or a description of the failure.
    `code` is the service's machine-readable error code (`not_found`, `no_pose_yet`,
    `unauthorized`, `forbidden`, ...), or None.
    """

    def __init__(self, status: int | None, reason: str, code: str | None = None) -> None:
        super().__init__(f"{status}: {reason}" if status is not None else reason)
        self.status = status
        self.reason = reason
        self.code = code


class MappingConnectionError(MappingError):
    """No HTTP answer: connection refused, DNS failure, timeout, broken stream."""

    def __init__(self, reason: str) -> None:
        super().__init__(None, reason)


class MappingProtocolError(MappingError):
    """An answer that does not have the documented shape (bad JSON, missing fields...)."""


# ---------------------------------------------------------------------------------------------
# Typed answers


@dataclass(frozen=True, slots=True)
class PoseView:
    """One pose of a session, in the session's map frame (metres, radians, REP-105)."""

    session_id: str
    robot_id: str
    sequence: int
    stamp_s: float  # seconds since the Unix epoch
    stamp_ns: int
    x_m: float
    y_m: float
    theta_rad: float
    quality: float
    flags: tuple[str, ...]  # PoseFlag names, e.g. ("AMBIGUOUS_X",)

    @property
    def pose_flags(self) -> PoseFlag:
        """The flags as a `PoseFlag` bit set; names this client does not know are ignored."""
        result = PoseFlag.NONE
        for name in self.flags:
            member = PoseFlag.__members__.get(name)
            if member is not None:
                result |= member
        return result

    @classmethod
    def from_json(cls, data: object) -> PoseView:
        obj = _object(data, "pose")
        return cls(
            session_id=_get_str(obj, "session_id", "pose"),
            robot_id=_get_str(obj, "robot_id", "pose"),
            sequence=_get_int(obj, "sequence", "pose"),
            stamp_s=_get_float(obj, "stamp", "pose"),
            stamp_ns=_get_int(obj, "stamp_ns", "pose"),
            x_m=_get_float(obj, "x", "pose"),
            y_m=_get_float(obj, "y", "pose"),
            theta_rad=_get_float(obj, "theta", "pose"),
            quality=_get_float(obj, "quality", "pose"),
            flags=tuple(_get_str_list(obj, "flags", "pose")),
        )

    def to_json(self) -> dict[str, Any]:
        """The service's JSON shape (for `--json` output and re-serialisation)."""
        return {
            "session_id": self.session_id,
            "robot_id": self.robot_id,
            "sequence": self.sequence,
            "stamp": self.stamp_s,
            "stamp_ns": self.stamp_ns,
            "x": self.x_m,
            "y": self.y_m,
            "theta": self.theta_rad,
            "quality": self.quality,
            "flags": list(self.flags),
        }


@dataclass(frozen=True, slots=True)
class Session:
    """A mapping session: one robot, one growing map."""

    id: str
    robot_id: str
    state: SessionState
    created_ns: int
    scans_accepted: int
    poses: int
    resolution_m: float
    use_odometry: bool
    last_pose: PoseView | None

    @property
    def active(self) -> bool:
        return self.state == "active"

    @classmethod
    def from_json(cls, data: object) -> Session:
        obj = _object(data, "session")
        state = _get_str(obj, "state", "session")
        if state not in _SESSION_STATES:
            raise MappingProtocolError(None, f"session: unknown state {state!r}")
        last = obj.get("last_pose")
        return cls(
            id=_get_str(obj, "id", "session"),
            robot_id=_get_str(obj, "robot_id", "session"),
            state="active" if state == "active" else "stopped",
            created_ns=_get_int(obj, "created_ns", "session"),
            scans_accepted=_get_int(obj, "scans_accepted", "session"),
            poses=_get_int(obj, "poses", "session"),
            resolution_m=_get_float(obj, "resolution_m", "session"),
            use_odometry=_get_bool(obj, "use_odometry", "session"),
            last_pose=None if last is None else PoseView.from_json(last),
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "robot_id": self.robot_id,
            "state": self.state,
            "created_ns": self.created_ns,
            "scans_accepted": self.scans_accepted,
            "poses": self.poses,
            "resolution_m": self.resolution_m,
            "use_odometry": self.use_odometry,
            "last_pose": None if self.last_pose is None else self.last_pose.to_json(),
        }


@dataclass(frozen=True, slots=True)
class MapUrls:
    """Where a saved map's files can be downloaded (paths relative to the service)."""

    png: str
    pgm: str
    yaml: str

    def for_format(self, fmt: MapFormat) -> str:
        return {"png": self.png, "pgm": self.pgm, "yaml": self.yaml}[fmt]


@dataclass(frozen=True, slots=True)
class SavedMap:
    """A saved, versioned snapshot of a session's map."""

    map_id: str
    version: int
    session_id: str
    robot_id: str
    saved_ns: int
    urls: MapUrls

    @classmethod
    def from_json(cls, data: object) -> SavedMap:
        obj = _object(data, "saved map")
        urls = _object(obj.get("urls"), "saved map urls")
        return cls(
            map_id=_get_str(obj, "map_id", "saved map"),
            version=_get_int(obj, "version", "saved map"),
            session_id=_get_str(obj, "session_id", "saved map"),
            robot_id=_get_str(obj, "robot_id", "saved map"),
            saved_ns=_get_int(obj, "saved_ns", "saved map"),
            urls=MapUrls(
                png=_get_str(urls, "png", "saved map urls"),
                pgm=_get_str(urls, "pgm", "saved map urls"),
                yaml=_get_str(urls, "yaml", "saved map urls"),
            ),
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "map_id": self.map_id,
            "version": self.version,
            "session_id": self.session_id,
            "robot_id": self.robot_id,
            "saved_ns": self.saved_ns,
            "urls": {"png": self.urls.png, "pgm": self.urls.pgm, "yaml": self.urls.yaml},
        }


@dataclass(frozen=True, slots=True)
class MapInfo:
    """The ROS map_server metadata of a map (`map.yaml`): where the image sits in the map frame.

    Pixel (col, row) of the image, rows counted from the top, covers the cell whose lower-left
    corner is at x = origin_x_m + col * resolution_m, y = origin_y_m + (height - 1 - row) * res.
    """

    image: str
    resolution_m: float
    origin_x_m: float
    origin_y_m: float
    origin_theta_rad: float
    negate: bool
    occupied_thresh: float
    free_thresh: float

    @classmethod
    def from_yaml(cls, text: str) -> MapInfo:
        """Parse the flat `key: value` YAML that map_server uses (no YAML library needed)."""
        fields: dict[str, str] = {}
        for raw_line in text.splitlines():
            line = raw_line.split("#", 1)[0].strip()
            if not line:
                continue
            key, sep, value = line.partition(":")
            if not sep:
                raise MappingProtocolError(None, f"map.yaml: cannot parse line {raw_line!r}")
            fields[key.strip()] = value.strip()
        try:
            origin = [float(v) for v in fields["origin"].strip("[]").split(",")]
            if len(origin) != 3:
                raise ValueError("origin needs 3 numbers")
            info = cls(
                image=fields["image"].strip("'\""),
                resolution_m=float(fields["resolution"]),
                origin_x_m=origin[0],
                origin_y_m=origin[1],
                origin_theta_rad=origin[2],
                negate=fields.get("negate", "0").strip().lower() in ("1", "true"),
                occupied_thresh=float(fields.get("occupied_thresh", "0.65")),
                free_thresh=float(fields.get("free_thresh", "0.196")),
            )
        except (KeyError, ValueError) as err:
            raise MappingProtocolError(None, f"map.yaml: {type(err).__name__}: {err}") from err
        if not (info.resolution_m > 0 and math.isfinite(info.resolution_m)):
            raise MappingProtocolError(None, f"map.yaml: bad resolution {info.resolution_m}")
        return info


@dataclass(frozen=True, slots=True)
class Health:
    """`GET /health`. `status` is the service's overall verdict ("ok" when healthy)."""

    status: str
    details: Mapping[str, Any]

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @classmethod
    def from_json(cls, data: object) -> Health:
        obj = _object(data, "health")
        return cls(status=_get_str(obj, "status", "health"), details=dict(obj))


# ---------------------------------------------------------------------------------------------
# Strict JSON field access: every mismatch is a MappingProtocolError naming the field.


@dataclass(frozen=True, slots=True)
class GraphNode:
    """A pose-graph node: its optimised pose and the front end's (map frame, m, rad)."""

    id: int
    sequence: int
    x: float
    y: float
    theta: float
    frontend_x: float
    frontend_y: float
    frontend_theta: float


@dataclass(frozen=True, slots=True)
class GraphClosure:
    """One loop-closure search: from the older node to the query node, kept or refused."""

    from_node: int
    to_node: int
    score: float
    accepted: bool
    reason: str


@dataclass(frozen=True, slots=True)
class Graph:
    """`GET /sessions/{id}/graph`: nodes, sequential edges (node i to i + 1), closures."""

    session_id: str
    revision: int
    nodes: list[GraphNode]
    edges: list[tuple[int, int]]
    closures: list[GraphClosure]
    accepted: int
    rejected: dict[str, int]

    @property
    def accepted_closures(self) -> list[GraphClosure]:
        return [c for c in self.closures if c.accepted]

    @classmethod
    def from_json(cls, data: object) -> Graph:
        what = "graph"
        obj = _object(data, what)
        nodes = []
        for raw in _get_list(obj, "nodes", what):
            n = _object(raw, "graph node")
            nodes.append(
                GraphNode(
                    id=_get_int(n, "id", "graph node"),
                    sequence=_get_int(n, "sequence", "graph node"),
                    **{
                        k: _get_float(n, k, "graph node")
                        for k in ("x", "y", "theta", "frontend_x", "frontend_y", "frontend_theta")
                    },
                )
            )
        edges = []
        for raw in _get_list(obj, "edges", what):
            e = _object(raw, "graph edge")
            edges.append((_get_int(e, "from_node", "graph edge"), _get_int(e, "to_node", "edge")))
        closures = []
        for raw in _get_list(obj, "closures", what):
            c = _object(raw, "graph closure")
            closures.append(
                GraphClosure(
                    from_node=_get_int(c, "from_node", "graph closure"),
                    to_node=_get_int(c, "to_node", "graph closure"),
                    score=_get_float(c, "score", "graph closure"),
                    accepted=_get_bool(c, "accepted", "graph closure"),
                    reason=_get_str(c, "reason", "graph closure"),
                )
            )
        counts = _object(_missing(obj, "loop_closures", what), "loop_closures")
        rejected = _object(_missing(counts, "rejected", "loop_closures"), "rejected")
        return cls(
            session_id=_get_str(obj, "session_id", what),
            revision=_get_int(obj, "revision", what),
            nodes=nodes,
            edges=edges,
            closures=closures,
            accepted=_get_int(counts, "accepted", "loop_closures"),
            rejected={str(k): _get_int(rejected, k, "rejected") for k in rejected},
        )


def _object(data: object, what: str) -> dict[str, Any]:
    if not isinstance(data, dict):
        raise MappingProtocolError(None, f"{what}: expected a JSON object, got {_kind(data)}")
    return data


def _kind(value: object) -> str:
    return "null" if value is None else type(value).__name__


def _missing(obj: dict[str, Any], key: str, what: str) -> Any:
    if key not in obj:
        raise MappingProtocolError(None, f"{what}: missing field {key!r}")
    return obj[key]


def _get_str(obj: dict[str, Any], key: str, what: str) -> str:
    value = _missing(obj, key, what)
    if not isinstance(value, str):
        raise MappingProtocolError(None, f"{what}: {key} is {_kind(value)}, expected a string")
    return value


def _get_int(obj: dict[str, Any], key: str, what: str) -> int:
    value = _missing(obj, key, what)
    if isinstance(value, bool) or not isinstance(value, int):
        raise MappingProtocolError(None, f"{what}: {key} is {_kind(value)}, expected an integer")
    return value


def _get_float(obj: dict[str, Any], key: str, what: str) -> float:
    value = _missing(obj, key, what)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise MappingProtocolError(None, f"{what}: {key} is {_kind(value)}, expected a number")
    return float(value)


def _get_bool(obj: dict[str, Any], key: str, what: str) -> bool:
    value = _missing(obj, key, what)
    if not isinstance(value, bool):
        raise MappingProtocolError(None, f"{what}: {key} is {_kind(value)}, expected a boolean")
    return value


def _get_list(obj: dict[str, Any], key: str, what: str) -> list[Any]:
    value = _missing(obj, key, what)
    if not isinstance(value, list):
        raise MappingProtocolError(None, f"{what}: {key} is {_kind(value)}, expected a list")
    return value


def _get_str_list(obj: dict[str, Any], key: str, what: str) -> list[str]:
    items = _get_list(obj, key, what)
    if not all(isinstance(v, str) for v in items):
        raise MappingProtocolError(None, f"{what}: {key} must be a list of strings")
    return items


# ---------------------------------------------------------------------------------------------
# The client


class MappingClient:
    """Synchronous client for one mapping service.

    `token` is sent as `Authorization: Bearer <token>` on every request: the control token (for
    everything), or the read token (reads only; control operations then answer 403). A service
    with a read token refuses reads without one (401). Use as a context manager, or call
    `close()`.
    """

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        headers = {"Accept": "application/json"}
        if token:
            headers["Authorization"] = f"Bearer {token}"
        self.base_url = base_url.rstrip("/")
        self._client = httpx.Client(
            base_url=self.base_url,
            headers=headers,
            timeout=timeout_s,
            transport=transport,
            follow_redirects=False,
        )

    # -- lifecycle --------------------------------------------------------------------------

    def close(self) -> None:
        self._client.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- sessions ---------------------------------------------------------------------------

    def create_session(
        self,
        robot_id: str,
        resolution_m: float | None = None,
        use_odometry: bool | None = None,
    ) -> Session:
        """Start mapping `robot_id` (its scans are ingested from now on)."""
        body: dict[str, Any] = {"robot_id": robot_id}
        if resolution_m is not None:
            body["resolution_m"] = resolution_m
        if use_odometry is not None:
            body["use_odometry"] = use_odometry
        return Session.from_json(self._json("POST", "/sessions", json_body=body))

    def list_sessions(self) -> list[Session]:
        obj = _object(self._json("GET", "/sessions"), "session list")
        return [Session.from_json(s) for s in _get_list(obj, "sessions", "session list")]

    def get_session(self, session_id: str) -> Session:
        return Session.from_json(self._json("GET", _session_path(session_id)))

    def delete_session(self, session_id: str, *, keep_maps: bool = False) -> None:
        """Delete a session, its recording and (unless `keep_maps`) its saved map versions."""
        params = {"keep_maps": "true"} if keep_maps else None
        self._request("DELETE", _session_path(session_id), params=params)

    def delete_map(self, map_id: str, version: int) -> None:
        """Delete one saved map version."""
        self._request("DELETE", f"/maps/{_segment(map_id)}/{int(version)}")

    def stop_session(self, session_id: str) -> Session:
        return Session.from_json(self._json("POST", _session_path(session_id, "stop")))

    def reset_session(self, session_id: str) -> Session:
        return Session.from_json(self._json("POST", _session_path(session_id, "reset")))

    def save_session(self, session_id: str) -> SavedMap:
        """Save a versioned snapshot of the session's map."""
        return SavedMap.from_json(self._json("POST", _session_path(session_id, "save")))

    # -- poses ------------------------------------------------------------------------------

    def get_pose(self, session_id: str) -> PoseView:
        """The latest pose. Until the session has its first pose: a `MappingError` with status
        409 and code `no_pose_yet` (404 `not_found` means there is no such session)."""
        return PoseView.from_json(self._json("GET", _session_path(session_id, "pose")))

    def get_graph(self, session_id: str) -> Graph:
        """The session's pose graph (loop closure): nodes, edges, closures and counters."""
        return Graph.from_json(self._json("GET", _session_path(session_id, "graph")))

    def get_trajectory_page(
        self, session_id: str, *, since_seq: int = 0, limit: int | None = None, every: int = 1
    ) -> tuple[list[PoseView], int | None]:
        """One page of the trajectory: poses with `sequence >= since_seq` (at most `limit`,
        the server's page size by default; only multiples of `every`), and the `since_seq`
        of the next page (None at the end)."""
        params = {"since_seq": str(since_seq), "every": str(every)}
        if limit is not None:
            params["limit"] = str(limit)
        obj = _object(
            self._json("GET", _session_path(session_id, "trajectory"), params=params),
            "trajectory",
        )
        poses = [PoseView.from_json(p) for p in _get_list(obj, "poses", "trajectory")]
        next_seq = obj.get("next_seq")
        if next_seq is not None and (not isinstance(next_seq, int) or next_seq <= since_seq):
            raise MappingProtocolError(None, f"trajectory: bad next_seq {next_seq!r}")
        return poses, next_seq

    def iter_trajectory(
        self, session_id: str, *, since_seq: int = 0, every: int = 1, page: int | None = None
    ) -> Iterator[PoseView]:
        """Every pose from `since_seq` on, fetched page by page (bounded memory per request)."""
        cursor: int | None = since_seq
        while cursor is not None:
            poses, cursor = self.get_trajectory_page(
                session_id, since_seq=cursor, limit=page, every=every
            )
            yield from poses

    def get_trajectory(self, session_id: str, *, every: int = 1) -> list[PoseView]:
        """The whole trajectory (paged through; `every` decimates)."""
        return list(self.iter_trajectory(session_id, every=every))

    def get_trajectory_tum(self, session_id: str, *, every: int = 1) -> str:
        """The trajectory as TUM text: `stamp x y z qx qy qz qw` per line (paged through)."""
        parts: list[str] = []
        cursor: str | None = "0"
        while cursor is not None:
            response = self._request(
                "GET",
                _session_path(session_id, "trajectory"),
                params={"format": "tum", "since_seq": cursor, "every": str(every)},
            )
            parts.append(response.text)
            following = response.headers.get("x-next-seq")
            if following is not None and (not following.isdigit() or int(following) <= int(cursor)):
                raise MappingProtocolError(None, f"trajectory: bad X-Next-Seq {following!r}")
            cursor = following
        return "".join(parts)

    def stream_poses(
        self, session_id: str, *, read_timeout_s: float | None = None
    ) -> Generator[PoseView, None, None]:
        """Follow the session's poses live (Server-Sent Events) until the server ends the stream.

        `read_timeout_s` bounds the silence between two events (None waits forever). Close the
        generator (or break out of the loop) to end the stream early.
        """
        timeout = httpx.Timeout(self._client.timeout.connect, read=read_timeout_s)
        path = _session_path(session_id, "pose", "stream")
        try:
            with self._client.stream(
                "GET", path, timeout=timeout, headers={"Accept": "text/event-stream"}
            ) as response:
                if response.is_error:
                    response.read()
                    raise _error_from_response(response)
                for event, data in _iter_sse(response.iter_lines()):
                    if event != "pose":
                        continue
                    try:
                        payload = json.loads(data)
                    except ValueError as err:
                        raise MappingProtocolError(
                            response.status_code, f"pose stream: invalid JSON ({err})"
                        ) from err
                    yield PoseView.from_json(payload)
        except httpx.HTTPError as err:
            raise _connection_error(err, self.base_url) from err

    # -- maps -------------------------------------------------------------------------------

    def get_map_png(self, session_id: str, *, trajectory: bool = True, robot: bool = True) -> bytes:
        """The live map as PNG, optionally with the trajectory and the robot drawn on it."""
        params = {"trajectory": _bool_param(trajectory), "robot": _bool_param(robot)}
        return self._request("GET", _session_path(session_id, "map.png"), params=params).content

    def get_map_pgm(self, session_id: str) -> bytes:
        return self._request("GET", _session_path(session_id, "map.pgm")).content

    def get_map_yaml(self, session_id: str) -> str:
        return self._request("GET", _session_path(session_id, "map.yaml")).text

    def get_map_info(self, session_id: str) -> MapInfo:
        """`map.yaml` parsed: resolution and origin of the live map."""
        return MapInfo.from_yaml(self.get_map_yaml(session_id))

    def list_maps(self) -> list[SavedMap]:
        obj = _object(self._json("GET", "/maps"), "map list")
        return [SavedMap.from_json(m) for m in _get_list(obj, "maps", "map list")]

    def download_map(self, map_id: str, version: int, fmt: MapFormat = "png") -> bytes:
        """One file of a saved map."""
        path = f"/maps/{_segment(map_id)}/{int(version)}/map.{fmt}"
        return self._request("GET", path).content

    # -- service ----------------------------------------------------------------------------

    def health(self) -> Health:
        return Health.from_json(self._json("GET", "/health"))

    def fleet_json(self) -> Any:
        """`GET /fleet`: every instance on the service's Zenoh network (`clients.fleet`)."""
        return self._json("GET", "/fleet")

    def metrics(self) -> str:
        """Prometheus text exposition."""
        return self._request("GET", "/metrics", headers={"Accept": "text/plain"}).text

    # -- plumbing ---------------------------------------------------------------------------

    def _request(
        self,
        method: str,
        path: str,
        *,
        json_body: object = None,
        params: Mapping[str, str] | None = None,
        headers: Mapping[str, str] | None = None,
    ) -> httpx.Response:
        try:
            response = self._client.request(
                method, path, json=json_body, params=params, headers=headers
            )
        except httpx.HTTPError as err:
            raise _connection_error(err, self.base_url) from err
        if response.is_error:
            raise _error_from_response(response)
        return response

    def _json(
        self,
        method: str,
        path: str,
        *,
        json_body: object = None,
        params: Mapping[str, str] | None = None,
    ) -> object:
        response = self._request(method, path, json_body=json_body, params=params)
        try:
            return response.json()
        except ValueError as err:
            raise MappingProtocolError(
                response.status_code, f"{method} {path}: answer is not JSON ({err})"
            ) from err


def _segment(value: str) -> str:
    """One URL path segment; refuses values that would change the path."""
    if not value or value in (".", ".."):
        raise MappingError(None, f"invalid identifier {value!r}")
    return quote(value, safe="")


def _session_path(session_id: str, *rest: str) -> str:
    return "/".join(("/sessions", _segment(session_id), *rest))


def _bool_param(value: bool) -> str:
    return "true" if value else "false"


def _error_from_response(response: httpx.Response) -> MappingError:
    """The service's `{"detail": ...}` as a MappingError (FastAPI 422 details are lists)."""
    reason = response.reason_phrase or "error"
    code: str | None = None
    try:
        body = response.json()
    except ValueError:
        text = response.text.strip().splitlines()
        if text:
            reason = text[0][:200]
    else:
        if isinstance(body, dict) and "detail" in body:
            reason = _detail_text(body["detail"])
            code = body.get("code") if isinstance(body.get("code"), str) else None
    return MappingError(response.status_code, reason, code)


def _detail_text(detail: object) -> str:
    if isinstance(detail, str):
        return detail
    if isinstance(detail, list):
        # FastAPI validation errors: [{"loc": [...], "msg": "...", ...}, ...]
        parts = []
        for item in detail:
            if isinstance(item, dict):
                loc = ".".join(str(p) for p in item.get("loc", []) if p != "body")
                msg = str(item.get("msg", item))
                parts.append(f"{loc}: {msg}" if loc else msg)
            else:
                parts.append(str(item))
        return "; ".join(parts)
    return json.dumps(detail)


def _connection_error(err: httpx.HTTPError, base_url: str) -> MappingConnectionError:
    if isinstance(err, httpx.TimeoutException):
        return MappingConnectionError(f"timed out talking to {base_url}")
    if isinstance(err, httpx.ConnectError):
        return MappingConnectionError(f"cannot connect to {base_url}: {err}")
    return MappingConnectionError(f"{type(err).__name__} talking to {base_url}: {err}")


def _iter_sse(lines: Iterator[str]) -> Iterator[tuple[str, str]]:
    """(event, data) pairs of a text/event-stream; comments and ids are skipped."""
    event = "message"
    data: list[str] = []
    for line in lines:
        if line == "":
            if data:
                yield event, "\n".join(data)
            event, data = "message", []
            continue
        if line.startswith(":"):
            continue  # keep-alive comment
        field, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if field == "event":
            event = value
        elif field == "data":
            data.append(value)
    if data:
        yield event, "\n".join(data)


__all__ = [
    "DEFAULT_TIMEOUT_S",
    "Graph",
    "GraphClosure",
    "GraphNode",
    "Health",
    "MapInfo",
    "MapUrls",
    "MappingClient",
    "MappingConnectionError",
    "MappingError",
    "MappingProtocolError",
    "PoseView",
    "SavedMap",
    "Session",
]
