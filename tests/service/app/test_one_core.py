"""One core for `mapping-service map` and the live service (`service.core.slam.SlamSession`).

One short recording (a robot of the simulator, 160 scans at 40 Hz) goes through the live
service and through the command line; both must make the same trajectory and the same map.
The live session is stopped at the end of its scans, which finishes its core as the end of the
input finishes the command line's (the final loop search and batch optimisation).

Why the trajectories are compared to 1e-9 and not bit for bit: the live service records the
front end's poses and moves each by its latest node's correction when it serves them
(`service.app.backend.correct_poses`, vectorised, with corrections below 1e-9 taken as none);
the command line composes the same correction with the same pose one `Pose2D` at a time. The
maps are drawn by the one core on both sides, and compared exactly.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import numpy.typing as npt
import pytest
import zenoh
from conftest import REPO_ROOT, wait_for
from fastapi.testclient import TestClient
from svc_testkit import (
    RuntimeFactory,
    ServiceProc,
    SimRobot,
    runtime_factory_fixture,  # noqa: F401  # fixtures, used by name
)

from clients.keyexpr import scan_key
from clients.logs import iter_log_scans
from clients.recording import RecordingWriter
from clients.zenoh_config import build_zenoh_config
from service.app.api.app import create_app
from service.offline import map_scans

SCANS = 160


@pytest.fixture(scope="module", name="recording")
def recording_fixture(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[bytes]]:
    """The recording (`.mrec`) and its scans' wire payloads, in order."""
    robot = SimRobot("core-1", seed=2)
    payloads = [robot.next_payload() for _ in range(SCANS)]
    path = tmp_path_factory.mktemp("one-core") / "core-1.mrec"
    with RecordingWriter(path) as writer:
        for payload in payloads:
            writer.append(payload)
    return path, payloads


def _all_poses(get: Any, session_id: str) -> list[dict[str, Any]]:
    poses: list[dict[str, Any]] = []
    since = 0
    while True:
        page = get(f"/sessions/{session_id}/trajectory?since_seq={since}&limit=10000")
        poses.extend(page["poses"])
        if page["next_seq"] is None:
            return poses
        since = page["next_seq"]


def _tum(text: str) -> tuple[list[str], npt.NDArray[np.float64]]:
    """TUM text: (stamps as written, (N, 7) x y z qx qy qz qw)."""
    rows = [line.split() for line in text.splitlines()]
    return [r[0] for r in rows], np.array([[float(v) for v in r[1:]] for r in rows])


def _run_cli(recording: Path, out: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "map", str(recording), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        cwd=REPO_ROOT,
    )
    assert result.returncode == 0, result.stderr


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mappers", [0, 1], ids=["in-process", "mapper-process"])
def test_live_session_makes_the_offline_trajectory_and_map(
    runtime_factory: RuntimeFactory, recording: tuple[Path, list[bytes]], mappers: int
) -> None:
    """The scans through the service's ingest path (as its Zenoh callback hands them over),
    with the core in the service's process or in a mapper process; then `map_scans`, the
    function `mapping-service map` runs: the same nodes and closures, poses within 1e-9, and
    the same map, cell for cell."""
    path, payloads = recording
    runtime = runtime_factory(mapper_processes=mappers)
    with TestClient(create_app(runtime)) as client:
        sid = client.post("/sessions", json={"robot_id": "core-1"}).json()["id"]
        for payload in payloads:
            wait_for(lambda: runtime.ingest.pending() < 8, 60, "room in the ingest queue", 0.005)
            runtime.ingest.submit(scan_key("core-1"), payload)
        wait_for(
            lambda: client.get(f"/sessions/{sid}").json()["scans_accepted"] == SCANS,
            60,
            "every scan mapped",
        )
        assert client.post(f"/sessions/{sid}/stop").status_code == 200
        assert runtime.sessions.get(sid).wait_backend(60)
        graph = client.get(f"/sessions/{sid}/graph").json()
        assert graph["loop_closures"]["pending"] == 0
        live_poses = _all_poses(lambda u: client.get(u).json(), sid)
        live_map = runtime.sessions.get(sid).map_image().image

    run = map_scans(iter_log_scans(path))
    assert run.scans == len(live_poses) == SCANS
    assert run.loops is not None
    assert len(graph["nodes"]) == sum(e.is_keyframe for e in run.estimates) > 5
    assert graph["loop_closures"]["accepted"] == run.loops.accepted
    assert [p["stamp_ns"] for p in live_poses] == run.stamps_ns
    live_xyt = np.array([(p["x"], p["y"], p["theta"]) for p in live_poses])
    cli_xyt = np.array([tuple(p) for p in run.poses])
    np.testing.assert_allclose(live_xyt, cli_xyt, rtol=0, atol=1e-9)
    cli_map = run.image
    assert cli_map is not None
    assert (live_map.origin_x_m, live_map.origin_y_m) == (cli_map.origin_x_m, cli_map.origin_y_m)
    np.testing.assert_array_equal(live_map.occupancy, cli_map.occupancy)
    assert np.count_nonzero(cli_map.occupancy >= 0) > 1000


