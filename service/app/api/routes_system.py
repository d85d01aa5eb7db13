"""`/health` and `/metrics`."""

from __future__ import annotations

import dataclasses
import time

from fastapi import APIRouter, Response

from service.app.api.deps import Read, RequestScope, Runtime, Scope
from service.app.api.schemas import (
    Fleet,
    FleetConflict,
    FleetHealth,
    Health,
    HealthStatus,
    HealthSummary,
    IngestHealth,
    RobotHealth,
    ZenohHealth,
    errors,
)
from service.app.errors import TransportError, UnauthorizedError

router = APIRouter(tags=["system"])

PROMETHEUS_TEXT = "text/plain; version=0.0.4; charset=utf-8"


@router.get(
    "/health",
    response_model=Health | HealthSummary,
    summary="Health",
    description="`ok`; `restoring` while sessions are replayed after a restart (HTTP 200: the "
    "service is alive and serves what is ready); `degraded` (with `warnings`) when Zenoh is "
    "closed, recording/fsync failed, a session's files were found damaged "
    "(`sessions_degraded`), another instance claims this one's robots (`fleet.conflicts`), or a "
    "second publisher uses a robot's key; plus per-robot ingest status and the ingest's limits "
    "and counts by reason (`ingest`). When the service has a "
    "read token, a request without a token gets the status only (no robot ids); a wrong token "
    "is 401.",
    responses=errors(401),
)
def health(runtime: Runtime, scope: RequestScope) -> Health | HealthSummary:
    report = _health(runtime)
    if runtime.settings.read_token is not None:
        if scope is Scope.NONE:
            return HealthSummary(status=report.status)
        if scope is Scope.WRONG:
            raise UnauthorizedError("wrong token")
    return report


def _health(runtime: Runtime) -> Health:
    zenoh_info = ZenohHealth(**runtime.zenoh_info())
    alive = runtime.alive_robots()
    robots = {r.robot_id: r for r in runtime.ingest.robots()}
    active = {s.robot_id: s.id for s in runtime.sessions.list() if s.is_active}
    publishers = {p.robot_id: p for p in runtime.publisher_status()}
    views = []
    for robot_id in sorted(set(robots) | alive | set(active) | set(publishers)):
        queue = robots.get(robot_id)
        pub = publishers.get(robot_id)
        views.append(
            RobotHealth(
                robot_id=robot_id,
                alive=robot_id in alive,
                queue_depth=queue.queue_depth if queue is not None else 0,
                last_scan_ns=queue.last_received_ns if queue is not None else 0,
                session_id=active.get(robot_id),
                publishers=pub.publishers if pub is not None else 0,
                duplicate_publisher=pub.conflict if pub is not None else False,
                duplicate_scans_refused=pub.refused if pub is not None else 0,
                stamps_refused=queue.stamps_refused if queue is not None else 0,
                stamp_gaps=queue.stamp_gaps if queue is not None else 0,
            )
        )
    conflicts = runtime.fleet.conflicts()
    fleet = FleetHealth(
        instance_id=runtime.instance_id,
        robots=list(runtime.patterns.patterns),
        instances_seen=len(runtime.fleet.last_view().instances),
        conflicts=[FleetConflict(**c.to_json()) for c in conflicts],
    )
    warnings = []
    if not zenoh_info.open:
        warnings.append("the Zenoh session is closed")
    if runtime.fsync_errors:
        warnings.append(f"{runtime.fsync_errors} fsync failures")
    if runtime.ingest.store_errors:
        warnings.append(f"{runtime.ingest.store_errors} scans could not be recorded")
    if conflicts:
        warnings.append(f"{len(conflicts)} other instance(s) claim this instance's robots")
    duplicates = [v.robot_id for v in views if v.duplicate_publisher]
    if duplicates:
        warnings.append("a second publisher uses the key of: " + ", ".join(duplicates))
    sessions = runtime.sessions.list()
    damaged = [s.id for s in sessions if s.status in ("degraded", "damaged")]
    restoring = sum(1 for s in sessions if s.status == "restoring")
    if damaged:
        warnings.append(f"{len(damaged)} session(s) with damaged files")
    status: HealthStatus = "degraded" if warnings else "restoring" if restoring else "ok"
    return Health(
        status=status,
        uptime_s=max(0.0, (time.time_ns() - runtime.started_ns) / 1e9),
        sessions_active=len(active),
        sessions_total=len(sessions),
        sessions_restoring=restoring,
        sessions_degraded=damaged,
        zenoh=zenoh_info,
        robots=views,
        ingest=IngestHealth(**dataclasses.asdict(runtime.ingest.summary())),
        fleet=fleet,
        warnings=warnings,
    )


@router.get(
    "/fleet",
    response_model=Fleet,
    summary="Every mapping-service instance on the Zenoh network",
    description="Asks `<prefix>/_instances/*/sessions` on Zenoh now (up to 2 s): each "
    "instance's robot patterns, sessions and robots, and conflicts between instances. "
    "The same view as `mapctl fleet --zenoh-connect ENDPOINT`. 503 when Zenoh is closed.",
    dependencies=Read,
    responses=errors(401, 503),
)
def fleet(runtime: Runtime) -> Fleet:
    try:
        view = runtime.fleet.query()
    except Exception as err:  # Zenoh closed or failing
        raise TransportError(f"cannot query the fleet on Zenoh: {err}") from err
    return Fleet.model_validate(view.to_json())


@router.get(
    "/metrics",
    response_class=Response,
    response_model=None,
    dependencies=Read,
    summary="Prometheus metrics",
    description="Prometheus text format 0.0.4: scans accepted / rejected by reason / unmapped / "
    "dropped, queue depths, per-scan processing time, pose subscribers and drops. Needs the "
    "read token when the service has one (Prometheus: `authorization: {credentials_file: ...}`).",
    responses={200: {"content": {PROMETHEUS_TEXT: {"schema": {"type": "string"}}}}, **errors(401)},
)
def metrics(runtime: Runtime) -> Response:
    return Response(runtime.metrics.render(), media_type=PROMETHEUS_TEXT)
