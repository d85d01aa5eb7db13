"""`/health` and `/metrics`."""

from __future__ import annotations

import time

from fastapi import APIRouter, Response

from service.app.api.deps import Runtime
from service.app.api.schemas import Health, RobotHealth, ZenohHealth

router = APIRouter(tags=["system"])

PROMETHEUS_TEXT = "text/plain; version=0.0.4; charset=utf-8"


@router.get(
    "/health",
    response_model=Health,
    summary="Health",
    description="`ok`, or `degraded` when Zenoh is closed or recording/fsync failed; plus "
    "per-robot ingest status.",
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
    ok = zenoh_info.open and runtime.fsync_errors == 0 and runtime.ingest.store_errors == 0
    return Health(
        status="ok" if ok else "degraded",
        uptime_s=max(0.0, (time.time_ns() - runtime.started_ns) / 1e9),
        sessions_active=len(active),
        sessions_total=len(runtime.sessions.list()),
        zenoh=zenoh_info,
        robots=views,
    )


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
