"""The live back end: loop closure in the service, its graph endpoint, corrected outputs.

In-process: a robot driving once around the corridor loop of synthetic building 1 (2 m/s, so
one loop is ~1,830 scans) through the real ingest path; then the graph, the trajectory, the
pose, the map and the counters. `test_live_loop_closure_real_processes` is the issue's
acceptance test: real `mapping-service serve`, scans over Zenoh, a loop, then kill -9.
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from conftest import wait_for
from fastapi.testclient import TestClient
from svc_testkit import (
    SCAN_PERIOD_NS,
    RuntimeFactory,
    ServiceProc,
    SimRobot,
    feed,
    metric_sum,
    relative,
    runtime_factory_fixture,  # noqa: F401  # fixtures, used by name
    runtime_fixture,  # noqa: F401
)

from clients import MappingClient
from clients.keyexpr import scan_key
from clients.zenoh_config import build_zenoh_config
from sensor_agent.sim import RobotMotion
from service.app.api.app import create_app
from service.app.foxglove import session_loop_closures
from service.app.runtime import MappingRuntime
from service.app.settings import IngestSettings, ServiceSettings, StorageSettings
from service.core.backend.params import GraphParams

SEED = 1
SPEED_MPS = 2.0  # one loop in ~46 s of scans (1,830): the closure comes back at the start


def loop_robot(robot_id: str) -> SimRobot:
    robot = SimRobot(robot_id, seed=SEED)
    robot.motion = RobotMotion(robot.world, SEED, speed_mps=SPEED_MPS)
    return robot


def loop_scans(robot: SimRobot) -> int:
    """Scans for one loop and one second more."""
    return int(robot.motion.loop_period_s * 1e9 / SCAN_PERIOD_NS) + 40


def loop_gap_m(robot: SimRobot, poses: list[dict[str, Any]]) -> float:
    """The last pose relative to the first, against the simulator's truth (stamps -> time)."""
    t0_ns = robot._t0_ns

    def truth(p: dict[str, Any]) -> tuple[float, float, float]:
        return robot.motion.pose_at((int(p["stamp_ns"]) - t0_ns) / 1e9)

    first, last = poses[0], poses[-1]
    est = relative((first["x"], first["y"], first["theta"]), (last["x"], last["y"], last["theta"]))
    true = relative(truth(first), truth(last))
    return float(math.hypot(est[0] - true[0], est[1] - true[1]))


def _all_poses(get: Any, session_id: str) -> list[dict[str, Any]]:
    poses: list[dict[str, Any]] = []
    since = 0
    while True:
        page = get(f"/sessions/{session_id}/trajectory?since_seq={since}&limit=10000")
        poses.extend(page["poses"])
        if page["next_seq"] is None:
            return poses
        since = page["next_seq"]


