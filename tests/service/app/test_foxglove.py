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
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import REPO_ROOT, free_port, wait_for
from foxglove_client import fetch
from svc_testkit import ServiceProc, SimRobot, zenoh_peer

import service.app.foxglove as foxglove_view
from clients.keyexpr import scan_key
from clients.wire import Pose, encode_scan
from service.app.foxglove import FoxgloveView
from service.app.sessions import MapSnapshot
from service.core.maps.grid import GridImage

pytestmark = pytest.mark.slow

ROBOT = "fox-1"


def _publish_scans(endpoint: str, robot: SimRobot, stop: threading.Event) -> None:
    with zenoh_peer(endpoint) as peer:
        while not stop.wait(0.025):
            peer.put(scan_key(robot.robot_id), encode_scan(robot.next_scan()))


WATCHED = f"a viewer watches {ROBOT}'s scans"
RELEASED = f"no viewer of {ROBOT}'s scans"


# Both layouts: one process (the scans are in the service's process), and the scans taken in by
# a mapper process (the service's process takes a watched robot's scans from Zenoh for display).
@pytest.mark.parametrize(
    "layout", [[], ["--mapper-processes", "1"]], ids=["one-process", "mapper-processes"]
)
def test_foxglove_client_decodes_grid_pose_scan_and_transform(
    tmp_path: Path, layout: list[str]
) -> None:
    fox_port = free_port()
    svc = ServiceProc(tmp_path / "data", extra_args=layout)
    svc.start(args=["--foxglove-port", str(fox_port)], timeout_s=60)
    stop = threading.Event()
    feeder: threading.Thread | None = None
    try:
        sid = svc.create_session(ROBOT)["id"]
        robot = SimRobot(ROBOT)
        feeder = threading.Thread(target=_publish_scans, args=(svc.zenoh_endpoint, robot, stop))
        feeder.start()
        wait_for(lambda: svc.json(f"/sessions/{sid}")["poses"] >= 20, 60, "20 poses")
        # Nobody watches yet: the service's process takes no scan key for the view.
        assert WATCHED not in svc.log_path.read_text()
        topics = {f"/{ROBOT}/map", f"/{ROBOT}/pose", f"/{ROBOT}/scan", "/tf"}
        got = fetch(f"ws://127.0.0.1:{fox_port}", topics | {f"/{ROBOT}/trajectory"})
        if layout:  # the viewer is gone: the scan key is released again
            wait_for(lambda: RELEASED in svc.log_path.read_text(), 10, "the scan key released")
            assert svc.log_path.read_text().count(WATCHED) == 1
        else:  # the ingest hands the view its scans: no scan key of its own
            assert WATCHED not in svc.log_path.read_text()
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


def _sessions_or_error(http_port: int) -> str:
    """The demo's sessions as the API lists them (what a failed fetch needs next to it)."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{http_port}/sessions", timeout=5) as r:
            return str(r.read().decode()[:3000])
    except OSError as err:
        return f"unavailable ({err})"


@dataclass
class _StillSession:
    """A session as the view reads it: a small fixed map, no trajectory."""

    robot_id: str
    id: str = field(init=False)
    map_revision: int = 1
    is_active: bool = True
    status: str = "ok"

    def __post_init__(self) -> None:
        self.id = f"s-{self.robot_id}"

    def map_image(self) -> Any:
        image = GridImage(np.full((4, 6), 100, dtype=np.int8), 0.0, 0.0, 0.05)
        return MapSnapshot(image, np.empty((0, 2)), None, self.map_revision)

    def trajectory(self) -> list[Pose]:
        return []


def test_a_viewer_connected_before_the_robots_appear_gets_every_map(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A viewer subscribes to a topic the moment it is advertised (a saved layout does). The SDK
    rejects about one such subscribe in five as "unknown channel" (foxglove-sdk 0.30): without
    the view's re-advertisement, 20 robots appearing one by one lose a map 98 % of the time."""
    monkeypatch.setattr(foxglove_view, "MAP_PERIOD_S", 0.2)  # robots found 5 times a second
    sessions: list[_StillSession] = []
    view = FoxgloveView(lambda: list(sessions), port=0)
    view.start()
    robots = [f"late-{i}" for i in range(20)]

    def appear() -> None:
        time.sleep(0.5)  # the viewer connects first
        for robot_id in robots:
            sessions.append(_StillSession(robot_id))
            time.sleep(0.25)  # one robot per pass over the sessions: each its own advertisement

    arrivals = threading.Thread(target=appear)
    arrivals.start()
    try:
        got = fetch(view.url, {f"/{r}/map" for r in robots}, timeout_s=30)
    finally:
        arrivals.join()
        view.close()
    assert all(got[f"/{r}/map"].message.column_count == 6 for r in robots)


@dataclass
class _FakeFeed:
    robot: SimRobot
    closed: bool = False

    def latest(self) -> Any:
        return self.robot.next_scan()

    def close(self) -> None:
        self.closed = True


def test_a_scan_tap_is_opened_only_while_a_viewer_watches_the_scans(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With the scans in the mapper processes the view takes a robot's scans itself: nothing
    while nobody watches them (a viewer of the map alone opens nothing), one feed while a
    viewer subscribes to the scan channel, closed when it leaves."""
    monkeypatch.setattr(foxglove_view, "MAP_PERIOD_S", 0.2)
    feeds: list[_FakeFeed] = []

    def tap(robot_id: str) -> _FakeFeed:
        feeds.append(_FakeFeed(SimRobot(robot_id)))
        return feeds[-1]

    view = FoxgloveView(lambda: [_StillSession("tap-1")], port=0, scan_tap=tap)
    view.start()
    try:
        fetch(view.url, {"/tap-1/map"}, timeout_s=30)
        time.sleep(0.3)  # a few passes of the publisher thread
        assert feeds == []
        got = fetch(view.url, {"/tap-1/scan"}, timeout_s=30)
        assert len(got["/tap-1/scan"].message.ranges) == 1081
        assert len(feeds) == 1
        wait_for(lambda: feeds[0].closed, 10, "the feed closed after the viewer left")
    finally:
        view.close()
    assert len(feeds) == 1


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
        try:
            got = fetch(url, {"/robot-1/map", "/robot-1/pose"}, timeout_s=60)
        except TimeoutError as err:
            raise AssertionError(
                f"{err}\nsessions: {_sessions_or_error(http_port)}\n"
                f"demo log:\n{err_path.read_text()[-3000:]}"
            ) from None
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
