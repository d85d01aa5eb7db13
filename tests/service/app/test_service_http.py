"""The HTTP API in process (TestClient): resources, errors, security, OpenAPI, live stream."""

from __future__ import annotations

import asyncio
import io
import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from PIL import Image
from svc_testkit import (  # noqa: F401  # *_fixture: pytest fixtures used by name
    RuntimeFactory,
    SimRobot,
    client_fixture,
    feed,
    runtime_factory_fixture,
    runtime_fixture,
    wait_for,
)

from service.app.api.app import BodyLimitMiddleware, create_app
from service.app.errors import SettingsError
from service.app.runtime import MappingRuntime
from service.app.settings import build_settings
from service.cli import build_parser


def test_session_lifecycle(client: TestClient) -> None:
    r = client.post("/sessions", json={"robot_id": "amr-1"})
    assert r.status_code == 201, r.text
    session = r.json()
    sid = session["id"]
    assert session["robot_id"] == "amr-1"
    assert session["state"] == "active"
    assert session["scans_accepted"] == 0
    assert session["resolution_m"] == 0.05
    assert session["use_odometry"] is True
    assert session["last_pose"] is None

    assert client.get(f"/sessions/{sid}").json()["id"] == sid
    assert [s["id"] for s in client.get("/sessions").json()["sessions"]] == [sid]

    dup = client.post("/sessions", json={"robot_id": "amr-1"})
    assert dup.status_code == 409
    assert sid in dup.json()["detail"]

    stopped = client.post(f"/sessions/{sid}/stop")
    assert stopped.status_code == 200
    assert stopped.json()["state"] == "stopped"
    # A stopped session frees the robot for a new one.
    second = client.post("/sessions", json={"robot_id": "amr-1", "resolution_m": 0.1})
    assert second.status_code == 201
    assert second.json()["resolution_m"] == 0.1

    assert client.delete(f"/sessions/{sid}").status_code == 204
    assert client.get(f"/sessions/{sid}").status_code == 404
    assert client.delete(f"/sessions/{sid}").status_code == 404
    assert len(client.get("/sessions").json()["sessions"]) == 1


def test_poses_trajectory_and_maps(client: TestClient, runtime: MappingRuntime) -> None:
    sid = client.post("/sessions", json={"robot_id": "amr-2"}).json()["id"]
    no_pose = client.get(f"/sessions/{sid}/pose")
    assert (no_pose.status_code, no_pose.json()["code"]) == (409, "no_pose_yet")

    robot = SimRobot("amr-2")
    feed(runtime, robot, 40)

    session = client.get(f"/sessions/{sid}").json()
    assert session["scans_accepted"] == 40
    assert session["poses"] == 40
    pose = client.get(f"/sessions/{sid}/pose").json()
    assert pose["sequence"] == 39
    assert pose["session_id"] == sid
    assert pose["robot_id"] == "amr-2"
    assert abs(pose["stamp"] - pose["stamp_ns"] / 1e9) < 1e-3
    assert 0.0 <= pose["quality"] <= 1.0
    assert isinstance(pose["flags"], list)
    assert session["last_pose"] == pose

    traj = client.get(f"/sessions/{sid}/trajectory").json()
    assert traj["session_id"] == sid
    assert [p["sequence"] for p in traj["poses"]] == list(range(40))
    tum = client.get(f"/sessions/{sid}/trajectory", params={"format": "tum"})
    assert tum.status_code == 200
    assert tum.headers["content-type"].startswith("text/plain")
    rows = [line.split() for line in tum.text.splitlines() if line and not line.startswith("#")]
    assert len(rows) == 40
    assert all(len(row) == 8 for row in rows)

    png = client.get(f"/sessions/{sid}/map.png", params={"trajectory": True, "robot": True})
    assert png.status_code == 200
    assert png.headers["content-type"] == "image/png"
    image = Image.open(io.BytesIO(png.content))
    assert image.width > 10
    assert image.height > 10
    pgm = client.get(f"/sessions/{sid}/map.pgm")
    assert pgm.status_code == 200
    assert pgm.content.startswith(b"P5")
    yaml_text = client.get(f"/sessions/{sid}/map.yaml").text
    assert "resolution:" in yaml_text
    assert "map.pgm" in yaml_text

    saved = client.post(f"/sessions/{sid}/save")
    assert saved.status_code == 201, saved.text
    meta = saved.json()
    assert (meta["map_id"], meta["version"]) == (sid, 1)
    assert client.post(f"/sessions/{sid}/save").json()["version"] == 2
    listing = client.get("/maps").json()["maps"]
    assert [(m["map_id"], m["version"]) for m in listing] == [(sid, 1), (sid, 2)]
    for url in meta["urls"].values():
        r = client.get(url)
        assert r.status_code == 200, url
        assert r.content
    assert client.get(f"/maps/{sid}/3/map.png").status_code == 404

    reset = client.post(f"/sessions/{sid}/reset").json()
    assert (reset["scans_accepted"], reset["poses"], reset["last_pose"]) == (0, 0, None)
    assert client.get(f"/sessions/{sid}/pose").status_code == 409  # no_pose_yet


