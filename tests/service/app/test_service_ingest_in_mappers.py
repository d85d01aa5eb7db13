"""Mapper processes that ingest (`--mapper-processes K`, the default layout), as real processes.

Each mapper process takes its robots' scans from Zenoh itself and maps, records and publishes
them; the service's process never takes a scan in. Checked here: two robots in two processes
both map every scan (and their poses reach Zenoh), /metrics and /health count the processes'
scans, a `kill -9` of a mapper process is recovered from (rebuilt from the recording, mapping
again), and a restart serves exactly what was recorded.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest
import zenoh
from conftest import wait_for
from svc_testkit import ServiceProc, SimRobot, metric_sum

from clients.keyexpr import pose_key, scan_key
from clients.zenoh_config import build_zenoh_config

pytestmark = pytest.mark.slow


def _service(tmp_path: Path, processes: int) -> Iterator[ServiceProc]:
    svc = ServiceProc(
        tmp_path / "data",
        extra_args=["--mapper-processes", str(processes)],
    )
    svc.start(timeout_s=60)
    try:
        yield svc
    finally:
        svc.stop()


@pytest.fixture(name="svc2")
def svc2_fixture(tmp_path: Path) -> Iterator[ServiceProc]:
    yield from _service(tmp_path, 2)


@pytest.fixture(name="svc1")
def svc1_fixture(tmp_path: Path) -> Iterator[ServiceProc]:
    yield from _service(tmp_path, 1)


def _client(svc: ServiceProc) -> zenoh.Session:
    return zenoh.open(build_zenoh_config(mode="client", connect=[svc.zenoh_endpoint]))


def _accepted(svc: ServiceProc, session_id: str) -> tuple[int, int]:
    info = svc.json(f"/sessions/{session_id}")
    return int(info["scans_accepted"]), int(info["poses"])  # type: ignore[call-overload]


def _mapper_pids(svc: ServiceProc) -> list[int]:
    """The service's mapper processes (spawned; not multiprocessing's resource tracker)."""
    assert svc.proc is not None
    out = []
    for child in psutil.Process(svc.proc.pid).children():
        try:
            cmd = " ".join(child.cmdline())
        except psutil.Error:
            continue
        if "spawn_main" in cmd:
            out.append(child.pid)
    return out


@pytest.mark.timeout(180)
def test_two_robots_in_two_processes_map_every_scan_and_the_service_takes_none_in(
    svc2: ServiceProc,
) -> None:
    robots = [SimRobot("mi-a", seed=1), SimRobot("mi-b", seed=2)]
    sessions = {r.robot_id: str(svc2.create_session(r.robot_id)["id"]) for r in robots}
    poses_seen: dict[str, int] = {r.robot_id: 0 for r in robots}
    count = 40
    with _client(svc2) as z:

        def on_pose(sample: zenoh.Sample) -> None:
            robot_id = str(sample.key_expr).split("/")[-2]
            poses_seen[robot_id] += 1

        subs = [z.declare_subscriber(pose_key(r.robot_id), on_pose) for r in robots]
        pubs = {r.robot_id: z.declare_publisher(scan_key(r.robot_id)) for r in robots}
        time.sleep(1.0)  # declarations propagate
        for _ in range(count):
            for robot in robots:
                pubs[robot.robot_id].put(robot.next_payload())
            time.sleep(0.025)
        for robot in robots:
            wait_for(
                lambda r=robot: _accepted(svc2, sessions[r.robot_id]) == (count, count),
                60,
                f"{robot.robot_id}: every scan recorded and mapped",
            )
        wait_for(lambda: all(v == count for v in poses_seen.values()), 10, "every pose on Zenoh")
        for sub in subs:
            sub.undeclare()  # type: ignore[no-untyped-call]
        for pub in pubs.values():
            pub.undeclare()  # type: ignore[no-untyped-call]

    # The counts reach /metrics from the processes (every half second); the service's own
    # ingest took no payload in: it never decoded a scan.
    def counted() -> bool:
        m = svc2.metrics()
        return metric_sum(m, "mapping_scans_accepted_total") == 2 * count

    wait_for(counted, 10, "the processes' counters in /metrics")
    m = svc2.metrics()
    assert metric_sum(m, "mapping_ingest_payloads_total", process="main") == 0
    # Each robot went to its own process (the least busy when its session started).
    assert metric_sum(m, "mapping_ingest_payloads_total", process="mapper-0") == count
    assert metric_sum(m, "mapping_ingest_payloads_total", process="mapper-1") == count
    assert metric_sum(m, "mapping_poses_published_total") == 2 * count
    assert m["mapping_scan_processing_seconds_count"] == 2 * count
    health = svc2.json("/health")
    assert health["ingest"]["robots_tracked"] == 2  # type: ignore[index]
    assert health["ingest"]["scans_accepted"] == 2 * count  # type: ignore[index]
    assert {r["robot_id"] for r in health["robots"]} == {"mi-a", "mi-b"}  # type: ignore[union-attr,index]
    # Reads: the pose and the trajectory come from the service's copy.
    for robot in robots:
        sid = sessions[robot.robot_id]
        assert svc2.json(f"/sessions/{sid}/pose")["sequence"] == count - 1
        assert len(svc2.json(f"/sessions/{sid}/trajectory")["poses"]) == count  # type: ignore[arg-type]


@pytest.mark.timeout(240)
def test_a_killed_mapper_process_is_recovered_and_a_restart_serves_what_was_recorded(
    svc1: ServiceProc,
) -> None:
    robot = SimRobot("mi-k", seed=3)
    sid = str(svc1.create_session(robot.robot_id)["id"])
    with _client(svc1) as z:
        pub = z.declare_publisher(scan_key(robot.robot_id))
        wait_for(lambda: pub.matching_status.matching, 30, "a mapper process's scan subscription")
        for _ in range(30):
            pub.put(robot.next_payload())
            time.sleep(0.025)
        wait_for(lambda: _accepted(svc1, sid) == (30, 30), 60, "30 scans mapped")
        (pid,) = _mapper_pids(svc1)
        os.kill(pid, signal.SIGKILL)
        # Rebuilt from the recording in a new process; keep publishing until it maps again.
        deadline = time.monotonic() + 90
        while _accepted(svc1, sid)[0] < 50:
            assert time.monotonic() < deadline, svc1.log_tail()
            pub.put(robot.next_payload())
            time.sleep(0.05)
        pub.undeclare()  # type: ignore[no-untyped-call]
    assert _mapper_pids(svc1) != [pid]
    assert metric_sum(svc1.metrics(), "mapping_mapper_restarts") == 1
    wait_for(lambda: _accepted(svc1, sid)[0] == _accepted(svc1, sid)[1], 10, "a pose per scan")
    before = svc1.json(f"/sessions/{sid}/trajectory")["poses"]
    accepted = _accepted(svc1, sid)
    # Every pose kept its place in the sequence across the rebuild.
    seqs = [p["sequence"] for p in before]  # type: ignore[union-attr,index]
    assert seqs == list(range(len(seqs)))

    # A restart replays what was recorded: the same counts and the same trajectory.
    assert svc1.stop() == 0
    svc1.start(timeout_s=90)
    assert _accepted(svc1, sid) == accepted
    after = svc1.json(f"/sessions/{sid}/trajectory")["poses"]
    assert [p["sequence"] for p in after] == seqs  # type: ignore[union-attr,index]
    assert len(_mapper_pids(svc1)) == 1