def test_loop_closure_in_process(runtime: MappingRuntime) -> None:
    """A loop closes; the trajectory, the pose and the map come from the graph; counters."""
    robot = loop_robot("lc-1")
    with TestClient(create_app(runtime)) as client:
        sid = client.post("/sessions", json={"robot_id": "lc-1", "use_odometry": False}).json()[
            "id"
        ]
        feed(runtime, robot, loop_scans(robot))

        def closed() -> dict[str, Any] | None:
            g = client.get(f"/sessions/{sid}/graph").json()
            done = g["loop_closures"]["accepted"] >= 1 and g["loop_closures"]["pending"] == 0
            return g if done else None

        graph = wait_for(closed, 60, "an accepted loop closure")
        nodes = graph["nodes"]
        assert len(nodes) > 100
        assert [n["id"] for n in nodes] == list(range(len(nodes)))
        assert graph["edges"][0] == {"from_node": 0, "to_node": 1}
        assert len(graph["edges"]) == len(nodes) - 1
        accepted = [c for c in graph["closures"] if c["accepted"]]
        assert accepted
        assert all(c["to_node"] - c["from_node"] >= 60 for c in accepted)
        assert all(c["reason"] == "accepted" and c["score"] >= 0.55 for c in accepted)

        # On this synthetic loop the front end is exact to a cell: the closures agree with it
        # and move nothing. A closure that pulls the end 0.3 m (added to the graph by hand,
        # the one fault made here) shows what a correction does to every output.
        published: list[Any] = []
        publish = runtime.ingest._publish
        runtime.ingest._publish = lambda pose, data: (published.append(pose), publish(pose, data))
        mapper = runtime.sessions.get(sid)._mapper
        assert mapper is not None
        assert mapper.wait_backend(30)  # type: ignore[attr-defined]  # every map drawn
        before_png = client.get(f"/sessions/{sid}/map.pgm").content
        # The back end's own revision now: maps drawn since `closed` bumped it.
        latest = mapper.graph()
        assert latest is not None
        revision = latest.revision
        _pull_last_node(runtime, sid, 0.3)

        def after_closure() -> tuple[dict[str, Any], dict[int, Any], dict[str, Any]] | None:
            # The graph, the trajectory and the pose are separate reads: they count together
            # only if no newer graph was published between them (the back end may still relax).
            g = client.get(f"/sessions/{sid}/graph").json()
            if g["revision"] <= revision:
                return None
            served = {p["sequence"]: p for p in _all_poses(lambda u: client.get(u).json(), sid)}
            now = client.get(f"/sessions/{sid}/pose").json()
            same = client.get(f"/sessions/{sid}/graph?nodes=false").json()["revision"]
            return (g, served, now) if same == g["revision"] else None

        graph, poses, pose = wait_for(after_closure, 10, "the graph after the closure")
        nodes = graph["nodes"]
        moved = 0.0
        for n in nodes:  # every node's scan, as served, sits where the graph put its node
            p = poses[n["sequence"]]
            assert p["x"] == pytest.approx(n["x"], abs=1e-6)
            assert p["y"] == pytest.approx(n["y"], abs=1e-6)
            moved = max(moved, math.hypot(n["x"] - n["frontend_x"], n["y"] - n["frontend_y"]))
        assert moved > 0.1
        last = max(poses.values(), key=lambda p: p["sequence"])
        assert pose["sequence"] == last["sequence"]
        assert (pose["x"], pose["y"]) == pytest.approx((last["x"], last["y"]), abs=1e-9)
        end = nodes[-1]
        assert math.hypot(pose["x"] - end["frontend_x"], pose["y"] - end["frontend_y"]) > 0.1
        # The map follows (drawn again by the back end within its period).
        wait_for(
            lambda: client.get(f"/sessions/{sid}/map.pgm").content != before_png, 10, "the map"
        )
        # The next scans are published where the graph puts them.
        feed(runtime, robot, 5)
        assert len(published) == 5
        served = client.get(f"/sessions/{sid}/pose").json()
        assert served["sequence"] == published[-1].seq
        assert (served["x"], served["y"]) == pytest.approx(
            (published[-1].x_m, published[-1].y_m), abs=1e-6
        )
        recorded = runtime.sessions.get(sid)._poses[-1]  # the front end's, as recorded
        assert recorded.seq == published[-1].seq
        assert math.hypot(published[-1].x_m - recorded.x_m, published[-1].y_m - recorded.y_m) > 0.1

        session = client.get(f"/sessions/{sid}").json()
        assert session["loop_closures"]["accepted"] == graph["loop_closures"]["accepted"]
        # The five scans fed since may have made a keyframe: the graph's count, read now.
        assert mapper.wait_backend(30)  # type: ignore[attr-defined]
        now = client.get(f"/sessions/{sid}/graph").json()
        assert client.get(f"/sessions/{sid}").json()["loop_closures"]["nodes"] == len(now["nodes"])
        assert len(nodes) <= len(now["nodes"]) <= len(nodes) + 5
        metrics = runtime.metrics.render()
        assert f'mapping_loop_closures_accepted{{session="{sid}"}}' in metrics
        # The solver never needed its QR rebuild here; the counter says so (`PoseGraph.update`).
        assert now["loop_closures"]["solver_restarts"] == 0
        assert f'mapping_graph_solver_restarts{{session="{sid}"}} 0' in metrics

        # The map is the core's, drawn at the optimised poses (by the back end's thread).
        yaml_text = client.get(f"/sessions/{sid}/map.yaml").text
        assert "resolution: 0.05" in yaml_text
        png = client.get(f"/sessions/{sid}/map.png?trajectory=true").content
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        session_obj = runtime.sessions.get(sid)
        image = session_obj.map_image().image
        assert image.width > 100
        assert image.height > 100
        lines = session_obj.loop_closures()
        # (`now`: the five scans fed since `graph` may have made a keyframe, and it a closure)
        assert len(lines) == now["loop_closures"]["accepted"]
        assert list(session_loop_closures(session_obj)) == lines  # the Foxglove view's hook

        light = client.get(f"/sessions/{sid}/graph?nodes=false").json()
        assert light["nodes"] == []
        assert light["closures"][0]["from_x"] == pytest.approx(accepted[0]["from_x"], abs=1e-3)


