"""`mapctl` end to end: real subprocesses, exit codes, --json, one-line errors."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
from pathlib import Path

import pytest
from conftest import free_port, wait_for
from svc_testkit import BIN, SHARED_TOKEN, ScanFeeder, ServiceProc, shared_service

from clients import MappingClient
from clients.cli import main


def mapctl(
    *args: str, server: str | None = None, env: dict[str, str] | None = None, timeout: float = 30
) -> subprocess.CompletedProcess[str]:
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("MAPPING_")}
    full_env.update(env or {})
    cmd = [str(BIN / "mapctl")]
    if server is not None:
        cmd += ["--server", server]
    return subprocess.run(
        [*cmd, *args], capture_output=True, text=True, timeout=timeout, env=full_env, check=False
    )


def run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """`mapctl` in this process (same code path as the console script, minus the start-up cost
    of a new interpreter); the live end-to-end test also runs the real executable."""
    out, err = io.StringIO(), io.StringIO()
    saved = {k: os.environ.pop(k) for k in list(os.environ) if k.startswith("MAPPING_")}
    os.environ.update(env or {})
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(list(args))
            except SystemExit as exit_:
                code = exit_.code if isinstance(exit_.code, int) else 2
    finally:
        for k in [k for k in os.environ if k.startswith("MAPPING_")]:
            del os.environ[k]
        os.environ.update(saved)
    return subprocess.CompletedProcess(["mapctl", *args], code, out.getvalue(), err.getvalue())


def assert_one_line_error(done: subprocess.CompletedProcess[str]) -> None:
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("mapctl: ")
    assert "Traceback" not in done.stderr


def test_help_documents_exit_codes() -> None:
    done = run("--help")
    assert done.returncode == 0
    for code in ("0", "1", "2", "3"):
        assert f"\n  {code} " in done.stdout
    assert "MAPPING_TOKEN" in done.stdout


def test_usage_errors_exit_2() -> None:
    assert run().returncode == 2
    assert run("frobnicate").returncode == 2
    assert run("stop").returncode == 2  # missing ID
    done = run("--server", f"http://127.0.0.1:{free_port()}", "map", "s1", "--out", "x.bmp")
    assert done.returncode == 2
    assert_one_line_error(done)
    assert run("--server", "http://127.0.0.1:1", "watch", "--interval", "0").returncode == 2


def test_cannot_connect_exits_3_with_one_line() -> None:
    url = f"http://127.0.0.1:{free_port()}"
    done = mapctl("sessions", server=url)  # the real console script
    assert done.returncode == 3
    assert_one_line_error(done)
    assert url in done.stderr
    # The server also comes from the environment.
    done = run("sessions", "--json", env={"MAPPING_SERVER": url})
    assert done.returncode == 3
    assert url in done.stderr
    assert_one_line_error(done)


# ---------------------------------------------------------------------------------------------
# Against a live service


@pytest.fixture
def live(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> ServiceProc:
    return shared_service(request.config, tmp_path_factory)


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_mapctl_end_to_end(live: ServiceProc, tmp_path: Path) -> None:
    url = live.url
    auth = {"MAPPING_TOKEN": SHARED_TOKEN}

    def ctl(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
        return run("--server", url, *args, env=env)

    done = mapctl("start", "ctl-1", server=url)
    assert done.returncode == 1, done.stderr
    assert_one_line_error(done)
    assert "401" in done.stderr
    # Tells how to pass a token with mapctl, not which HTTP header the service wants.
    assert "--token-file" in done.stderr
    assert "MAPPING_TOKEN" in done.stderr
    assert "Authorization" not in done.stderr
    done = ctl("--token", "not-the-token", "start", "ctl-1")
    assert done.returncode == 1
    assert "wrong token (HTTP 401)" in done.stderr

    done = mapctl("--json", "start", "ctl-1", server=url, env=auth)
    assert done.returncode == 0, done.stderr
    session = json.loads(done.stdout)
    sid = session["id"]
    assert session["robot_id"] == "ctl-1"

    done = ctl("sessions", "--json")
    assert done.returncode == 0
    assert sid in [s["id"] for s in json.loads(done.stdout)]
    done = ctl("sessions")
    assert done.returncode == 0
    assert "SESSION" in done.stdout
    assert sid in done.stdout

    done = ctl("pose", sid)
    assert done.returncode == 1  # 409: no pose yet
    assert_one_line_error(done)
    done = ctl("stop", "no-such", env=auth)
    assert done.returncode == 1
    assert "404" in done.stderr

    with ScanFeeder(live.zenoh_endpoint, "ctl-1"), MappingClient(url) as client:
        wait_for(lambda: client.get_session(sid).poses >= 5, 30, "5 poses")
        done = ctl("pose", sid, "--json")
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout)["session_id"] == sid
        done = ctl("pose", sid)
        assert "quality" in done.stdout
        done = mapctl("pose", sid, "--follow", "--count", "3", "--json", server=url)
        assert done.returncode == 0, done.stderr
        follow = [json.loads(line) for line in done.stdout.splitlines()]
        assert len(follow) == 3
        assert follow[0]["sequence"] < follow[2]["sequence"], follow

        done = ctl("watch", "--count", "2", "--interval", "0.3")
        assert done.returncode == 0, done.stderr
        assert "ctl-1" in done.stdout
        assert "\x1b[" not in done.stdout  # no ANSI when not on a terminal
        done = ctl("--json", "watch", "--count", "2", "--interval", "0.3")
        frames = [json.loads(line) for line in done.stdout.splitlines()]
        assert len(frames) == 2
        mine = [x for x in frames[1]["sessions"] if x["id"] == sid]
        assert mine[0]["scans_per_s"] is not None

    png = tmp_path / "map.png"
    done = mapctl("map", sid, "--out", str(png), server=url)
    assert done.returncode == 0, done.stderr
    assert png.read_bytes().startswith(b"\x89PNG")
    done = ctl("map", sid, "--out", str(tmp_path / "map.yaml"))
    assert done.returncode == 0
    assert "resolution" in (tmp_path / "map.yaml").read_text()

    done = ctl("trajectory", sid, "--format", "tum")
    assert done.returncode == 0
    rows = [line.split() for line in done.stdout.splitlines() if line and line[0] != "#"]
    assert len(rows) >= 5
    assert all(len(r) == 8 for r in rows)
    done = ctl("trajectory", sid, "--format", "json")
    assert len(json.loads(done.stdout)["poses"]) >= 5

    done = mapctl("save", sid, "--json", server=url, env=auth)
    assert done.returncode == 0, done.stderr
    saved = json.loads(done.stdout)
    done = ctl("maps", "--json")
    assert saved["map_id"] in [m["map_id"] for m in json.loads(done.stdout)]

    done = mapctl("stop", sid, server=url, env=auth)
    assert done.returncode == 0
    assert "stopped" in done.stdout
    done = ctl("--token", SHARED_TOKEN, "delete", sid)
    assert done.returncode == 0
    done = ctl("show", sid)
    assert done.returncode == 1