class _Publisher:
    """Publishes the payloads over Zenoh from a peer of its own, never more than 16 ahead of
    what the service accepted (so a slow machine drops none)."""

    def __init__(self, svc: ServiceProc, session_id: str, payloads: list[bytes]) -> None:
        self.svc = svc
        self.session_id = session_id
        self.payloads = payloads
        self.sent = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _accepted(self) -> int:
        return int(self.svc.json(f"/sessions/{self.session_id}")["scans_accepted"])  # type: ignore[call-overload]

    def _run(self) -> None:
        session = zenoh.open(build_zenoh_config(connect=[self.svc.zenoh_endpoint]))
        try:
            pub = session.declare_publisher(
                scan_key("core-1"), congestion_control=zenoh.CongestionControl.BLOCK
            )
            wait_for(lambda: pub.matching_status.matching, 30, "the service's subscription", 0.01)
            for payload in self.payloads:
                wait_for(lambda: self.sent - self._accepted() < 16, 60, "the service", 0.005)
                pub.put(payload)
                self.sent += 1
            pub.undeclare()  # type: ignore[no-untyped-call]
        except BaseException as err:  # reported by the test
            self.error = err
        finally:
            session.close()  # type: ignore[no-untyped-call]

    def __enter__(self) -> _Publisher:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._thread.join(timeout=60)

    def done(self) -> bool:
        if self.error is not None:
            pytest.fail(f"publisher failed: {self.error!r}")
        return not self._thread.is_alive()


@pytest.mark.timeout(300)
def test_serve_and_the_command_line_write_the_same_files(
    tmp_path: Path, recording: tuple[Path, list[bytes]]
) -> None:
    """Real processes: the scans published over Zenoh into `mapping-service serve` (its core in
    a mapper process), and the recording through `mapping-service map`: the served PGM and
    YAML are the command line's files byte for byte, the TUM trajectory the same stamps and
    the same poses to the file's precision."""
    path, payloads = recording
    out = tmp_path / "cli"
    _run_cli(path, out)
    svc = ServiceProc(tmp_path / "data", extra_args=["--mapper-processes", "1"])
    svc.start()
    try:
        sid = str(svc.create_session("core-1")["id"])
        with _Publisher(svc, sid, payloads) as publisher:
            wait_for(publisher.done, 120, "the scans to be published")
        wait_for(
            lambda: svc.json(f"/sessions/{sid}")["scans_accepted"] == SCANS,
            60,
            "every scan mapped",
        )
        stopped = httpx.post(f"{svc.url}/sessions/{sid}/stop", headers=svc.headers(), timeout=30)
        assert stopped.status_code == 200

        def settled() -> bool:
            graph: Any = svc.json(f"/sessions/{sid}/graph?nodes=false")
            return bool(graph["loop_closures"]["pending"] == 0)

        wait_for(settled, 60, "the back end to finish")
        # Nobody read the map while it was made: the first read composes it as the core has
        # it now, every scan and the final optimisation in (no render period to wait for).
        assert svc.get(f"/sessions/{sid}/map.pgm").content == (out / "map.pgm").read_bytes()
        assert svc.get(f"/sessions/{sid}/map.yaml").text == (out / "map.yaml").read_text()
        served = _tum(svc.get(f"/sessions/{sid}/trajectory?format=tum&limit=10000").text)
        written = _tum((out / "trajectory.tum").read_text())
        assert served[0] == written[0]  # the stamps, as text
        # Poses to the file's last digit: a pose the command line moves by 1e-17 prints as
        # "-0.000000" where the service's, moved by nothing, prints "0.000000".
        np.testing.assert_allclose(served[1], written[1], rtol=0, atol=1.01e-6)
    finally:
        svc.stop()