def _pull_last_node(runtime: MappingRuntime, session_id: str, offset_m: float) -> None:
    """Add a closure that puts the newest node `offset_m` (along x) from where the graph has
    it, relative to node 0, as if the loop search had found it; then let the back end publish."""
    from service.core.types import Pose2D

    backend = runtime.sessions.get(session_id)._mapper._backend  # type: ignore[union-attr]
    with backend._work:
        core = backend._core
        last = core.node_count - 1
        rel = core.graph.estimate(0).between(core.graph.estimate(last))
        target = Pose2D(rel.x_m + offset_m, rel.y_m, rel.theta_rad)
        core.graph.add_loop(0, last, target, np.diag([1e-6, 1e-6, 1e-8]))
        core.graph.update()
        correction = core.latest_correction()
        with backend._lock:
            backend._revision += 1
            backend._correction = correction
        backend._view_due = backend._image_due = True
        backend._last_map_s = 0.0
    backend._scheduler.schedule(backend)


def test_loop_closure_in_a_mapper_process(runtime_factory: RuntimeFactory) -> None:
    """With mapper processes the back end runs there; a mapper process killed takes the graph
    along, and the session rebuilds it from the recording with the rest of its state."""
    runtime = runtime_factory(mapper_processes=1)
    assert runtime.mapper_pool is not None
    robot = loop_robot("mp-1")
    with TestClient(create_app(runtime)) as client:
        sid = client.post("/sessions", json={"robot_id": "mp-1", "use_odometry": False}).json()[
            "id"
        ]
        feed(runtime, robot, loop_scans(robot))

        def closed(min_nodes: int = 0) -> dict[str, Any] | None:
            g = client.get(f"/sessions/{sid}/graph").json()
            counts = g["loop_closures"]
            done = counts["accepted"] >= 1 and counts["pending"] == 0
            return g if done and len(g["nodes"]) >= min_nodes else None

        graph = wait_for(closed, 60, "an accepted loop closure in the mapper process")
        pid = runtime.mapper_pool.pids[0]
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        feed(runtime, robot, 3)  # the next scan finds the process gone: rebuilt, then mapped
        pool = runtime.mapper_pool

        def rebuilt() -> dict[str, Any] | None:
            # From a new process: under load a graph answer can come before the restart.
            g = closed(len(graph["nodes"]))
            return g if g is not None and pool.pids[0] not in (None, pid) else None

        again = wait_for(rebuilt, 60, "the graph rebuilt in a new mapper process")
        n = len(graph["nodes"])
        before = np.array([(v["x"], v["y"]) for v in graph["nodes"]])
        after = np.array([(v["x"], v["y"]) for v in again["nodes"][:n]])
        assert np.abs(after - before).max() < 1e-6
        assert again["loop_closures"]["accepted"] == graph["loop_closures"]["accepted"]
        # The rebuilt nodes are named by the same pose sequences.
        assert [v["sequence"] for v in again["nodes"][:n]] == [
            v["sequence"] for v in graph["nodes"]
        ]


def test_front_end_alone_has_an_empty_graph(tmp_path: Path) -> None:
    settings = ServiceSettings(
        storage=StorageSettings(data_dir=tmp_path / "data", fsync_interval_s=0.2),
        ingest=IngestSettings(loop_closure=False),
    )
    runtime = MappingRuntime(settings, zenoh_config=build_zenoh_config())
    runtime.start()
    try:
        robot = loop_robot("fe-1")
        with TestClient(create_app(runtime)) as client:
            sid = client.post("/sessions", json={"robot_id": "fe-1"}).json()["id"]
            feed(runtime, robot, 200)
            graph = client.get(f"/sessions/{sid}/graph").json()
            assert graph["nodes"] == []
            assert graph["loop_closures"]["accepted"] == 0
            assert client.get(f"/sessions/{sid}").json()["loop_closures"]["nodes"] == 0
            assert client.get(f"/sessions/{sid}/map.yaml").status_code == 200
    finally:
        runtime.close()


def test_graph_needs_the_read_token(runtime_factory: RuntimeFactory) -> None:
    runtime = runtime_factory(token="c" * 24, read_token="r" * 24)
    with TestClient(create_app(runtime)) as client:
        control = {"Authorization": "Bearer " + "c" * 24}
        sid = client.post("/sessions", json={"robot_id": "tok-1"}, headers=control).json()["id"]
        assert client.get(f"/sessions/{sid}/graph").status_code == 401
        read = {"Authorization": "Bearer " + "r" * 24}
        assert client.get(f"/sessions/{sid}/graph", headers=read).status_code == 200
        schema = client.get("/openapi.json", headers=read).json()
        assert "/sessions/{session_id}/graph" in schema["paths"]
        assert "Graph" in schema["components"]["schemas"]


