"""`/health` and `/metrics`."""

from __future__ import annotations

import time

from fastapi import APIRouter, Response

from service.app.api.deps import Runtime
from service.app.api.schemas import (
    Fleet,
    FleetConflict,
    FleetHealth,
    Health,
    RobotHealth,
    ZenohHealth,
)
from service.app.errors import TransportError

router = APIRouter(tags=["system"])

PROMETHEUS_TEXT = "text/plain; version=0.0.4; charset=utf-8"


@router.get(
    "/health",
    response_model=Health,
    summary="Health",
    description="`ok`, or `degraded` when Zenoh is closed, recording/fsync failed, or another "
    "instance claims this one's robots (`fleet.conflicts`); plus per-robot ingest status.",
)
def health(runtime: Runtime) -> Health:
    zenoh_info = ZenohHealth(**runtime.zenoh_info())
    alive = runtime.alive_robots()
    robots = {r.robot_id: r for r in runtime.ingest.robots()}
    active = {s.robot_id: s.id for s in runtime.sessions.list() if s.is_active}
    views = [
        RobotHealth(
            robot_id=robot_id,
            alive=robot_id in alive,
            queue_depth=robots[robot_id].queue_depth if robot_id in robots else 0,
            last_scan_ns=robots[robot_id].last_received_ns if robot_id in robots else 0,
            session_id=active.get(robot_id),
        )
        for robot_id in sorted(set(robots) | alive | set(active))
    ]
    conflicts = runtime.fleet.conflicts()
    fleet = FleetHealth(
        instance_id=runtime.instance_id,
        robots=list(runtime.patterns.patterns),
        instances_seen=len(runtime.fleet.last_view().instances),
        conflicts=[FleetConflict(**c.to_json()) for c in conflicts],
    )
    ok = (
        zenoh_info.open
        and runtime.fsync_errors == 0
        and runtime.ingest.store_errors == 0
        and not conflicts
    )
    return Health(
        status="ok" if ok else "degraded",
        uptime_s=max(0.0, (time.time_ns() - runtime.started_ns) / 1e9),
        sessions_active=len(active),
        sessions_total=len(runtime.sessions.list()),
        zenoh=zenoh_info,
        robots=views,
        fleet=fleet,
    )


@router.get(
    "/fleet",
    response_model=Fleet,
    summary="Every mapping-service instance on the Zenoh network",
    description="Asks `<prefix>/_instances/*/sessions` on Zenoh now (up to 2 s): each "
    "instance's robot patterns, sessions and robots, and conflicts between instances. "
    "The same view as `mapctl fleet --zenoh-connect ENDPOINT`. 503 when Zenoh is closed.",
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
    summary="Prometheus metrics",
    description="Prometheus text format 0.0.4: scans accepted / rejected by reason / unmapped / "
    "dropped, queue depths, per-scan processing time, pose subscribers and drops.",
    responses={200: {"content": {PROMETHEUS_TEXT: {"schema": {"type": "string"}}}}},
)
def metrics(runtime: Runtime) -> Response:
    return Response(runtime.metrics.render(), media_type=PROMETHEUS_TEXT)
