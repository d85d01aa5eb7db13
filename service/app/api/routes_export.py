"""`GET /sessions/{id}/recording.mcap`: a session's scans, poses and map as MCAP (ROS 2)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Any

from fastapi import APIRouter
from fastapi.responses import StreamingResponse

from clients.recording import RecordingError, read_messages
from clients.wire import Pose, Scan
from service.app.api.deps import Read
from service.app.api.routes_sessions import NO_STORE, SessionDep
from service.app.api.schemas import errors
from service.mcapio import stream_mcap

log = logging.getLogger(__name__)

router = APIRouter(prefix="/sessions", tags=["sessions"])

MCAP_MEDIA_TYPE = "application/x-mcap"


@router.get(
    "/{session_id}/recording.mcap",
    response_class=StreamingResponse,
    response_model=None,
    dependencies=Read,
    summary="Recording as MCAP (ROS 2 schemas)",
    description="Every scan (`/scan`, sensor_msgs/msg/LaserScan), every pose (`/pose`, "
    "geometry_msgs/msg/PoseStamped, and `/tf`, tf2_msgs/msg/TFMessage map -> "
    "<robot>/base_link), stamped with the scans' stamps, then the current map (`/map`, "
    "nav_msgs/msg/OccupancyGrid). Streamed as it is written; of an active session, what is "
    "recorded when the download reaches it. Messages stamped outside ROS time (before 1970, "
    "after 2038) are left out. A failure once the file has started (a segment gone or "
    "unreadable) aborts the transfer: the response ends without its last chunk, which HTTP "
    "clients report as an error; it never ends as a complete but truncated file.",
    responses={
        200: {"content": {MCAP_MEDIA_TYPE: {}}, "description": "an MCAP file"},
        **errors(401, 404, 422),
    },
)
def read_recording_mcap(session: SessionDep) -> StreamingResponse:
    paths = session.recording_paths()  # segments; none yet after a start or a reset

    def messages() -> Iterator[Scan | Pose]:
        # The headers (200) are sent by now: a failure must reach the client as a broken
        # transfer, never as a well-formed but truncated file. Raising aborts the response
        # without its last chunk, which every HTTP client reports as an error.
        try:
            for path in paths:
                yield from read_messages(path)
        except FileNotFoundError as err:  # pruned or reset meanwhile
            log.error("session %s: export aborted: a segment is gone (%s)", session.id, err)
            raise
        except (RecordingError, OSError) as err:
            log.error("session %s: export aborted: %s", session.id, err)
            raise

    def final_map() -> Any:
        return session.map_image().image

    return StreamingResponse(
        stream_mcap(messages(), final_map),
        media_type=MCAP_MEDIA_TYPE,
        headers={
            **NO_STORE,
            "Content-Disposition": f'attachment; filename="{session.id}.mcap"',
        },
    )
