"""HTTP request and response models (the OpenAPI document), apart from internal types.

Shapes follow docs/architecture.md ("HTTP resources"); the class names are the schema names
fleet tools see, hence `Session`, `PoseView`, `SavedMap`.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from clients.wire import Pose, PoseFlag
from service.app.backend import GraphSnapshot
from service.app.sessions import DamageSummary, SessionInfo
from service.app.store import SavedMapMeta

ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$"


class SessionCreate(BaseModel):
    """Start mapping a robot. Scans already arriving on `<prefix>/<robot_id>/scan` are used."""

    # strict: "0.05" is not a number and "yes" is not a boolean (an int is still a number).
    model_config = ConfigDict(extra="forbid", strict=True)

    robot_id: str = Field(pattern=ID_PATTERN, max_length=64, examples=["amr-07"])
    # allow_inf_nan=False: NaN (which Python's JSON parser takes) is "not a finite number",
    # not "should be less than or equal to 1".
    resolution_m: float = Field(
        0.05, ge=0.01, le=1.0, allow_inf_nan=False, description="map cell size in metres"
    )
    use_odometry: bool = Field(True, description="use the scans' odometry as motion prior")


class PoseView(BaseModel):
    """One pose in the session's map frame: metres, radians (counter-clockwise), REP-105."""

    session_id: str
    robot_id: str
    sequence: int = Field(description="0-based index in the session's trajectory")
    stamp: float = Field(description="seconds since the Unix epoch (the scan's host stamp)")
    stamp_ns: int
    x: float = Field(description="metres, map frame")
    y: float = Field(description="metres, map frame")
    theta: float = Field(description="radians, counter-clockwise, in [-π, π)")
    quality: float = Field(ge=0.0, le=1.0, description="0 = no confidence, 1 = fully constrained")
    flags: list[str] = Field(description="PoseFlag names, e.g. AMBIGUOUS_X")
    covariance: list[float] | None = Field(
        default=None,
        min_length=9,
        max_length=9,
        description="row-major 3x3 covariance of (x, y, theta) relative to the latest keyframe, "
        "map axes (m², m·rad, rad²); null when the estimator gave none",
    )

    @classmethod
    def of(cls, pose: Pose) -> PoseView:
        return cls(
            session_id=pose.session_id,
            robot_id=pose.robot_id,
            sequence=pose.seq,
            stamp=pose.stamp_ns / 1e9,
            stamp_ns=pose.stamp_ns,
            x=pose.x_m,
            y=pose.y_m,
            theta=pose.theta_rad,
            quality=pose.quality,
            flags=flag_names(pose.flags),
            covariance=list(pose.covariance) if pose.covariance is not None else None,
        )


def flag_names(flags: PoseFlag) -> list[str]:
    return [f.name for f in PoseFlag if f.value and flags & f and f.name is not None]


class SessionDamage(BaseModel):
    """What a restore found wrong in the session's files (all zero / empty when nothing)."""

    records_lost: int = Field(description="records skipped as damaged (a lower bound)")
    bytes_lost: int = Field(description="bytes of the recording skipped as damaged")
    regions: int = Field(description="damaged stretches of the recording")
    checkpoints_rejected: int = Field(description="checkpoints that failed their checksum")
    notes: list[str] = Field(description="one line per finding")

    @classmethod
    def of(cls, damage: DamageSummary) -> SessionDamage:
        return cls(
            records_lost=damage.records_lost,
            bytes_lost=damage.bytes_lost,
            regions=damage.regions,
            checkpoints_rejected=damage.checkpoints_rejected,
            notes=list(damage.notes),
        )


class LoopClosureCounts(BaseModel):
    """The back end's counters (loop closure on)."""

    accepted: int = Field(description="loop closures accepted into the pose graph")
    rejected: dict[str, int] = Field(
        description="searches refused, by reason: low_score, ambiguous, inconsistent, few_points"
    )
    nodes: int = Field(description="nodes (keyframes) in the pose graph")
    pending: int = Field(description="nodes queued for the back end, not yet in the graph")
    solver_restarts: int = Field(
        0, description="iSAM2 rebuilt from every factor with QR after a failed update"
    )

    @classmethod
    def of(cls, snap: GraphSnapshot) -> LoopClosureCounts:
        return cls(
            accepted=snap.accepted,
            rejected=dict(sorted(snap.rejected.items())),
            nodes=snap.nodes,
            pending=snap.pending,
            solver_restarts=snap.solver_restarts,
        )


class GraphNode(BaseModel):
    id: int = Field(description="node index, 0-based")
    sequence: int = Field(description="the pose sequence of the node's scan")
    x: float = Field(description="optimised pose, metres, map frame")
    y: float
    theta: float = Field(description="radians")
    frontend_x: float = Field(description="the front end's pose of the node (before the graph)")
    frontend_y: float
    frontend_theta: float


class GraphEdge(BaseModel):
    from_node: int
    to_node: int