def test_unmapped_robot_and_metrics(client: TestClient, runtime: MappingRuntime) -> None:
    feed(runtime, SimRobot("nobody"), 3)
    text = client.get("/metrics")
    assert text.status_code == 200
    assert text.headers["content-type"].startswith("text/plain; version=0.0.4")
    body = text.text
    assert 'mapping_scans_unmapped_total{robot="nobody"} 3' in body
    for family in (
        "mapping_scans_accepted_total",
        "mapping_scans_rejected_total",
        "mapping_scans_dropped_total",
        "mapping_scan_processing_seconds",
        "mapping_ingest_queue_depth",
        "mapping_pose_stream_subscribers",
        "mapping_pose_stream_dropped_total",
        "mapping_poses_published_total",
        "mapping_sessions",
    ):
        assert f"# TYPE {family} " in body
    health = client.get("/health").json()
    assert health["status"] == "ok"
    assert health["zenoh"]["open"] is True
    assert [r["robot_id"] for r in health["robots"]] == ["nobody"]
    assert health["robots"][0]["session_id"] is None


def test_control_needs_token_when_configured(runtime_factory: RuntimeFactory) -> None:
    runtime = runtime_factory(token="s3cret")
    with TestClient(create_app(runtime)) as client:
        r = client.post("/sessions", json={"robot_id": "amr-3"})
        assert r.status_code == 401
        assert r.headers["www-authenticate"] == "Bearer"
        assert "token" in r.json()["detail"]
        wrong = {"Authorization": "Bearer nope"}
        assert (
            client.post("/sessions", json={"robot_id": "amr-3"}, headers=wrong).status_code == 401
        )
        good = {"Authorization": "Bearer s3cret"}
        created = client.post("/sessions", json={"robot_id": "amr-3"}, headers=good)
        assert created.status_code == 201
        sid = created.json()["id"]
        for path in ("stop", "reset", "save"):
            assert client.post(f"/sessions/{sid}/{path}").status_code == 401, path
        assert client.delete(f"/sessions/{sid}").status_code == 401
        # Reads stay open.
        assert client.get(f"/sessions/{sid}").status_code == 200
        assert client.get("/sessions").status_code == 200
        assert client.post(f"/sessions/{sid}/stop", headers=good).status_code == 200
        assert client.delete(f"/sessions/{sid}", headers=good).status_code == 204


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        ({"robot_id": "../etc"}, "robot_id"),
        ({"robot_id": "a b"}, "robot_id"),
        ({"robot_id": ""}, "robot_id"),
        ({}, "robot_id"),
        ({"robot_id": "ok", "resolution_m": 0}, "resolution_m"),
        ({"robot_id": "ok", "surprise": 1}, "surprise"),
    ],
)
def test_invalid_bodies_are_clear_4xx(client: TestClient, body: object, fragment: str) -> None:
    r = client.post("/sessions", json=body)
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert isinstance(detail, str)
    assert "\n" not in detail
    assert fragment in detail


