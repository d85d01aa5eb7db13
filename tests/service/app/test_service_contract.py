"""The OpenAPI document and the server agree (issue 16, "smaller findings").

One test per finding of the schemathesis review, in process; then schemathesis itself against a
live `mapping-service serve` (bounded, deterministic), so that the two cannot drift apart again.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from svc_testkit import (  # noqa: F401  # *_fixture: pytest fixtures used by name
    ServiceProc,
    client_fixture,
    runtime_factory_fixture,
    runtime_fixture,
)

CONTROL = "control-token-0123456789"
READ = "read-token-0123456789abc"


def test_error_media_types_match_the_openapi_document(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            for status, response in operation["responses"].items():
                if status.startswith(("4", "5")):
                    assert list(response["content"]) == ["application/json"], (
                        method,
                        path,
                        status,
                    )
    # What is sent: JSON errors where the success is YAML or an event stream.
    for path in ("/sessions/nope/map.yaml", "/sessions/nope/pose/stream", "/maps/x/1/map.yaml"):
        r = client.get(path)
        assert r.status_code == 404, path
        assert r.headers["content-type"] == "application/json", path
        assert r.json()["code"] == "not_found", path


@pytest.mark.parametrize(
    ("method", "path", "allow"),
    [
        ("OPTIONS", "/sessions", "GET, POST"),
        ("PUT", "/sessions", "GET, POST"),
        ("PUT", "/sessions/s-1", "DELETE, GET"),
        ("OPTIONS", "/sessions/s-1/pose", "GET"),
        ("PATCH", "/maps", "GET"),
        ("DELETE", "/health", "GET"),
        ("POST", "/", "GET, HEAD"),
    ],
)
def test_unsupported_methods_name_the_routes_methods(
    client: TestClient, method: str, path: str, allow: str
) -> None:
    r = client.request(method, path)
    assert r.status_code == 405
    assert r.headers["allow"] == allow
    assert r.json()["code"] == "method_not_allowed"


def test_the_page_is_still_served(client: TestClient) -> None:
    for path, kind in (
        ("/", "text/html"),
        ("/index.html", "text/html"),
        ("/app.js", "text/javascript"),
        ("/style.css", "text/css"),
        ("/favicon.svg", "image/svg+xml"),
    ):
        r = client.get(path)
        assert r.status_code == 200, path
        assert r.headers["content-type"].startswith(kind), path
        assert client.head(path).status_code == 200, path
    assert client.get("/nope.js").status_code == 404


@pytest.mark.parametrize(
    ("body", "code"),
    [
        (b'{"robot_id": "\xff\xfe"}', "invalid_utf8"),
        (b"[" * 5000 + b"]" * 5000, "json_too_deep"),
        (b'{"robot_id": {"a": ' * 40 + b"1" + b"}" * 40 + b"}", "json_too_deep"),
        (b'{"robot_id": ', "invalid_json"),
    ],
)
def test_bodies_that_are_not_json_are_a_documented_400(
    client: TestClient, body: bytes, code: str
) -> None:
    r = client.post("/sessions", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 400
    assert r.json()["code"] == code
    documented = client.get("/openapi.json").json()["paths"]["/sessions"]["post"]["responses"]
    assert code in documented["400"]["description"]
    # Deep but legal nesting inside strings is not nesting.
    ok = client.post("/sessions", json={"robot_id": "deep-ok", "pad": "[" * 100})
    assert ok.status_code == 422  # unknown field, not a 400


def test_pose_tells_no_session_from_no_pose_yet(client: TestClient) -> None:
    missing = client.get("/sessions/s-missing/pose")
    assert (missing.status_code, missing.json()["code"]) == (404, "not_found")
    sid = client.post("/sessions", json={"robot_id": "amr-5"}).json()["id"]
    waiting = client.get(f"/sessions/{sid}/pose")
    assert (waiting.status_code, waiting.json()["code"]) == (409, "no_pose_yet")
    spec = client.get("/openapi.json").json()
    responses = spec["paths"]["/sessions/{session_id}/pose"]["get"]["responses"]
    assert {"404", "409"} <= set(responses)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("resolution_m", "0.05"),
        ("use_odometry", "yes"),
        ("use_odometry", 1),
        ("use_odometry", "true"),
        ("robot_id", 7),
    ],
)
def test_request_bodies_have_strict_types(client: TestClient, field: str, value: object) -> None:
    body = {"robot_id": "amr-6", field: value}
    r = client.post("/sessions", json=body)
    assert r.status_code == 422, r.text
    assert field in r.json()["detail"]


@pytest.mark.parametrize("literal", [b"NaN", b"Infinity", b"-Infinity"])
def test_a_resolution_that_is_not_finite_is_named_so(client: TestClient, literal: bytes) -> None:
    # Python's JSON parser takes these literals; the answer must not be about a bound.
    body = b'{"robot_id": "amr-8", "resolution_m": ' + literal + b"}"
    r = client.post("/sessions", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "resolution_m" in detail
    assert "finite number" in detail
    assert "less than" not in detail
    assert "greater than" not in detail


def test_strict_types_still_take_json_numbers(client: TestClient) -> None:
    body = {"robot_id": "amr-7", "resolution_m": 1, "use_odometry": False}
    r = client.post("/sessions", json=body)
    assert r.status_code == 201, r.text
    assert (r.json()["resolution_m"], r.json()["use_odometry"]) == (1.0, False)


# The coverage phase tries these methods on every path (the default list adds TRACE etc.).
SCHEMATHESIS_CONFIG = """
[phases.coverage]
unexpected-methods = ["OPTIONS", "PUT", "PATCH", "DELETE", "POST"]
"""


def schemathesis(config: Path, url: str, *args: str) -> subprocess.CompletedProcess[str]:
    # cwd: schemathesis keeps a cache (.schemathesis/) in its working directory.
    return subprocess.run(
        [
            str(Path(sys.executable).with_name("schemathesis")),
            "--config-file",
            str(config),
            "run",
            f"{url}/openapi.json",
            "--checks",
            "all",
            "--max-examples",
            "3",
            "--generation-deterministic",
            # One worker: hypothesis' lambda-source inspection in two threads hits a CPython
            # 3.11 race ("AST constructor recursion depth mismatch").
            "--workers",
            "1",
            "--header",
            f"Authorization: Bearer {CONTROL}",
            "--no-color",
            *args,
        ],
        capture_output=True,
        text=True,
        timeout=100,
        check=False,
        cwd=config.parent,
    )


@pytest.mark.slow
@pytest.mark.timeout(240)  # 20-40 s here; the bound is for a machine loaded by other work
def test_schemathesis_finds_nothing(tmp_path: Path) -> None:
    """schemathesis (every check, deterministic generation) against a live service with both
    tokens; it also checks that each operation that declares security refuses requests
    without the token. ~380 requests, 5-10 s.

    The pose stream runs apart: schemathesis reads an event stream until its request
    timeout, and the stateful phase opens streams of sessions it created (an endless stream
    each); alone, with no session to stream, its error answers are what gets checked."""
    config = tmp_path / "schemathesis.toml"
    config.write_text(SCHEMATHESIS_CONFIG)
    svc = ServiceProc(tmp_path / "data", token=CONTROL, extra_args=["--read-token", READ])
    svc.start()
    try:
        api = schemathesis(config, svc.url, "--exclude-path-regex", "/stream$")
        stream = schemathesis(
            config, svc.url, "--include-path-regex", "/stream$", "--request-timeout", "2"
        )
    finally:
        svc.stop()
    for done in (api, stream):
        summary = done.stdout[-8000:] + done.stderr[-2000:]
        assert done.returncode == 0, summary
        assert " passed" in summary, summary