class GraphClosure(BaseModel):
    from_node: int = Field(description="the older node (the anchor of the submap searched)")
    to_node: int = Field(description="the node whose scan was placed in that submap")
    score: float = Field(description="mean likelihood of the scan's points at the best placement")
    accepted: bool
    reason: str = Field(description="accepted, low_score, ambiguous, inconsistent, few_points")
    from_x: float = Field(description="the older node's optimised position, metres, map frame")
    from_y: float
    to_x: float = Field(description="the query node's optimised position")
    to_y: float


class Graph(BaseModel):
    """The session's pose graph: nodes, sequential edges and loop closures."""

    session_id: str
    revision: int = Field(description="grows whenever the graph changes")
    nodes: list[GraphNode]
    edges: list[GraphEdge] = Field(description="sequential constraints, node i to i + 1")
    closures: list[GraphClosure] = Field(
        description="every accepted closure, then the latest refused searches (at most 100)"
    )
    loop_closures: LoopClosureCounts

    @classmethod
    def of(cls, session_id: str, snap: GraphSnapshot, *, nodes: bool = True) -> Graph:
        fe, opt, seq = snap.frontend.tolist(), snap.optimised.tolist(), snap.node_seq.tolist()
        n = snap.nodes if nodes else 0
        return cls(
            session_id=session_id,
            revision=snap.revision,
            nodes=[
                GraphNode(
                    id=i,
                    sequence=seq[i],
                    x=opt[i][0],
                    y=opt[i][1],
                    theta=opt[i][2],
                    frontend_x=fe[i][0],
                    frontend_y=fe[i][1],
                    frontend_theta=fe[i][2],
                )
                for i in range(n)
            ],
            edges=[GraphEdge(from_node=i, to_node=i + 1) for i in range(n - 1)],
            closures=[
                GraphClosure(
                    from_node=c.from_node,
                    to_node=c.to_node,
                    score=c.score,
                    accepted=c.accepted,
                    reason=c.reason,
                    from_x=opt[c.from_node][0],
                    from_y=opt[c.from_node][1],
                    to_x=opt[c.to_node][0],
                    to_y=opt[c.to_node][1],
                )
                for c in snap.closures
                if max(c.from_node, c.to_node) < snap.nodes
            ],
            loop_closures=LoopClosureCounts.of(snap),
        )


class Session(BaseModel):
    id: str
    robot_id: str
    state: Literal["active", "stopped"]
    status: Literal["restoring", "ok", "degraded", "damaged"] = Field(
        description="`restoring` until replayed after a restart (counters read 0 meanwhile); "
        "`degraded`: damage was found and skipped (see `damage`); `damaged`: the files "
        "cannot be restored (kept as they are; see `mapping-service fsck`)"
    )
    damage: SessionDamage
    created_ns: int
    scans_accepted: int = Field(description="scans recorded into this session's current map")
    poses: int = Field(description="length of the trajectory")
    resolution_m: float
    use_odometry: bool
    last_pose: PoseView | None = Field(description="where the pose graph puts the latest pose")
    loop_closures: LoopClosureCounts | None = Field(
        default=None, description="the back end's counters; null with loop closure off"
    )

    @classmethod
    def of(cls, info: SessionInfo) -> Session:
        return cls(
            id=info.id,
            robot_id=info.robot_id,
            state=info.state,
            created_ns=info.created_ns,
            scans_accepted=info.scans_accepted,
            poses=info.poses,
            resolution_m=info.resolution_m,
            use_odometry=info.use_odometry,
            last_pose=PoseView.of(info.last_pose) if info.last_pose is not None else None,
            status=info.status,
            damage=SessionDamage.of(info.damage),
            loop_closures=(LoopClosureCounts.of(info.graph) if info.graph is not None else None),
        )


class SessionList(BaseModel):
    sessions: list[Session]


class Trajectory(BaseModel):
    session_id: str
    poses: list[PoseView]
    next_seq: int | None = Field(
        description="`since_seq` for the next page; null when this page reaches the end"
    )
    total: int = Field(description="poses in the whole trajectory")


class MapUrls(BaseModel):
    png: str
    pgm: str
    yaml: str


class SavedMap(BaseModel):
    map_id: str
    version: int = Field(ge=1)
    session_id: str
    robot_id: str
    saved_ns: int
    urls: MapUrls

    @classmethod
    def of(cls, meta: SavedMapMeta) -> SavedMap:
        base = f"/maps/{meta.map_id}/{meta.version}"
        return cls(
            map_id=meta.map_id,
            version=meta.version,
            session_id=meta.session_id,
            robot_id=meta.robot_id,
            saved_ns=meta.saved_ns,
            urls=MapUrls(png=f"{base}/map.png", pgm=f"{base}/map.pgm", yaml=f"{base}/map.yaml"),
        )


class SavedMapList(BaseModel):
    maps: list[SavedMap]


