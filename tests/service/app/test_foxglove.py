"""The Foxglove live view from a real client: `mapping-service serve --foxglove-port` and the
demo, read by a WebSocket client speaking the Foxglove protocol (tests/.../foxglove_client.py)."""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO_ROOT, free_port, wait_for
from foxglove_client import fetch
from svc_testkit import ServiceProc, SimRobot, zenoh_peer

from clients.keyexpr import scan_key
from clients.wire import encode_scan

pytestmark = pytest.mark.slow

ROBOT = "fox-1"


def _publish_scans(endpoint: str, robot: SimRobot, stop: threading.Event) -> None:
    with zenoh_peer(endpoint) as peer:
        while not stop.wait(0.025):
            peer.put(scan_key(robot.robot_id), encode_scan(robot.next_scan()))


def test_foxglove_client_decodes_grid_pose_scan_and_transform(tmp_path: Path) -> None:
    fox_port = free_port()
    svc = ServiceProc(tmp_path / "data")
    svc.start(args=["--foxglove-port", str(fox_port)])
    stop = threading.Event()
    feeder: threading.Thread | None = None
    try:
        sid = svc.create_session(ROBOT)["id"]
        robot = SimRobot(ROBOT)
        feeder = threading.Thread(target=_publish_scans, args=(svc.zenoh_endpoint, robot, stop))
        feeder.start()
        wait_for(lambda: svc.json(f"/sessions/{sid}")["poses"] >= 20, 60, "20 poses")
        topics = {f"/{ROBOT}/map", f"/{ROBOT}/pose", f"/{ROBOT}/scan", "/tf"}
        got = fetch(f"ws://127.0.0.1:{fox_port}", topics | {f"/{ROBOT}/trajectory"})
    finally:
        stop.set()
        if feeder is not None:
            feeder.join(timeout=10)
        code = svc.stop()
    assert code == 0, svc.log_tail()

    grid = got[f"/{ROBOT}/map"].message
    assert grid.frame_id == "map"
    assert [(f.name, f.offset) for f in grid.fields] == [("occupancy", 0)]
    assert grid.cell_stride == 1
    assert grid.row_stride == grid.column_count > 0
    cells = np.frombuffer(grid.data, dtype=np.int8)
    assert len(cells) % grid.column_count == 0
    assert cells.min() >= -1
    assert cells.max() <= 100
    assert (cells > 50).any(), "walls are in the map"
    assert math.isclose(grid.cell_size.x, 0.05)

    pose = got[f"/{ROBOT}/pose"].message
    assert pose.frame_id == "map"
    q = pose.pose.orientation
    assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, rel_tol=1e-9)
    # The scan's stamp (SimRobot's clock: 1.7e18 ns + 25 ms steps), not the wall clock's.
    stamp_ns = pose.timestamp.seconds * 1_000_000_000 + pose.timestamp.nanos
    assert (stamp_ns - 1_700_000_000_000_000_000) % 25_000_000 == 0
    assert got[f"/{ROBOT}/pose"].log_time_ns == stamp_ns

    transform = got["/tf"].message.transforms[0]
    assert (transform.parent_frame_id, transform.child_frame_id) == ("map", f"{ROBOT}/base_link")

    scan = got[f"/{ROBOT}/scan"].message
    assert scan.frame_id == f"{ROBOT}/base_link"
    assert len(scan.ranges) == 1081
    assert scan.start_angle < 0 < scan.end_angle

    line = got[f"/{ROBOT}/trajectory"].message.entities[0].lines[0]
    assert len(line.points) >= 2


def test_demo_prints_a_foxglove_address_a_client_reads(tmp_path: Path) -> None:
    http_port, fox_port = free_port(), free_port()
    err_path = tmp_path / "demo.log"
    with err_path.open("wb") as err:
        demo = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "service.cli",
                "demo",
                "--http-port",
                str(http_port),
                "--foxglove-port",
                str(fox_port),
                "--duration",
                "60",
            ],
            stdout=subprocess.PIPE,
            stderr=err,
            cwd=REPO_ROOT,
            # No --data-dir: the demo keeps its data in a named folder under XDG_DATA_HOME.
            env={**os.environ, "XDG_DATA_HOME": str(tmp_path / "xdg")},
        )
    try:
        assert demo.stdout is not None
        lines = [demo.stdout.readline().decode() for _ in range(3)]
        found = [m for line in lines if (m := re.search(r"Foxglove: (ws://\S+)", line))]
        assert found, f"no Foxglove line: {lines!r}\n{err_path.read_text()[-3000:]}"
        url = found[0].group(1)
        assert url == f"ws://127.0.0.1:{fox_port}"
        data_dir = tmp_path / "xdg" / "manhattan-mapper" / "demo"
        assert any(line.startswith(f"Data: {data_dir} ") for line in lines), lines
        got = fetch(url, {"/robot-1/map", "/robot-1/pose"}, timeout_s=60)
        assert got["/robot-1/map"].message.column_count > 0
        assert got["/robot-1/pose"].message.frame_id == "map"
        demo.send_signal(signal.SIGINT)
        assert demo.wait(timeout=30) == 0, err_path.read_text()[-3000:]
    finally:
        if demo.poll() is None:
            # Ctrl-C first: the demo stops its agents (own process groups); a bare kill
            # would orphan them.
            demo.send_signal(signal.SIGINT)
            try:
                demo.wait(timeout=30)
            except subprocess.TimeoutExpired:
                demo.kill()
                demo.wait()
    # The data outlives the demo (a temporary folder would be gone with the saved maps).
    assert list((data_dir / "sessions").iterdir())
