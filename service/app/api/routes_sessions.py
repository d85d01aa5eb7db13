"""`/sessions`: create, list, control, poses, trajectory, live map and pose stream."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Path, Query, Response
from fastapi.responses import PlainTextResponse
from starlette.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from clients.wire import Pose
from service.app import render
from service.app.api.bodies import JsonBodyRoute
from service.app.api.deps import Control, Read, ReadOrQuery, Runtime, Sessions, get_sessions
from service.app.api.schemas import (
    ID_PATTERN,
    Graph,
    PoseView,
    SavedMap,
    Session,
    SessionCreate,
    SessionList,
    Trajectory,
    errors,
)
from service.app.errors import ConflictError
from service.app.fanout import PoseStream
from service.app.sessions import MappingSession, SessionManager

router = APIRouter(prefix="/sessions", tags=["sessions"], route_class=JsonBodyRoute)

SessionId = Annotated[
    str, Path(pattern=ID_PATTERN, max_length=64, description="a session id from POST /sessions")
]
NO_STORE = {"Cache-Control": "no-store"}
# 1,000 poses is ~250 KB of JSON: 25 s of a 40 Hz robot per page.
TRAJECTORY_PAGE = 1000
TRAJECTORY_PAGE_MAX = 10_000


def get_session(session_id: SessionId, sessions: Sessions) -> MappingSession:
    return sessions.get(session_id)


SessionDep = Annotated[MappingSession, Depends(get_session)]


@router.post(
    "",
    status_code=201,
    response_model=Session,
    dependencies=Control,
    summary="Start a mapping session",
    description="Start mapping `robot_id`: its scans are recorded and mapped from now on. "
    "One active session per robot (409 otherwise), on an instance whose robot patterns match "
    "it and not while another instance maps it (409). 503 at the robot or descriptor limit "
    "(nothing is created).",
    responses=errors(400, 401, 403, 409, 413, 422, 503),
)
def create_session(body: SessionCreate, sessions: Sessions, runtime: Runtime) -> Session:
    runtime.check_claim(body.robot_id)
    session = sessions.create(body.robot_id, body.resolution_m, body.use_odometry)
    return Session.of(session.info())


@router.get(
    "",
    response_model=SessionList,
    dependencies=Read,
    responses=errors(401),
    summary="List sessions",
    description="Every session of this service, active and stopped, oldest first.",
)
def list_sessions(sessions: Sessions) -> SessionList:
    return SessionList(sessions=[Session.of(s.info()) for s in sessions.list()])


@router.get(
    "/{session_id}",
    response_model=Session,
    dependencies=Read,
    summary="Get a session",
    description="State, counters and last pose of one session.",
    responses=errors(401, 404, 422),
)
def read_session(session: SessionDep) -> Session:
    return Session.of(session.info())


@router.delete(
    "/{session_id}",
    status_code=204,
    response_class=Response,
    response_model=None,
    dependencies=Control,
    summary="Delete a session",
    description="Stop the session and delete its recording, its map and its saved map "
    "versions (`/maps/<session id>/...`); `?keep_maps=true` keeps the saved maps.",
    responses=errors(401, 403, 404, 422, 503),
)
def delete_session(
    session_id: SessionId,
    sessions: Sessions,
    runtime: Runtime,
    keep_maps: Annotated[bool, Query(description="keep the session's saved maps")] = False,
) -> Response:
    sessions.delete(session_id, keep_maps=keep_maps)
    runtime.fanout.end_streams_threadsafe(session_id)
    return Response(status_code=204)


@router.post(
    "/{session_id}/stop",
    response_model=Session,
    dependencies=Control,
    summary="Stop a session",
    description="Stop mapping; the map, trajectory and recording stay available. "
    "The robot may then get a new session.",
    responses=errors(401, 403, 404, 422),
)
def stop_session(session_id: SessionId, sessions: Sessions) -> Session:
    return Session.of(sessions.stop(session_id).info())


@router.post(
    "/{session_id}/reset",
    response_model=Session,
    dependencies=Control,
    summary="Reset a session",
    description="Forget the map and the trajectory; the next scan defines a new map frame.",
    responses=errors(401, 403, 404, 422),
)
def reset_session(session_id: SessionId, sessions: Sessions) -> Session:
    return Session.of(sessions.reset(session_id).info())


@router.post(
    "/{session_id}/save",
    status_code=201,
    response_model=SavedMap,
    dependencies=Control,
    summary="Save the map",
    description="Store a snapshot of the map (PNG, PGM + YAML) as the next version of map "
    "`map_id` (= the session id); download it later from `/maps`.",
    responses=errors(401, 403, 404, 422),
)
def save_session(session_id: SessionId, sessions: Sessions) -> SavedMap:
    return SavedMap.of(sessions.save(session_id))


@router.get(
    "/{session_id}/pose",
    response_model=PoseView,
    dependencies=Read,
    summary="Current pose",
    description="The latest pose (map frame: metres, radians). `404` (`not_found`): no such "
    "session; `409` (`no_pose_yet`): the session exists but has no pose yet (retry later); "
    "`503` (`unavailable`) with `Retry-After`: the session is still being restored after a "
    "restart.",
    responses=errors(401, 404, 409, 422, 503),
)
def read_pose(session: SessionDep) -> PoseView:
    pose = session.pose_for_read()
    if pose is None:
        raise ConflictError(f"session {session.id} has no pose yet", code="no_pose_yet")
    return PoseView.of(pose)


@router.get(
    "/{session_id}/trajectory",
    response_model=Trajectory,
    dependencies=Read,
    summary="Trajectory (paged)",
    description="The session's poses in order, one page at a time: those with "
    f"`sequence >= since_seq`, at most `limit` (default {TRAJECTORY_PAGE}, at most "
    f"{TRAJECTORY_PAGE_MAX}), only every `every`-th sequence (decimation: sequences that are "
    "multiples of `every`). `next_seq` is the `since_seq` of the next page (null at the end). "
    "As JSON, or as TUM text (`stamp x y z qx qy qz qw`, readable by evo) with `?format=tum`, "
    "where the next page's `since_seq` is in the `X-Next-Seq` header (absent at the end).",
    responses={
        200: {"content": {"text/plain": {"schema": {"type": "string"}}}},
        **errors(401, 404, 422, 503),
    },
)
def read_trajectory(
    session: SessionDep,
    format: Annotated[  # the query parameter's public name
        Literal["json", "tum"], Query(description="json (default) or tum")
    ] = "json",
    since_seq: Annotated[int, Query(ge=0, description="first sequence wanted")] = 0,
    limit: Annotated[
        int, Query(ge=1, le=TRAJECTORY_PAGE_MAX, description="poses per page at most")
    ] = TRAJECTORY_PAGE,
    every: Annotated[
        int, Query(ge=1, le=1_000_000, description="only sequences that are multiples of this")
    ] = 1,
) -> Trajectory | Response:
    poses, next_seq, total = session.trajectory_page(since_seq, limit, every)
    if format == "tum":
        headers = dict(NO_STORE)
        if next_seq is not None:
            headers["X-Next-Seq"] = str(next_seq)
        return PlainTextResponse(render.trajectory_tum(poses), headers=headers)
    return Trajectory(
        session_id=session.id,
        poses=[PoseView.of(p) for p in poses],
        next_seq=next_seq,
        total=total,
    )


@router.get(
    "/{session_id}/graph",
    response_model=Graph,
    dependencies=Read,
    summary="Pose graph (loop closure)",
    description="The back end's pose graph: every node (its optimised pose and the front "
    "end's), the sequential edges, the accepted loop closures and the latest refused searches "
    "(with their score and reason), and the counters. Empty (no nodes) with loop closure off. "
    "The trajectory, the pose and the map are drawn from the same graph. `?nodes=false` "
    "leaves out the nodes and edges (the live page polls the closures and counters).",
    responses=errors(401, 404, 422, 503),
)
def read_graph(
    session: SessionDep,
    nodes: Annotated[bool, Query(description="include the nodes and edges")] = True,
) -> Graph:
    return Graph.of(session.id, session.graph(), nodes=nodes)


_PNG: dict[int | str, dict[str, Any]] = {
    200: {"content": {"image/png": {}}, "description": "the map as PNG"}
}


@router.get(
    "/{session_id}/map.png",
    response_class=Response,
    response_model=None,
    dependencies=Read,
    summary="Map as PNG",
    description="The occupancy map (white free, black occupied, grey unknown), optionally with "
    "the trajectory and the robot drawn on it.",
    responses={**_PNG, **errors(401, 404, 422)},
)
def read_map_png(
    session: SessionDep,
    trajectory: Annotated[bool, Query(description="draw the trajectory")] = False,
    robot: Annotated[bool, Query(description="draw the robot's last pose")] = False,
) -> Response:
    snapshot = session.map_snapshot() if trajectory or robot else session.map_image()
    png = render.map_png(snapshot, trajectory=trajectory, robot=robot)
    return Response(png, media_type="image/png", headers=NO_STORE)


@router.get(
    "/{session_id}/map.pgm",
    response_class=Response,
    response_model=None,
    dependencies=Read,
    summary="Map as PGM (ROS map_server)",
    description="The occupancy map as a binary PGM, to pair with `map.yaml`.",
    responses={
        200: {"content": {"image/x-portable-graymap": {}}, "description": "PGM"},
        **errors(401, 404, 422),
    },
)
def read_map_pgm(session: SessionDep) -> Response:
    pgm = render.map_pgm(session.map_image())
    return Response(pgm, media_type="image/x-portable-graymap", headers=NO_STORE)


@router.get(
    "/{session_id}/map.yaml",
    response_class=Response,
    response_model=None,
    dependencies=Read,
    summary="Map metadata (ROS map_server YAML)",
    description="Resolution, origin [x, y, yaw] and thresholds; the image is `map.pgm`.",
    responses={
        200: {"content": {"application/yaml": {}}, "description": "YAML"},
        **errors(401, 404, 422),
    },
)
def read_map_yaml(session: SessionDep) -> Response:
    text = render.map_yaml(session.map_image())
    return Response(text, media_type="application/yaml", headers=NO_STORE)


def sse_pose_frame(pose: Pose) -> bytes:
    """One pose as an SSE frame: encoded once per pose, written to every stream of its session."""
    data = PoseView.of(pose).model_dump_json()
    return f"event: pose\ndata: {data}\nid: {pose.seq}\n\n".encode()


@router.get(
    "/{session_id}/pose/stream",
    response_class=StreamingResponse,
    dependencies=ReadOrQuery,
    summary="Live poses (Server-Sent Events)",
    description="`event: pose` with a `PoseView` JSON as `data` for every new pose, starting "
    "with the current one. Poses that arrive together are written together (at most one write "
    "per `MAPPING_SSE_INTERVAL_S`, default 0.2 s, and longer when more streams are open than "
    "`MAPPING_SSE_MAX_WRITES_PER_S` allows at that interval). A slow reader loses the oldest poses "
    "(counted in /metrics), never slows the service. Comment lines (`: ping`) keep idle "
    "connections open. With a read token, the token may also be given as `?access_token=` "
    "(EventSource cannot set headers).",
    responses={
        200: {
            "content": {
                "text/event-stream": {
                    # No `schema`: under OpenAPI 3.2 rules it would describe the whole stream
                    "example": 'event: pose\ndata: {"session_id": "s-...", "x": 1.0}\n\n',
                }
            },
            "description": "an endless event stream",
        },
        **errors(401, 404, 422),
    },
)
async def stream_poses(
    session: Annotated[MappingSession, Depends(get_session)],
    runtime: Runtime,
) -> StreamingResponse:
    fanout = runtime.fanout
    stream = fanout.open_stream(session.id)
    last = session.last_pose  # after subscribing, so nothing falls in between
    first = b""
    if last is not None:
        stream.skip = (last.seq, last.stamp_ns)
        first = sse_pose_frame(last)

    return PoseStreamResponse(stream, first, fanout.close_stream)


class PoseStreamResponse(StreamingResponse):
    """The pose stream as a bare ASGI loop: one `send` per chunk.

    `StreamingResponse` runs an async generator inside an anyio task group for every response
    and goes through both per chunk; with 1,000 streams that machinery was most of the HTTP
    loop's work, on the process (and GIL) that also receives every scan. A disconnect is
    noticed by a task waiting on `receive()`, which ends the stream.
    """

    def __init__(
        self, stream: PoseStream, first: bytes, on_close: Callable[[PoseStream], None]
    ) -> None:
        super().__init__(
            iter(()),  # not used: __call__ writes the stream's chunks itself
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
        )
        self._stream = stream
        self._first = first
        self._on_close = on_close

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        stream = self._stream

        async def watch() -> None:
            while (await receive())["type"] != "http.disconnect":
                pass
            stream.end()

        watcher = asyncio.ensure_future(watch())
        try:
            await send(
                {
                    "type": "http.response.start",
                    "status": self.status_code,
                    "headers": self.raw_headers,
                }
            )
            chunk: bytes | None = self._first
            while chunk is not None:
                if chunk:
                    await send({"type": "http.response.body", "body": chunk, "more_body": True})
                chunk = await stream.next_chunk()
            await send({"type": "http.response.body", "body": b"", "more_body": False})
        except OSError:  # the connection went away under the write
            pass
        finally:
            watcher.cancel()
            self._on_close(stream)


__all__ = ["SessionManager", "get_sessions", "router"]