class _Publisher:
    """A robot driving the loop, published over Zenoh as fast as the service takes it in
    (at most `ahead` scans beyond what the service has accepted: nothing is dropped)."""

    def __init__(self, svc: ServiceProc, robot: SimRobot, session_id: str, count: int) -> None:
        self.svc, self.robot, self.session_id, self.count = svc, robot, session_id, count
        self.sent = 0
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="loop-publisher", daemon=True)

    def _accepted(self) -> int:
        return int(self.svc.json(f"/sessions/{self.session_id}")["scans_accepted"])

    def _run(self) -> None:
        session = zenoh.open(build_zenoh_config(connect=[self.svc.zenoh_endpoint]))
        try:
            pub = session.declare_publisher(
                scan_key(self.robot.robot_id), congestion_control=zenoh.CongestionControl.BLOCK
            )
            accepted = 0
            while self.sent < self.count and not self._stop.is_set():
                if self.sent - accepted >= 16:
                    accepted = self._accepted()
                    if self.sent - accepted >= 16:
                        time.sleep(0.005)
                        continue
                pub.put(self.robot.next_payload())
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
        self._stop.set()
        self._thread.join(timeout=10)

    def done(self) -> bool:
        if self.error is not None:
            pytest.fail(f"publisher failed: {self.error!r}")
        return not self._thread.is_alive()


@pytest.mark.slow
def test_live_loop_closure_real_processes(tmp_path: Path) -> None:
    """Issue 13's live acceptance: a loop through Zenoh into `serve`; back at its start, the
    HTTP graph has an accepted closure and the trajectory's loop gap against the simulator's
    truth is <= 0.1 m; kill -9, restart: the graph and the corrected trajectory are back."""
    svc = ServiceProc(tmp_path / "data")
    svc.start()
    try:
        sid = str(svc.create_session("loop-1", use_odometry=False)["id"])
        robot = loop_robot("loop-1")
        count = loop_scans(robot)
        # The emulated robot publishes (over Zenoh, scans stamped on the simulated 40 Hz
        # clock) as fast as the service takes them in: a loop in ~30 s instead of 46 s.
        with _Publisher(svc, robot, sid, count) as publisher:
            wait_for(publisher.done, 120, "the loop to be published")
        assert publisher.sent == count
        wait_for(
            lambda: svc.json(f"/sessions/{sid}")["scans_accepted"] == count,
            30,
            "every scan mapped",
        )

        def closed() -> dict[str, Any] | None:
            g = svc.json(f"/sessions/{sid}/graph")
            counts: Any = g["loop_closures"]
            return g if counts["accepted"] >= 1 and counts["pending"] == 0 else None

        graph = wait_for(closed, 30, "an accepted loop closure on the HTTP graph")
        poses = _all_poses(svc.json, sid)
        assert len(poses) == count
        gap = loop_gap_m(robot, poses)
        assert gap <= 0.1, f"loop gap {gap:.3f} m"
        with MappingClient(svc.url) as api:
            typed = api.get_graph(sid)
        assert typed.accepted == graph["loop_closures"]["accepted"]  # type: ignore[index]
        assert typed.accepted_closures
        assert len(typed.nodes) == len(graph["nodes"])
        assert metric_sum(svc.metrics(), "mapping_loop_closures_accepted", session=sid) >= 1

        svc.kill9()  # no checkpoint since the start: the recording is replayed
        svc.start()

        def restored() -> dict[str, Any] | None:
            g = svc.json(f"/sessions/{sid}/graph")
            counts: Any = g["loop_closures"]
            done = counts["pending"] == 0 and len(g["nodes"]) == len(graph["nodes"])  # type: ignore[arg-type]
            return g if done and counts["accepted"] >= 1 else None

        again = wait_for(restored, 60, "the graph rebuilt after kill -9")
        before = np.array([(n["x"], n["y"]) for n in graph["nodes"]])  # type: ignore[union-attr]
        after = np.array([(n["x"], n["y"]) for n in again["nodes"]])
        assert np.abs(after - before).max() < 1e-6  # the same nodes, the same closures
        assert again["loop_closures"] == graph["loop_closures"]
        poses_after = _all_poses(svc.json, sid)
        assert len(poses_after) == count
        assert loop_gap_m(robot, poses_after) == pytest.approx(gap, abs=1e-6)

        # A clean stop writes a checkpoint (with the back end): it restores without a replay.
        assert svc.stop() == 0
        svc.start()
        third = wait_for(restored, 30, "the graph from the checkpoint")
        after = np.array([(n["x"], n["y"]) for n in third["nodes"]])
        # The same factors, relinearised at the saved estimate: one Gauss-Newton step from
        # there, which the live iSAM2 (relinearising only variables that moved more than
        # `GraphParams.relinearize_threshold`, 1 cm) need not have taken. Closures off the
        # guess by millimetres (refined peaks) move it by that much (2.6 mm measured).
        assert np.abs(after - before).max() < GraphParams().relinearize_threshold
        assert third["loop_closures"]["accepted"] == graph["loop_closures"]["accepted"]  # type: ignore[index]
    finally:
        svc.stop()
