"""Who may read, who may control: token scopes, token files, the bind rule (issue 16).

In process (TestClient) for the HTTP rules; one real `mapping-service serve` for the token
files, to check that no token appears on its command line (`ps`).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from svc_testkit import (  # noqa: F401  # *_fixture: pytest fixtures used by name
    RuntimeFactory,
    ServiceProc,
    SimRobot,
    feed,
    runtime_factory_fixture,
)

from service.app.api.app import create_app
from service.app.errors import SettingsError
from service.app.settings import build_settings
from service.cli import build_parser

CONTROL = "control-token-0123456789"
READ = "read-token-0123456789abc"
AS_CONTROL = {"Authorization": f"Bearer {CONTROL}"}
AS_READER = {"Authorization": f"Bearer {READ}"}
WRONG = {"Authorization": "Bearer not-the-token-at-all"}


def read_paths(sid: str) -> list[str]:
    """Every read of the API, with a real session id (so a 200 is possible)."""
    return [
        "/sessions",
        f"/sessions/{sid}",
        f"/sessions/{sid}/pose",
        f"/sessions/{sid}/trajectory",
        f"/sessions/{sid}/trajectory?format=tum",
        f"/sessions/{sid}/map.png",
        f"/sessions/{sid}/map.pgm",
        f"/sessions/{sid}/map.yaml",
        f"/sessions/{sid}/recording.mcap",
        "/maps",
        f"/maps/{sid}/1/map.png",
        f"/maps/{sid}/1/map.pgm",
        f"/maps/{sid}/1/map.yaml",
        "/metrics",
        "/fleet",
    ]


def test_every_read_needs_a_token_when_a_read_token_is_set(
    runtime_factory: RuntimeFactory,
) -> None:
    runtime = runtime_factory(token=CONTROL, read_token=READ)
    with TestClient(create_app(runtime)) as client:
        sid = client.post("/sessions", json={"robot_id": "amr-9"}, headers=AS_CONTROL).json()["id"]
        feed(runtime, SimRobot("amr-9"), 20)
        assert client.post(f"/sessions/{sid}/save", headers=AS_CONTROL).status_code == 201
        for path in read_paths(sid):
            anonymous = client.get(path)
            assert anonymous.status_code == 401, path
            assert anonymous.headers["www-authenticate"] == "Bearer", path
            assert anonymous.json()["code"] == "unauthorized", path
            assert "amr-9" not in anonymous.text, path
            assert client.get(path, headers=WRONG).status_code == 401, path
            assert client.get(path, headers=AS_READER).status_code == 200, path
            assert client.get(path, headers=AS_CONTROL).status_code == 200, path
        # The stream: no token is 401; the header or ?access_token= (EventSource) opens it.
        stream = f"/sessions/{sid}/pose/stream"
        assert client.get(stream).status_code == 401
        assert client.get(stream + "?access_token=nope").status_code == 401
        for kwargs in ({"headers": AS_READER}, {"params": {"access_token": READ}}):
            with client.stream("GET", stream, **kwargs) as r:  # type: ignore[arg-type]
                assert r.status_code == 200
                first = next(line for line in r.iter_lines() if line.startswith("data:"))
                assert sid in first
                runtime.fanout.end_streams_threadsafe()
        # The page itself and the API document hold no data: open.
        assert client.get("/").status_code == 200
        assert client.get("/openapi.json").status_code == 200


def test_health_without_a_token_is_the_status_only(runtime_factory: RuntimeFactory) -> None:
    runtime = runtime_factory(token=CONTROL, read_token=READ)
    with TestClient(create_app(runtime)) as client:
        client.post("/sessions", json={"robot_id": "secret-robot"}, headers=AS_CONTROL)
        feed(runtime, SimRobot("secret-robot"), 3)
        minimal = client.get("/health")
        assert minimal.status_code == 200
        assert minimal.json() == {"status": "ok"}
        assert client.get("/health", headers=WRONG).status_code == 401
        full = client.get("/health", headers=AS_READER).json()
        assert [r["robot_id"] for r in full["robots"]] == ["secret-robot"]
        assert full["sessions_active"] == 1


def test_the_read_token_cannot_control(runtime_factory: RuntimeFactory) -> None:
    runtime = runtime_factory(token=CONTROL, read_token=READ)
    with TestClient(create_app(runtime)) as client:
        refused = client.post("/sessions", json={"robot_id": "amr-4"}, headers=AS_READER)
        assert (refused.status_code, refused.json()["code"]) == (403, "forbidden")
        sid = client.post("/sessions", json={"robot_id": "amr-4"}, headers=AS_CONTROL).json()["id"]
        for action in ("stop", "reset", "save"):
            assert client.post(f"/sessions/{sid}/{action}", headers=AS_READER).status_code == 403
        assert client.delete(f"/sessions/{sid}", headers=AS_READER).status_code == 403
        assert client.delete(f"/sessions/{sid}", headers=AS_CONTROL).status_code == 204


@pytest.mark.timeout(60)
def test_the_token_is_checked_before_the_body(runtime_factory: RuntimeFactory) -> None:
    """A caller without the control token learns 401/403, whatever its body: it is told
    nothing about what the service accepts before it has shown a token."""
    runtime = runtime_factory(token=CONTROL, read_token=READ)
    bodies = [
        b"{not json",  # invalid_json
        b'{"robot_id": "\xff"}',  # invalid_utf8
        b"[" * 40 + b"]" * 40,  # json_too_deep
        b'{"robot_id": 5}',  # valid JSON, refused by the schema (422 with the token)
    ]
    json_type = {"Content-Type": "application/json"}
    with TestClient(create_app(runtime)) as client:
        for body in bodies:
            anonymous = client.post("/sessions", content=body, headers=json_type)
            assert anonymous.status_code == 401, (body, anonymous.text)
            assert anonymous.headers["www-authenticate"] == "Bearer"
            wrong = client.post("/sessions", content=body, headers={**json_type, **WRONG})
            assert wrong.status_code == 401, body
            reader = client.post("/sessions", content=body, headers={**json_type, **AS_READER})
            assert reader.status_code == 403, body
            control = client.post("/sessions", content=body, headers={**json_type, **AS_CONTROL})
            assert control.status_code in (400, 422), body


def test_reads_stay_open_without_a_read_token_on_loopback(
    runtime_factory: RuntimeFactory,
) -> None:
    runtime = runtime_factory(token=CONTROL)
    with TestClient(create_app(runtime)) as client:
        assert client.get("/sessions").status_code == 200
        assert "robots" in client.get("/health").json()


def _serve_args(tmp_path: Path, *extra: str) -> object:
    return build_parser().parse_args(["serve", "--data-dir", str(tmp_path), *extra])


def test_non_loopback_bind_needs_a_read_token_or_public_reads(tmp_path: Path) -> None:
    open_bind = ("--http-host", "0.0.0.0")
    with pytest.raises(SettingsError, match="without a token"):
        build_settings(_serve_args(tmp_path, *open_bind), env={})
    with pytest.raises(SettingsError, match="public reads"):
        build_settings(_serve_args(tmp_path, *open_bind), env={"MAPPING_TOKEN": CONTROL})
    scoped = build_settings(
        _serve_args(tmp_path, *open_bind),
        env={"MAPPING_TOKEN": CONTROL, "MAPPING_READ_TOKEN": READ},
    )
    assert (scoped.token, scoped.read_token) == (CONTROL, READ)
    public = build_settings(
        _serve_args(tmp_path, *open_bind, "--public-reads"), env={"MAPPING_TOKEN": CONTROL}
    )
    assert public.read_token is None
    # Contradictory or unsafe combinations.
    for env, message in (
        ({"MAPPING_READ_TOKEN": READ}, "without a control token"),
        ({"MAPPING_TOKEN": CONTROL, "MAPPING_READ_TOKEN": CONTROL}, "must differ"),
        ({"MAPPING_TOKEN": "has space in it 0123"}, "visible ASCII"),
    ):
        with pytest.raises(SettingsError, match=message):
            build_settings(_serve_args(tmp_path), env=env)
    with pytest.raises(SettingsError, match="Foxglove"):
        build_settings(
            _serve_args(tmp_path, "--foxglove-port", "8765"),
            env={"MAPPING_TOKEN": CONTROL, "MAPPING_READ_TOKEN": READ},
        )
    with pytest.raises(SettingsError, match="contradict"):
        build_settings(
            _serve_args(tmp_path, "--public-reads"),
            env={"MAPPING_TOKEN": CONTROL, "MAPPING_READ_TOKEN": READ},
        )
    described = str(scoped.describe())
    assert CONTROL not in described
    assert READ not in described


def test_token_files(tmp_path: Path) -> None:
    control_file = tmp_path / "control.token"
    control_file.write_text(CONTROL + "\n")
    control_file.chmod(0o600)
    read_file = tmp_path / "read.token"
    read_file.write_text(f"  {READ}  \n\nignored second line\n")
    read_file.chmod(0o600)
    settings = build_settings(
        _serve_args(
            tmp_path, "--token-file", str(control_file), "--read-token-file", str(read_file)
        ),
        env={},
    )
    assert (settings.token, settings.read_token) == (CONTROL, READ)
    from_env = build_settings(
        _serve_args(tmp_path),
        env={"MAPPING_TOKEN_FILE": str(control_file), "MAPPING_READ_TOKEN_FILE": str(read_file)},
    )
    assert (from_env.token, from_env.read_token) == (CONTROL, READ)
    # The flag wins over the environment.
    assert (
        build_settings(
            _serve_args(tmp_path, "--token-file", str(control_file)),
            env={"MAPPING_TOKEN": "x" * 20},
        ).token
        == CONTROL
    )
    empty = tmp_path / "empty.token"
    empty.write_text("\n")
    with pytest.raises(SettingsError, match="empty"):
        build_settings(_serve_args(tmp_path, "--token-file", str(empty)), env={})
    with pytest.raises(SettingsError, match="cannot read"):
        build_settings(_serve_args(tmp_path, "--token-file", str(tmp_path / "missing")), env={})
    with pytest.raises(SettingsError, match="once"):
        build_settings(
            _serve_args(tmp_path, "--token", CONTROL, "--token-file", str(control_file)), env={}
        )


def test_help_says_the_environment_is_safer_than_a_flag() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "serve", "--help"],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    text = " ".join(done.stdout.split())
    for fragment in ("--token-file", "--read-token-file", "--public-reads", "MAPPING_READ_TOKEN"):
        assert fragment in text
    assert "visible to every user in `ps`: prefer MAPPING_TOKEN" in text


def test_a_service_with_token_files_keeps_them_out_of_ps(tmp_path: Path) -> None:
    control_file = tmp_path / "control.token"
    control_file.write_text(CONTROL + "\n")
    read_file = tmp_path / "read.token"
    read_file.write_text(READ + "\n")
    for f in (control_file, read_file):
        f.chmod(0o600)
    svc = ServiceProc(
        tmp_path / "data",
        extra_args=["--token-file", str(control_file), "--read-token-file", str(read_file)],
    )
    svc.start()
    try:
        assert svc.proc is not None
        cmdline = Path(f"/proc/{svc.proc.pid}/cmdline").read_bytes()
        assert CONTROL.encode() not in cmdline
        assert READ.encode() not in cmdline
        assert httpx.get(svc.url + "/sessions").status_code == 401
        assert httpx.get(svc.url + "/sessions", headers=AS_READER).status_code == 200
        created = httpx.post(svc.url + "/sessions", json={"robot_id": "ps-1"}, headers=AS_CONTROL)
        assert created.status_code == 201
        log = svc.log_path.read_text()
        assert CONTROL not in log
        assert READ not in log
    finally:
        assert svc.stop() == 0


def test_client_and_mapctl_with_a_read_token(tmp_path: Path) -> None:
    from clients import MappingClient
    from clients.http import MappingError

    svc = ServiceProc(tmp_path / "data", token=CONTROL, extra_args=["--read-token", READ])
    svc.start()
    try:
        with MappingClient(svc.url, token=CONTROL) as control:
            sid = control.create_session("cli-1").id
        with MappingClient(svc.url, token=READ) as reader:
            assert [s.id for s in reader.list_sessions()] == [sid]
            assert reader.health().details["robots"] == [
                {
                    "robot_id": "cli-1",
                    "alive": False,
                    "queue_depth": 0,
                    "last_scan_ns": 0,
                    "session_id": sid,
                    "publishers": 0,
                    "duplicate_publisher": False,
                    "duplicate_scans_refused": 0,
                    "stamps_refused": 0,
                    "stamp_gaps": 0,
                }
            ]
            with pytest.raises(MappingError) as forbidden:
                reader.stop_session(sid)
            assert (forbidden.value.status, forbidden.value.code) == (403, "forbidden")
        with MappingClient(svc.url) as anonymous:
            assert anonymous.health().status == "ok"
            assert "robots" not in anonymous.health().details
            with pytest.raises(MappingError) as unauthorized:
                anonymous.list_sessions()
            assert (unauthorized.value.status, unauthorized.value.code) == (401, "unauthorized")
        token_file = tmp_path / "reader.token"
        token_file.write_text(READ + "\n")
        mapctl = [sys.executable, "-m", "clients.cli", "--server", svc.url]
        env = {k: v for k, v in os.environ.items() if not k.startswith("MAPPING_")}
        done = subprocess.run(
            [*mapctl, "--token-file", str(token_file), "sessions", "--json"],
            capture_output=True,
            text=True,
            timeout=60,
            env=env,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        assert sid in done.stdout
        done = subprocess.run(
            [*mapctl, "sessions"],
            capture_output=True,
            text=True,
            timeout=60,
            env={**env, "MAPPING_TOKEN_FILE": str(token_file)},
            check=False,
        )
        assert done.returncode == 0, done.stderr
        refused = subprocess.run(
            [*mapctl, "sessions"], capture_output=True, text=True, timeout=60, env=env, check=False
        )
        assert refused.returncode == 1
        assert "401" in refused.stderr
    finally:
        svc.stop()
