"""`create_app(runtime)`: the FastAPI application over a started `MappingRuntime`."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

import service
from service.app.api import routes_export, routes_maps, routes_sessions, routes_system
from service.app.errors import ServiceError, StoreError
from service.app.runtime import MappingRuntime

log = logging.getLogger(__name__)

DESCRIPTION = """\
Maps buildings from the 2D laser scans robots publish over Zenoh
(`<prefix>/<robot_id>/scan`). A **session** maps one robot; its poses are published on
`<prefix>/<robot_id>/pose` and streamed here. Control operations (create, stop, reset, save,
delete) need `Authorization: Bearer <token>` when the service has a token. Errors are JSON
`{"detail": "<one-line reason>"}`.
"""

_FALLBACK_PAGE = """<!doctype html><meta charset="utf-8"><title>Mapping service</title>
<p>The live map page is not installed. API: <a href="/docs">/docs</a>.</p>"""


def web_dir() -> Path | None:
    """The packaged live map page (`service/web`), if present."""
    path = Path(str(resources.files(service).joinpath("web")))
    return path if (path / "index.html").is_file() else None


def create_app(runtime: MappingRuntime) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        runtime.fanout.bind_loop(asyncio.get_running_loop(), routes_sessions.sse_pose_frame)
        try:
            yield
        finally:
            runtime.fanout.end_streams()
            runtime.fanout.bind_loop(None)

    # Swagger UI and ReDoc assets served from the package, not a CDN: /docs works offline.
    app = FastAPIOffline(
        title="Manhattan Mapper service",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
        openapi_tags=[
            {"name": "sessions", "description": "Mapping sessions: control, poses, live maps."},
            {"name": "maps", "description": "Saved, versioned maps."},
            {"name": "system", "description": "Health and metrics."},
        ],
    )
    app.state.runtime = runtime
    app.add_middleware(BodyLimitMiddleware, max_bytes=runtime.settings.http.max_body_bytes)

    @app.exception_handler(ServiceError)
    async def service_error(request: Request, exc: ServiceError) -> JSONResponse:
        if isinstance(exc, StoreError):
            log.error("%s %s: %s", request.method, request.url.path, exc.reason)
        headers = {"WWW-Authenticate": "Bearer"} if exc.status == 401 else None
        return JSONResponse({"detail": exc.reason}, status_code=exc.status, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": _one_line(exc)}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        return JSONResponse(
            {"detail": str(exc.detail)}, status_code=exc.status_code, headers=exc.headers
        )

    app.include_router(routes_sessions.router)
    app.include_router(routes_export.router)
    app.include_router(routes_maps.router)
    app.include_router(routes_system.router)

    # Mounted last so that the API routes win.
    static = web_dir()
    if static is not None:
        app.mount("/", StaticFiles(directory=static, html=True), name="web")
    else:

        @app.get("/", include_in_schema=False)
        def index() -> HTMLResponse:
            return HTMLResponse(_FALLBACK_PAGE)

    return app


class BodyLimitMiddleware:
    """Refuse request bodies above `max_bytes` with a JSON 413, declared or streamed."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length")
        if declared is not None:
            if not (declared.isascii() and declared.isdigit()):  # int() refuses '¹'
                await _reply(scope, receive, send, 400, "invalid Content-Length header")
                return
            if int(declared) > self.max_bytes:
                await _reply(scope, receive, send, 413, self._too_large())
                return
        total = 0

        async def limited_receive() -> Message:
            nonlocal total
            message = await receive()
            if message["type"] == "http.request":
                total += len(message.get("body", b""))
                if total > self.max_bytes:
                    # FastAPI re-raises HTTPException from body reading; our handler answers.
                    raise StarletteHTTPException(413, self._too_large())
            return message

        await self.app(scope, limited_receive, send)

    def _too_large(self) -> str:
        return f"request body larger than {self.max_bytes} bytes"


async def _reply(scope: Scope, receive: Receive, send: Send, status: int, detail: str) -> None:
    await JSONResponse({"detail": detail}, status_code=status)(scope, receive, send)


def _one_line(exc: RequestValidationError) -> str:
    parts = []
    for err in exc.errors()[:3]:
        loc = ".".join(str(p) for p in err.get("loc", ()) if p != "body") or "body"
        parts.append(f"{loc}: {err.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"
