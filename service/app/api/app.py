"""`create_app(runtime)`: the FastAPI application over a started `MappingRuntime`."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path
from typing import Any, Final

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
from fastapi_offline import FastAPIOffline
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import BaseRoute
from starlette.types import ASGIApp, Message, Receive, Scope, Send

import service
from service.app.api import routes_export, routes_maps, routes_sessions, routes_system
from service.app.api.schemas import ErrorBody
from service.app.errors import ServiceError, StoreError, UnavailableError
from service.app.runtime import MappingRuntime

log = logging.getLogger(__name__)

DESCRIPTION = """\
Maps buildings from the 2D laser scans robots publish over Zenoh
(`<prefix>/<robot_id>/scan`). A **session** maps one robot; its poses are published on
`<prefix>/<robot_id>/pose` and streamed here. Control operations (create, stop, reset, save,
delete) need `Authorization: Bearer <control token>` when the service has a token. When the
service has a read token, every read needs `Authorization: Bearer <read or control token>`
(the pose stream also takes `?access_token=`); `/health` without a token is the status only.
Errors are JSON `{"detail": "<one-line reason>", "code": "<machine-readable code>"}`.
"""

# The live map page: the only files served besides the API (no catch-all mount at `/`, whose
# 405 would answer for API paths with the wrong `Allow`).
WEB_FILES: Final = {
    "index.html": "text/html; charset=utf-8",
    "app.js": "text/javascript; charset=utf-8",
    "style.css": "text/css; charset=utf-8",
    "favicon.svg": "image/svg+xml",
}
_STATUS_CODES: Final = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    409: "conflict",
    413: "payload_too_large",
    422: "validation_error",
    503: "unavailable",
}

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
        if isinstance(exc, UnavailableError) and exc.retry_after_s is not None:
            headers = {"Retry-After": str(exc.retry_after_s)}
        return error_response(exc.status, exc.reason, exc.code, headers)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        return error_response(422, _one_line(exc), "validation_error")

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            # Starlette names the methods of the first route whose path matched; every route
            # of that path counts.
            headers["Allow"] = ", ".join(allowed_methods(all_routes, request.url.path))
        return error_response(
            exc.status_code,
            str(exc.detail),
            _STATUS_CODES.get(exc.status_code, "error"),
            headers or None,
        )

    routers = (
        routes_sessions.router,
        routes_export.router,
        routes_maps.router,
        routes_system.router,
    )
    for router in routers:
        app.include_router(router)
    _add_web_routes(app)
    # For `Allow`: the routers' own routes carry their full paths (FastAPI keeps included
    # routers as lazy wrappers in app.routes).
    all_routes = [*app.routes, *(r for router in routers for r in router.routes)]

    default_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = default_openapi()
            schemas = schema.setdefault("components", {}).setdefault("schemas", {})
            schemas.setdefault("ErrorBody", ErrorBody.model_json_schema())
            # /health answers without a token too (the status only).
            get = schema["paths"]["/health"]["get"]
            get["security"] = [{}, *get.get("security", [])]
        return app.openapi_schema or {}

    app.openapi = openapi  # type: ignore[method-assign]
    return app


def error_response(
    status: int, detail: str, code: str, headers: dict[str, str] | None = None
) -> JSONResponse:
    return JSONResponse({"detail": detail, "code": code}, status_code=status, headers=headers)


def allowed_methods(routes: Sequence[BaseRoute], path: str) -> list[str]:
    """Every method of the routes whose path pattern matches `path` (for `Allow`)."""
    methods: set[str] = set()
    for route in routes:
        pattern = getattr(route, "path_regex", None)
        route_methods = getattr(route, "methods", None)
        if pattern is not None and route_methods and pattern.match(path):
            methods.update(route_methods)
    return sorted(methods)


def _add_web_routes(app: FastAPI) -> None:
    """`/` and the page's own files (no data in them: open like /docs)."""
    static = web_dir()
    if static is None:

        @app.get("/", include_in_schema=False)
        def index() -> HTMLResponse:
            return HTMLResponse(_FALLBACK_PAGE)

        return

    def server(name: str) -> Callable[[], FileResponse]:
        def serve() -> FileResponse:
            return FileResponse(static / name, media_type=WEB_FILES[name])

        return serve

    methods = ["GET", "HEAD"]  # HEAD for probes that check the page
    app.add_api_route("/", server("index.html"), methods=methods, include_in_schema=False)
    for name in WEB_FILES:
        app.add_api_route(f"/{name}", server(name), methods=methods, include_in_schema=False)


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
    response = error_response(status, detail, _STATUS_CODES.get(status, "error"))
    await response(scope, receive, send)


def _one_line(exc: RequestValidationError) -> str:
    parts = []
    for err in exc.errors()[:3]:
        loc = ".".join(str(p) for p in err.get("loc", ()) if p != "body") or "body"
        parts.append(f"{loc}: {err.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"