def test_bounded_bodies_and_safe_paths(client: TestClient) -> None:
    big = json.dumps({"robot_id": "x", "pad": "y" * 70_000})
    r = client.post("/sessions", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert isinstance(r.json()["detail"], str)

    def chunks() -> Iterator[bytes]:  # no Content-Length: the streamed body is counted
        yield b'{"robot_id": "x", "pad": "'
        for _ in range(10):
            yield b"y" * 10_000
        yield b'"}'

    streamed = client.post(
        "/sessions", content=chunks(), headers={"content-type": "application/json"}
    )
    assert streamed.status_code == 413
    assert "larger than" in streamed.json()["detail"]
    not_json = client.post("/sessions", content=b"{", headers={"content-type": "application/json"})
    assert not_json.status_code == 400  # documented: a malformed body is 400, invalid_json
    assert not_json.json()["code"] == "invalid_json"
    for path in (
        "/sessions/..%2F..%2Fetc/map.png",
        "/sessions/%2e%2e/map.pgm",
        "/sessions/a%20b",
        "/maps/..%2Fsessions/1/map.png",
        "/maps/x/0/map.png",
        "/maps/x/1/map.json",
        "/maps/x/1/..%2F..%2Fservice.lock",
    ):
        r = client.get(path)
        assert r.status_code in (404, 422), path
        if r.headers["content-type"].startswith("application/json"):
            assert isinstance(r.json()["detail"], str), path


def test_openapi_documents_every_route(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    for name in ("Session", "PoseView", "SavedMap", "SessionList", "Trajectory", "Health"):
        assert name in schemas, name
    assert set(schemas["PoseView"]["properties"]) == {
        "session_id",
        "robot_id",
        "sequence",
        "stamp",
        "stamp_ns",
        "x",
        "y",
        "theta",
        "quality",
        "flags",
        "covariance",
    }
    expected = {
        ("post", "/sessions"),
        ("get", "/sessions"),
        ("get", "/sessions/{session_id}"),
        ("delete", "/sessions/{session_id}"),
        ("post", "/sessions/{session_id}/stop"),
        ("post", "/sessions/{session_id}/reset"),
        ("post", "/sessions/{session_id}/save"),
        ("get", "/sessions/{session_id}/pose"),
        ("get", "/sessions/{session_id}/trajectory"),
        ("get", "/sessions/{session_id}/graph"),
        ("get", "/sessions/{session_id}/map.png"),
        ("get", "/sessions/{session_id}/map.pgm"),
        ("get", "/sessions/{session_id}/map.yaml"),
        ("get", "/sessions/{session_id}/pose/stream"),
        ("get", "/sessions/{session_id}/recording.mcap"),
        ("get", "/maps"),
        ("get", "/maps/{map_id}/{version}/map.png"),
        ("get", "/maps/{map_id}/{version}/map.pgm"),
        ("get", "/maps/{map_id}/{version}/map.yaml"),
        ("delete", "/maps/{map_id}/{version}"),
        ("get", "/health"),
        ("get", "/fleet"),
        ("get", "/metrics"),
    }
    found = {(m, p) for p, ops in spec["paths"].items() for m in ops}
    assert expected == found
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            assert op.get("tags"), (method, path)
            assert op.get("summary"), (method, path)
            assert op.get("description"), (method, path)
            ok = op["responses"].get("200") or op["responses"].get("201") or {}
            if method != "delete":
                assert ok.get("content"), (method, path)
    create = spec["paths"]["/sessions"]["post"]
    assert create["responses"]["201"]["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/Session"
    }
    assert create["security"], "control routes declare the bearer scheme"
    stream = spec["paths"]["/sessions/{session_id}/pose/stream"]["get"]
    assert "text/event-stream" in stream["responses"]["200"]["content"]


def test_web_page_is_served_at_root(client: TestClient) -> None:
    r = client.get("/")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/html")
    # API routes win over the static mount.
    assert client.get("/health").headers["content-type"].startswith("application/json")


def test_pose_stream_sends_current_and_new_poses(
    client: TestClient, runtime: MappingRuntime
) -> None:
    sid = client.post("/sessions", json={"robot_id": "amr-4"}).json()["id"]
    robot = SimRobot("amr-4")
    feed(runtime, robot, 2)
    events: list[dict[str, object]] = []
    with client.stream("GET", f"/sessions/{sid}/pose/stream") as r:
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/event-stream")
        lines = r.iter_lines()
        kind = None
        for line in lines:
            if line.startswith("event:"):
                kind = line.split(":", 1)[1].strip()
            elif line.startswith("data:") and kind == "pose":
                events.append(json.loads(line.split(":", 1)[1]))
                if len(events) == 1:
                    feed(runtime, robot, 3)
                if len(events) == 4:
                    runtime.fanout.end_streams_threadsafe()  # lets the response finish
    assert [e["sequence"] for e in events] == [1, 2, 3, 4]
    assert all(e["session_id"] == sid for e in events)
    assert client.get("/sessions/nope/pose/stream").status_code == 404


def test_settings_refuse_open_bind_without_token(tmp_path: Path) -> None:
    parser = build_parser()
    args = parser.parse_args(["serve", "--http-host", "0.0.0.0", "--data-dir", str(tmp_path)])
    with pytest.raises(SettingsError, match="token"):
        build_settings(args, env={})
    # A token alone no longer opens a non-loopback bind: reads need a scope too
    # (tests/service/app/test_service_security.py).
    env = {"MAPPING_TOKEN": "t", "MAPPING_READ_TOKEN": "r"}
    assert build_settings(args, env=env).token == "t"
    insecure = parser.parse_args(
        ["serve", "--http-host", "0.0.0.0", "--allow-insecure-bind", "--data-dir", str(tmp_path)]
    )
    assert build_settings(insecure, env={}).token is None
    local = parser.parse_args(["serve", "--data-dir", str(tmp_path)])
    settings = build_settings(local, env={"MAPPING_QUEUE_DEPTH": "7"})
    assert settings.ingest.queue_depth == 7
    assert (
        "t"
        not in json.dumps(
            build_settings(args, env={**env, "MAPPING_TOKEN": "zzz-secret"}).describe()
        ).replace("<set>", "")[:0]
    )
    assert "zzz-secret" not in json.dumps(
        build_settings(args, env={**env, "MAPPING_TOKEN": "zzz-secret"}).describe()
    )


def test_settings_mapper_processes_from_flag_or_environment(tmp_path: Path) -> None:
    parser = build_parser()
    plain = parser.parse_args(["serve", "--data-dir", str(tmp_path)])
    default = build_settings(plain, env={})
    assert (default.ingest.mapper_processes, default.ingest.worker_threads) == (0, 1)
    from_env = build_settings(plain, env={"MAPPING_MAPPER_PROCESSES": "3"})
    assert (from_env.ingest.mapper_processes, from_env.ingest.worker_threads) == (3, 6)
    flag = parser.parse_args(["serve", "--data-dir", str(tmp_path), "--mapper-processes", "2"])
    settings = build_settings(
        flag, env={"MAPPING_MAPPER_PROCESSES": "3", "MAPPING_INGEST_WORKERS": "5"}
    )
    assert (settings.ingest.mapper_processes, settings.ingest.worker_threads) == (2, 5)
    bad = parser.parse_args(["serve", "--data-dir", str(tmp_path), "--mapper-processes", "-1"])
    with pytest.raises(SettingsError, match="mapper_processes"):
        build_settings(bad, env={})


def test_scans_go_to_the_mapper_processes_by_default_when_there_are_any(tmp_path: Path) -> None:
    parser = build_parser()
    base = ["serve", "--data-dir", str(tmp_path), "--zenoh-listen", "tcp/127.0.0.1:7447"]

    def scans_in_mappers(*flags: str, env: dict[str, str] | None = None) -> bool:
        ingest = build_settings(parser.parse_args([*base, *flags]), env=env or {}).ingest
        return ingest.scans_in_mappers(has_endpoint=True)

    assert not scans_in_mappers()  # no mapper processes: all in one process
    assert scans_in_mappers("--mapper-processes", "2")
    assert not scans_in_mappers("--mapper-processes", "2", "--no-ingest-in-mappers")
    assert not scans_in_mappers("--mapper-processes", "2", env={"MAPPING_INGEST_IN_MAPPERS": "0"})
    assert scans_in_mappers(  # the flag wins over the environment
        "--mapper-processes", "2", "--ingest-in-mappers", env={"MAPPING_INGEST_IN_MAPPERS": "0"}
    )
    # Without an endpoint for the processes to connect to, the default falls back to the scans
    # through the service's process; asking for it explicitly is refused.
    plain = build_settings(
        parser.parse_args(["serve", "--data-dir", str(tmp_path), "--mapper-processes", "2"]),
        env={},
    )
    assert not plain.ingest.scans_in_mappers(has_endpoint=False)
    explicit = ["serve", "--data-dir", str(tmp_path), "--mapper-processes", "2"]
    with pytest.raises(SettingsError, match="zenoh-listen"):
        build_settings(parser.parse_args([*explicit, "--ingest-in-mappers"]), env={})


def test_body_limit_refuses_a_non_ascii_digit_content_length() -> None:
    """'¹' passes str.isdigit() but not int(): a clear 400, not a server error. (h11 refuses
    such a header before the app sees it; other servers may not, so the ASGI app is called.)"""
    sent: list[dict[str, object]] = []

    async def app(scope: object, receive: object, send: object) -> None:
        raise AssertionError("the body limit must answer first")

    async def receive() -> dict[str, object]:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: dict[str, object]) -> None:
        sent.append(message)

    scope = {
        "type": "http",
        "method": "POST",
        "path": "/sessions",
        "headers": [(b"content-length", "¹".encode("latin-1"))],
    }
    asyncio.run(BodyLimitMiddleware(app, 1024)(scope, receive, send))  # type: ignore[arg-type]
    assert sent[0]["status"] == 400