class RobotHealth(BaseModel):
    robot_id: str
    alive: bool = Field(description="the agent's liveliness token is present")
    queue_depth: int
    last_scan_ns: int = Field(description="host time of the last received scan, 0 = never")
    session_id: str | None = Field(description="the robot's active session, if any")
    publishers: int = Field(
        0, description="live publishers on the robot's key (per-publisher liveliness tokens)"
    )
    duplicate_publisher: bool = Field(
        False,
        description="a second publisher uses this robot's key now: its scans are refused",
    )
    duplicate_scans_refused: int = Field(
        0, description="scans refused because they came from a second publisher"
    )
    stamps_refused: int = Field(
        0,
        description="scans refused by the time contract: host stamp out of ROS time, or not "
        "after the previous scan mapped in the session (docs/wire-format.md, Time)",
    )
    stamp_gaps: int = Field(
        0, description="scans mapped after a forward stamp jump beyond the gap limit"
    )


class IngestHealth(BaseModel):
    """Ingest limits and counts, summarised: one entry per reason, never one per robot id."""

    robots_tracked: int = Field(description="robots with ingest state (a queue)")
    max_robots: int = Field(
        description="robots without a session tracked at most (robots with one always fit)"
    )
    robots_forgotten: int = Field(description="silent robots without a session forgotten")
    newcomers_queued: int = Field(description="payloads of untracked robots awaiting validation")
    scans_accepted: int
    scans_unmapped: int = Field(description="valid scans of robots without an active session")
    scans_rejected: dict[str, int] = Field(description="refused scans by reason")
    scans_dropped: dict[str, int] = Field(description="scans not processed, by reason")
    stamp_anomalies: dict[str, int] = Field(
        description="time-contract findings of robots with a session, by reason"
    )


class ZenohHealth(BaseModel):
    open: bool
    zid: str | None = None
    peers: int = 0
    routers: int = 0


class FleetConflict(BaseModel):
    instances: list[str] = Field(description="the two instances (this one among them)")
    patterns: list[list[str]] = Field(description="overlapping robot patterns (ours, theirs)")
    robots: list[str] = Field(description="robots with an active session on both")
    detail: str


class FleetHealth(BaseModel):
    instance_id: str
    robots: list[str] = Field(description="the robot-id patterns this instance maps")
    instances_seen: int = Field(description="instances in the last fleet check, this one included")
    conflicts: list[FleetConflict] = Field(description="other instances claiming our robots")


HealthStatus = Literal["ok", "restoring", "degraded"]


class Health(BaseModel):
    """The full health report (with the read token, or when reads are open)."""

    status: HealthStatus
    uptime_s: float
    sessions_active: int
    sessions_total: int
    sessions_restoring: int = Field(description="sessions not replayed yet after a restart")
    sessions_degraded: list[str] = Field(
        description="ids of sessions whose files were found damaged (`degraded` or `damaged`)"
    )
    zenoh: ZenohHealth
    robots: list[RobotHealth]
    ingest: IngestHealth
    fleet: FleetHealth
    warnings: list[str] = Field(
        default_factory=list, description="why the status is not ok, one line each"
    )


class HealthSummary(BaseModel):
    """Health without a read token: the status only (no robot ids, no sessions)."""

    model_config = ConfigDict(extra="forbid")

    status: HealthStatus


class FleetSession(BaseModel):
    session_id: str
    robot_id: str
    state: str
    scans_accepted: int


class FleetInstance(BaseModel):
    instance_id: str
    patterns: list[str]
    http_url: str | None
    started_ns: int
    sessions: list[FleetSession]
    robots_receiving: list[str] = Field(description="robots whose scans reach the instance")


class Fleet(BaseModel):
    instances: list[FleetInstance]
    alive_without_answer: list[str] = Field(
        description="instances whose liveliness token is present but that did not answer"
    )
    conflicts: list[FleetConflict]


class ErrorBody(BaseModel):
    detail: str = Field(description="one-line reason")
    code: str = Field(
        description="machine-readable reason: e.g. not_found, no_pose_yet, unauthorized, "
        "forbidden, conflict, validation_error, invalid_utf8, json_too_deep, invalid_json, "
        "payload_too_large, method_not_allowed"
    )


ERRORS: dict[int, dict[str, str]] = {
    400: {
        "description": "the body is not UTF-8 JSON (`invalid_utf8`, `invalid_json`) or nests "
        "deeper than 32 levels (`json_too_deep`)",
    },
    401: {"description": "missing or wrong bearer token"},
    403: {"description": "the read token on a control operation"},
    404: {"description": "no such resource"},
    409: {"description": "conflicts with the current state (`conflict`, `no_pose_yet`)"},
    413: {"description": "request body too large"},
    422: {"description": "request does not validate"},
    503: {
        "description": "Zenoh is closed or failing (`zenoh_unavailable`), or not now: a session "
        "is restoring or a limit is reached (`unavailable`)",
    },
}

ERROR_SCHEMA_REF = "#/components/schemas/ErrorBody"


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """Error responses of a route, always documented as `application/json`.

    FastAPI would document an error `model` under the route's own media type (`text/plain`
    for a YAML route, `text/event-stream` for SSE), but errors are sent as JSON; so the content
    is spelled out (`create_app` puts ErrorBody into the components).
    """
    return {
        code: {
            "description": ERRORS[code]["description"],
            "content": {"application/json": {"schema": {"$ref": ERROR_SCHEMA_REF}}},
        }
        for code in codes
    }
