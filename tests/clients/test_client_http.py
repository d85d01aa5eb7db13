"""MappingClient: strict parsing and error mapping (mock transport), then a live service."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from conftest import free_port, wait_for
from svc_testkit import ScanFeeder, ServiceProc, shared_service

from clients import MappingClient, MappingError, PoseView, Session
from clients.http import MapInfo, MappingConnectionError, MappingProtocolError, _iter_sse
from clients.wire import PoseFlag

POSE = {
    "session_id": "s1",
    "robot_id": "amr-07",
    "sequence": 4,
    "stamp": 1700000000.25,
    "stamp_ns": 1700000000250000000,
    "x": 1.5,
    "y": -2,
    "theta": 0.1,
    "quality": 0.8,
    "flags": ["AMBIGUOUS_X", "SOMETHING_NEW"],
}
SESSION = {
    "id": "s1",
    "robot_id": "amr-07",
    "state": "active",
    "created_ns": 1700000000000000000,
    "scans_accepted": 10,
    "poses": 9,
    "resolution_m": 0.05,
    "use_odometry": True,
    "last_pose": POSE,
}
SAVED = {
    "map_id": "amr-07",
    "version": 2,
    "session_id": "s1",
    "robot_id": "amr-07",
    "saved_ns": 1700000001000000000,
    "urls": {
        "png": "/maps/amr-07/2/map.png",
        "pgm": "/maps/amr-07/2/map.pgm",
        "yaml": "/maps/amr-07/2/map.yaml",
    },
}
MAP_YAML = """image: map.pgm
resolution: 0.050000
origin: [-3.250000, -1.500000, 0.000000]
negate: 0
occupied_thresh: 0.65
free_thresh: 0.196
"""

Handler = Callable[[httpx.Request], httpx.Response]


def mock_client(handler: Handler, token: str | None = None) -> MappingClient:
    return MappingClient("http://svc", token=token, transport=httpx.MockTransport(handler))


# ---------------------------------------------------------------------------------------------
# Parsing and error mapping (no server)


def test_parses_session_and_pose_strictly() -> None:
    session = Session.from_json(SESSION)
    assert session.active
    assert session.last_pose is not None
    assert session.last_pose.y_m == -2.0
    assert session.last_pose.flags == ("AMBIGUOUS_X", "SOMETHING_NEW")
    assert session.last_pose.pose_flags == PoseFlag.AMBIGUOUS_X  # unknown names ignored
    assert Session.from_json(session.to_json()) == session
    assert PoseView.from_json(session.last_pose.to_json()) == session.last_pose


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.pop("robot_id"), "missing field 'robot_id'"),
        (lambda d: d.update(scans_accepted="10"), "scans_accepted is str"),
        (lambda d: d.update(scans_accepted=True), "scans_accepted is bool"),
        (lambda d: d.update(state="paused"), "unknown state"),
        (lambda d: d.update(last_pose={"x": 1}), "missing field"),
        (lambda d: d.update(use_odometry=1), "use_odometry is int"),
    ],
)
def test_malformed_session_raises_protocol_error(
    mutate: Callable[[dict[str, object]], object], message: str
) -> None:
    data = json.loads(json.dumps(SESSION))
    mutate(data)
    with pytest.raises(MappingProtocolError, match=message):
        Session.from_json(data)


def test_methods_build_the_documented_requests() -> None:
    seen: list[tuple[str, str, bytes, str | None]] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(
            (
                request.method,
                str(request.url),
                request.content,
                request.headers.get("authorization"),
            )
        )
        path = request.url.path
        if path == "/sessions" and request.method == "POST":
            return httpx.Response(201, json=SESSION)
        if path == "/sessions":
            return httpx.Response(200, json={"sessions": [SESSION]})
        if path.endswith("/save"):
            return httpx.Response(201, json=SAVED)
        if path.endswith("/trajectory") and request.url.params.get("format") == "tum":
            return httpx.Response(200, text="1.0 0 0 0 0 0 0 1\n")
        if path.endswith("/trajectory"):
            return httpx.Response(200, json={"session_id": "s1", "poses": [POSE, POSE]})
        if path.endswith("/pose"):
            return httpx.Response(200, json=POSE)
        if path.endswith("map.png"):
            return httpx.Response(200, content=b"\x89PNG...")
        if path.endswith("map.yaml"):
            return httpx.Response(200, text=MAP_YAML)
        if path == "/maps":
            return httpx.Response(200, json={"maps": [SAVED]})
        if path == "/health":
            return httpx.Response(200, json={"status": "ok", "sessions": 1})
        if request.method == "DELETE":
            return httpx.Response(204)
        return httpx.Response(200, json=SESSION)

    with mock_client(handler, token="t0k") as client:
        assert client.create_session("amr-07", resolution_m=0.1, use_odometry=False).id == "s1"
        assert [s.id for s in client.list_sessions()] == ["s1"]
        assert client.stop_session("s1").robot_id == "amr-07"
        assert client.save_session("s1").urls.png == "/maps/amr-07/2/map.png"
        assert len(client.get_trajectory("s1")) == 2
        assert client.get_trajectory_tum("s1").startswith("1.0 ")
        assert client.get_pose("s1").sequence == 4
        assert client.get_map_png("s1", trajectory=False).startswith(b"\x89PNG")
        info = client.get_map_info("s1")
        assert (info.resolution_m, info.origin_x_m, info.origin_y_m) == (0.05, -3.25, -1.5)
        assert client.list_maps()[0].version == 2
        assert client.health().ok
        client.delete_session("s1")
    create = seen[0]
    assert create[0] == "POST"
    assert json.loads(create[2]) == {
        "robot_id": "amr-07",
        "resolution_m": 0.1,
        "use_odometry": False,
    }
    assert all(auth == "Bearer t0k" for *_, auth in seen)
    assert any("trajectory=false&robot=true" in url for _, url, _, _ in seen)


@pytest.mark.parametrize(
    ("status", "body", "reason"),
    [
        (404, {"detail": "no session 'x'"}, "no session 'x'"),
        (401, {"detail": "missing or wrong token"}, "missing or wrong token"),
        (
            422,
            {"detail": [{"loc": ["body", "robot_id"], "msg": "Field required"}]},
            "robot_id: Field required",
        ),
        (500, "<html>Internal Server Error</html>", "<html>Internal Server Error</html>"),
    ],
)
def test_http_errors_carry_status_and_reason(status: int, body: object, reason: str) -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        if isinstance(body, str):
            return httpx.Response(status, text=body)
        return httpx.Response(status, json=body)

    with mock_client(handler) as client, pytest.raises(MappingError) as info:
        client.get_session("x")
    assert (info.value.status, info.value.reason) == (status, reason)


def test_non_json_answer_is_a_protocol_error() -> None:
    with (
        mock_client(lambda r: httpx.Response(200, text="hello")) as client,
        pytest.raises(MappingProtocolError, match="not JSON"),
    ):
        client.list_sessions()


def test_connection_refused_is_a_connection_error() -> None:
    with MappingClient(f"http://127.0.0.1:{free_port()}", timeout_s=2) as client:
        with pytest.raises(MappingConnectionError) as info:
            client.list_sessions()
        assert info.value.status is None
        assert "cannot connect" in info.value.reason


def test_ids_cannot_escape_the_path() -> None:
    urls: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        urls.append(request.url.raw_path.decode())
        return httpx.Response(200, json=SESSION)

    with mock_client(handler) as client:
        client.get_session("../maps")
        with pytest.raises(MappingError):
            client.get_session("..")
    assert urls == ["/sessions/..%2Fmaps"]


def test_sse_parser_handles_comments_multiline_and_other_events() -> None:
    lines = iter([": keep-alive", "", "event: pose", 'data: {"a":', "data: 1}", "", "data: x", ""])
    assert list(_iter_sse(lines)) == [("pose", '{"a":\n1}'), ("message", "x")]


def test_stream_poses_yields_pose_events() -> None:
    body = (
        ": hello\n\n"
        + "".join(f"event: pose\ndata: {json.dumps({**POSE, 'sequence': i})}\n\n" for i in range(3))
        + "event: other\ndata: {}\n\n"
    )

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == "/sessions/s1/pose/stream"
        return httpx.Response(200, text=body, headers={"content-type": "text/event-stream"})

    with mock_client(handler) as client:
        assert [p.sequence for p in client.stream_poses("s1")] == [0, 1, 2]


def test_map_yaml_parser_rejects_garbage() -> None:
    assert MapInfo.from_yaml(MAP_YAML).image == "map.pgm"
    with pytest.raises(MappingProtocolError):
        MapInfo.from_yaml("resolution: 0.05\n")
    with pytest.raises(MappingProtocolError):
        MapInfo.from_yaml("image: a\nresolution: -1\norigin: [0, 0, 0]\n")


# ---------------------------------------------------------------------------------------------
# Against a live service


@pytest.fixture
def live(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> ServiceProc:
    return shared_service(request.config, tmp_path_factory)


@pytest.mark.slow
@pytest.mark.timeout(90)
def test_live_session_lifecycle(live: ServiceProc, tmp_path: Path) -> None:
    with MappingClient(live.url, token=live.token) as client:
        assert client.health().ok
        assert "# " in client.metrics() or client.metrics().strip()
        session = client.create_session("live-1", resolution_m=0.05)
        assert session.robot_id == "live-1"
        assert session.state == "active"
        assert session.id in [s.id for s in client.list_sessions()]
        with pytest.raises(MappingError) as no_pose:
            client.get_pose(session.id)
        assert (no_pose.value.status, no_pose.value.code) == (409, "no_pose_yet")

        with ScanFeeder(live.zenoh_endpoint, "live-1"):
            wait_for(lambda: client.get_session(session.id).poses >= 10, 30, "10 poses")
            stream = client.stream_poses(session.id, read_timeout_s=10)
            first = next(stream)
            second = next(stream)
            stream.close()
            assert second.sequence > first.sequence
            assert first.session_id == session.id

        pose = client.get_pose(session.id)
        assert 0.0 <= pose.quality <= 1.0
        trajectory = client.get_trajectory(session.id)
        assert len(trajectory) >= 10
        assert trajectory[-1].sequence >= trajectory[0].sequence
        tum = client.get_trajectory_tum(session.id)
        assert len(tum.strip().splitlines()) >= 10
        assert client.get_map_png(session.id).startswith(b"\x89PNG")
        assert client.get_map_png(session.id, trajectory=False, robot=False).startswith(b"\x89PNG")
        assert client.get_map_pgm(session.id).startswith(b"P5")
        info = client.get_map_info(session.id)
        assert info.resolution_m == pytest.approx(0.05)

        saved = client.save_session(session.id)
        assert saved.session_id == session.id
        assert any(m.map_id == saved.map_id for m in client.list_maps())
        assert client.download_map(saved.map_id, saved.version, "png").startswith(b"\x89PNG")
        assert client.download_map(saved.map_id, saved.version, "pgm").startswith(b"P5")

        stopped = client.stop_session(session.id)
        assert stopped.state == "stopped"
        client.delete_session(session.id)
        with pytest.raises(MappingError) as gone:
            client.get_session(session.id)
        assert gone.value.status == 404


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_live_error_paths(live: ServiceProc) -> None:
    with MappingClient(live.url) as anonymous:
        with pytest.raises(MappingError) as unauthorised:
            anonymous.create_session("live-2")
        assert unauthorised.value.status == 401
        assert unauthorised.value.reason
        anonymous.list_sessions()  # reads need no token
    with MappingClient(live.url, token="wrong") as wrong, pytest.raises(MappingError) as bad:
        wrong.create_session("live-2")
    assert bad.value.status in (401, 403)
    with MappingClient(live.url, token=live.token) as client:
        with pytest.raises(MappingError) as missing:
            client.get_session("no-such-session")
        assert missing.value.status == 404
        assert missing.value.reason
        for bad_input in ({"robot_id": "a/b"}, {"robot_id": "ok", "resolution_m": -1.0}):
            with pytest.raises(MappingError) as invalid:
                client.create_session(
                    str(bad_input["robot_id"]),
                    resolution_m=bad_input.get("resolution_m"),  # type: ignore[arg-type]
                )
            assert invalid.value.status in (400, 422), invalid.value
        with pytest.raises(MappingError) as no_stop:
            client.stop_session("no-such-session")
        assert no_stop.value.status == 404
