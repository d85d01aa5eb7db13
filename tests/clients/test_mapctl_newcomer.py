"""What a newcomer tripped on with `mapctl`: downloading a saved map version, and
`pose --follow` ending silently with exit 0 when the service goes away."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
from conftest import wait_for
from svc_testkit import BIN, ScanFeeder, ServiceProc

from clients import MappingClient

pytestmark = pytest.mark.slow


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("MAPPING_")}


def _mapctl(url: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(BIN / "mapctl"), "--server", url, *args],
        capture_output=True, text=True, timeout=30, env=_env(), check=False,
    )  # fmt: skip


def test_maps_get_downloads_a_version_and_follow_fails_when_the_service_stops(
    tmp_path: Path,
) -> None:
    live = ServiceProc(tmp_path / "data")
    live.start()
    try:
        with MappingClient(live.url) as client:
            sid = client.create_session("nc-1").id
            with ScanFeeder(live.zenoh_endpoint, "nc-1"):
                wait_for(lambda: client.get_session(sid).poses >= 5, 30, "5 poses")
                first = client.save_session(sid)
                wait_for(lambda: client.get_session(sid).poses >= 40, 30, "40 poses")
                second = client.save_session(sid)
            assert (first.version, second.version) == (1, 2)
            v1_pgm = client.download_map(sid, 1, "pgm")
            v2_png = client.download_map(sid, 2, "png")

        out = tmp_path / "v1.pgm"
        done = _mapctl(live.url, "maps", "get", sid, "--version", "1", "--out", str(out))
        assert done.returncode == 0, done.stderr
        assert out.read_bytes() == v1_pgm
        latest = tmp_path / "latest.png"
        done = _mapctl(live.url, "maps", "get", sid, "--out", str(latest))
        assert done.returncode == 0, done.stderr
        assert "v2" in done.stdout
        assert latest.read_bytes() == v2_png
        done = _mapctl(live.url, "maps", "get", sid, "--version", "9", "--out", str(out))
        assert done.returncode == 1
        assert "no version 9" in done.stderr
        done = _mapctl(live.url, "maps", "get", "nosuch", "--out", str(out))
        assert done.returncode == 1
        done = _mapctl(live.url, "maps")  # the list still works without a subcommand
        assert done.returncode == 0
        assert sid in done.stdout

        follow = subprocess.Popen(
            [str(BIN / "mapctl"), "--server", live.url, "pose", sid, "--follow"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(),
        )  # fmt: skip
        try:
            assert follow.stdout is not None
            assert "quality" in follow.stdout.readline()  # the current pose: it follows
            live.stop()
            code = follow.wait(timeout=30)
        finally:
            if follow.poll() is None:
                follow.kill()
                follow.wait()
        assert follow.stderr is not None
        err = follow.stderr.read()
        assert code == 3, err
        assert err.startswith("mapctl: ")
        assert "stopped" in err
    finally:
        live.stop()
