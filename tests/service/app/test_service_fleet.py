"""Acceptance with real processes on loopback: the demo's agent path against ground truth, a fleet
of robots in one service, five Zenoh pose subscribers, and a flood of malformed scans.

Against ground truth, poses are compared as motion relative to the first pose (the estimator's map
frame is its first scan's frame), on several figures at once, so that no single one can be fooled
(a tracker frozen at its first pose has no end-point error after a loop, but no distance either):
distance travelled, end-point error, absolute trajectory error (RMS and worst) and final heading.
The bounds are the measured values plus a stated margin; see `LOCKSTEP` and `AGENT_PATH`.
"""

from __future__ import annotations

import io
import itertools
import re
import signal
import subprocess
import sys
import threading
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil
import pytest
import zenoh
from conftest import REPO_ROOT, free_port
from PIL import Image
from svc_testkit import (
    ServiceProc,
    SimRobot,
    check_against_truth,
    malformed_payloads,
    metric_sum,
    wait_for,
    zenoh_peer,
)

from clients.keyexpr import pose_key, scan_key
from clients.wire import Pose, decode_pose
from sensor_agent.scene import WorldScene
from sensor_agent.sim import RobotMotion, generate_building

pytestmark = pytest.mark.slow


# ---------------------------------------------------------------------------------------------
# Ground truth helpers


@dataclass(frozen=True)
class Tolerance:
    distance_rel: float  # |distance estimated - true| / true
    end_error_m: float
    ate_rms_m: float
    ate_max_m: float
    heading_deg: float


# Scans on a simulated 40 Hz clock, taken in lockstep (deterministic: the same figures in every
# run). Measured over robots ra, rb, rc (2.08 m each) with the default front end, the matcher:
# distance -0.23 .. +0.11 %, end point 3.6-10.7 mm, ATE RMS 6.5-10.5 mm, ATE worst 8.7-12.8 mm,
# heading 0.025-0.058°. Bounds: about three times the worst, for other machines' floating point
# and future estimator changes.
LOCKSTEP = Tolerance(
    distance_rel=0.01, end_error_m=0.03, ate_rms_m=0.03, ate_max_m=0.04, heading_deg=0.2
)
# The demo's agent path: stamps are the agent's wall clock when it read each scan, so load on
# this machine shifts them against the emulator's scene time (0.7 m/s x the jitter), and the
# time alignment with them. Measured over 5.0-5.5 m with the machine lightly loaded: distance
# -0.06 .. -0.003 %, end point 0.6-3.0 mm, ATE RMS 11-21 mm, ATE worst 64-182 mm, heading
# 0.004-0.016°; in a full suite run with the machine loaded by other work: distance +1.5 %,
# end point and ATE RMS 78 mm, worst 100 mm, heading 0.036°. Bounds: the loaded run plus
# about 2.5x on the distances, which a frozen or scaled tracker still fails by far.
AGENT_PATH = Tolerance(
    distance_rel=0.05, end_error_m=0.2, ate_rms_m=0.2, ate_max_m=0.5, heading_deg=1.0
)


def assert_within_tolerance(
    report: dict[str, float], min_distance_m: float, tol: Tolerance
) -> None:
    d = report["distance_true_m"]
    assert d >= min_distance_m, report
    assert abs(report["distance_est_m"] - d) <= tol.distance_rel * d, report
    assert report["end_error_m"] <= tol.end_error_m, report
    assert report["ate_rms_m"] <= tol.ate_rms_m, report
    assert report["ate_max_m"] <= tol.ate_max_m, report
    assert report["heading_error_deg"] <= tol.heading_deg, report


def map_shows_corridors(png: bytes, pgm: bytes, resolution_m: float) -> None:
    """The PNG decodes to free space and walls; the PGM has long parallel wall lines."""
    gray = np.asarray(Image.open(io.BytesIO(png)).convert("L"))
    free_px = np.count_nonzero(gray > 235)
    wall_px = np.count_nonzero(gray < 80)
    assert free_px > 0.05 * gray.size, (free_px, gray.size)
    assert wall_px > 0.002 * gray.size, (wall_px, gray.size)
    header, _, pixels = _split_pgm(pgm)
    w, h = header
    cells = np.frombuffer(pixels, dtype=np.uint8).reshape(h, w)
    occupied = cells == 0
    min_cells = int(2.0 / resolution_m)  # a wall line of 2 m or more
    lines = [
        *(("row", i) for i in np.flatnonzero(occupied.sum(axis=1) >= min_cells)),
        *(("col", j) for j in np.flatnonzero(occupied.sum(axis=0) >= min_cells)),
    ]
    assert len(lines) >= 2, "expected at least two long wall lines (a corridor)"
    assert np.count_nonzero(cells == 254) > 10 * np.count_nonzero(occupied)


def _split_pgm(pgm: bytes) -> tuple[tuple[int, int], int, bytes]:
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        line_end = pgm.index(b"\n", pos)
        line = pgm[pos:line_end]
        pos = line_end + 1
        if line.startswith(b"#"):
            continue
        tokens += line.split()
    assert tokens[0] == b"P5"
    return (int(tokens[1]), int(tokens[2])), int(tokens[3]), pgm[pos:]


# ---------------------------------------------------------------------------------------------
# The demo: agent (emulated UTM-30LX on a pty + real driver) -> Zenoh -> service


@pytest.mark.timeout(120)
def test_demo_agent_path_matches_ground_truth(tmp_path: Path) -> None:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    err_path = tmp_path / "demo.log"
    with err_path.open("wb") as err:
        demo = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "service.cli",
                "demo",
                "--http-port",
                str(port),
                "--data-dir",
                str(tmp_path / "data"),
                "--world-seed",
                "1",
            ],
            stdout=subprocess.PIPE,
            stderr=err,
            cwd=REPO_ROOT,
        )
    try:
        assert demo.stdout is not None
        line = demo.stdout.readline().decode()
        m = re.search(r"Live map: (http://\S+)/\?session=(\S+)", line)
        assert m, f"no URL line: {line!r}\n{err_path.read_text()[-3000:]}"
        assert m.group(1) == url
        sid = m.group(2)
        assert httpx.get(url + "/").status_code == 200

        def covered_s() -> float:
            poses = httpx.get(f"{url}/sessions/{sid}/trajectory").json()["poses"]
            return (poses[-1]["stamp_ns"] - poses[0]["stamp_ns"]) / 1e9 if poses else 0.0

        wait_for(lambda: covered_s() >= 7.0, 90, "7 s of trajectory", period_s=0.5)
        poses = httpx.get(f"{url}/sessions/{sid}/trajectory").json()["poses"]
        pose = httpx.get(f"{url}/sessions/{sid}/pose").json()
        png = httpx.get(f"{url}/sessions/{sid}/map.png").content
        pgm = httpx.get(f"{url}/sessions/{sid}/map.pgm").content
        children = psutil.Process(demo.pid).children(recursive=True)
        assert children, "the demo runs the agent as a child process"
        demo.send_signal(signal.SIGINT)  # Ctrl-C
        assert demo.wait(timeout=30) == 0, err_path.read_text()[-3000:]
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
    assert not [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
    assert pose["sequence"] >= poses[-1]["sequence"]

    # What the agent's emulator drives (sensor_agent.scene.WorldScene(1)), vectorised.
    motion = RobotMotion(generate_building(1), 1)
    assert motion.pose_at(3.0) == WorldScene(1).pose_at(3.0)
    report = check_against_truth(poses, motion.poses_at)
    print("agent path vs ground truth:", report)
    assert_within_tolerance(report, min_distance_m=4.0, tol=AGENT_PATH)
    map_shows_corridors(png, pgm, 0.05)


# ---------------------------------------------------------------------------------------------
# One service, many robots and subscribers


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProc]:
    svc = ServiceProc(tmp_path_factory.mktemp("fleet") / "data")
    # Deep queues, so that bursts of 1,000 malformed scans are all decoded and counted by
    # reason (overflow is counted as dropped instead; test_service_ingest covers that).
    svc.start(env={"MAPPING_QUEUE_DEPTH": "1024"})
    yield svc
    assert svc.stop() == 0, svc.log_tail()


def publish_lockstep(
    svc: ServiceProc, pubs: dict[str, tuple[Any, SimRobot, str]], rounds: int, batch: int = 8
) -> None:
    """Publish `rounds` scans per robot; wait for the service to take each batch (no drops)."""
    done = 0
    while done < rounds:
        n = min(batch, rounds - done)
        for _ in range(n):
            for pub, robot, _sid in pubs.values():
                pub.put(robot.next_payload())
        done += n
        for _pub, _robot, sid in pubs.values():
            wait_for(
                lambda sid=sid, done=done: svc.json(f"/sessions/{sid}")["scans_accepted"] >= done,
                60,
                f"{done} scans in {sid}",
            )


@pytest.mark.timeout(120)
def test_three_robots_each_with_own_session_and_map(service: ServiceProc) -> None:
    robots = {rid: SimRobot(rid, seed=seed) for rid, seed in (("ra", 1), ("rb", 2), ("rc", 3))}
    sids = {rid: service.create_session(rid)["id"] for rid in robots}
    with zenoh_peer(service.zenoh_endpoint) as peer:
        pubs = {
            rid: (
                peer.declare_publisher(
                    scan_key(rid), congestion_control=zenoh.CongestionControl.BLOCK
                ),
                robot,
                sids[rid],
            )
            for rid, robot in robots.items()
        }
        publish_lockstep(service, pubs, rounds=120)
        for pub, _, _ in pubs.values():
            pub.undeclare()  # type: ignore[no-untyped-call]
    images = []
    for rid, robot in robots.items():
        session = service.json(f"/sessions/{sids[rid]}")
        assert session["robot_id"] == rid
        assert session["scans_accepted"] == session["poses"] == 120
        poses = service.json(f"/sessions/{sids[rid]}/trajectory")["poses"]
        assert {p["robot_id"] for p in poses} == {rid}
        assert {p["session_id"] for p in poses} == {sids[rid]}
        report = check_against_truth(poses, lambda t, r=robot: r.motion.poses_at(t))
        print(f"{rid} vs ground truth:", report)
        assert_within_tolerance(report, min_distance_m=2.0, tol=LOCKSTEP)
        png = service.get(f"/sessions/{sids[rid]}/map.png").content
        images.append(np.asarray(Image.open(io.BytesIO(png)).convert("L")))
    # Three different buildings: three different maps.
    assert len({img.tobytes() for img in images}) == 3
    listed = {s["robot_id"] for s in service.json("/sessions")["sessions"]}
    assert {"ra", "rb", "rc"} <= listed


@pytest.mark.timeout(120)
def test_five_zenoh_subscribers_receive_every_pose_in_order(service: ServiceProc) -> None:
    rid = "sub-bot"
    sid = service.create_session(rid)["id"]
    robot = SimRobot(rid, seed=4)
    received: list[list[Pose]] = [[] for _ in range(5)]
    lock = threading.Lock()
    sessions = [zenoh.open(_peer_config(service.zenoh_endpoint)) for _ in range(5)]
    try:
        subs = []
        for i, s in enumerate(sessions):

            def on_pose(sample: Any, i: int = i) -> None:
                pose = decode_pose(sample.payload.to_bytes())
                with lock:
                    received[i].append(pose)

            subs.append(s.declare_subscriber(pose_key(rid), on_pose))
        with zenoh_peer(service.zenoh_endpoint) as peer:
            pub = peer.declare_publisher(
                scan_key(rid), congestion_control=zenoh.CongestionControl.BLOCK
            )

            def everyone_has_one() -> bool:
                pub.put(robot.next_payload())
                with lock:
                    return all(received)

            # Declarations propagate asynchronously: warm up until all five are matched.
            wait_for(everyone_has_one, 30, "all five subscribers to be matched", period_s=0.1)
            with lock:
                start = max(r[0].seq for r in received)
            publish_lockstep(service, {rid: (pub, robot, sid)}, rounds=150)
            pub.undeclare()  # type: ignore[no-untyped-call]
        total = service.json(f"/sessions/{sid}")["poses"]
        wait_for(lambda: all(r and r[-1].seq == total - 1 for r in received), 20, "the last pose")
        for sub in subs:
            sub.undeclare()
    finally:
        for s in sessions:
            s.close()  # type: ignore[no-untyped-call]
    trajectory = service.json(f"/sessions/{sid}/trajectory")["poses"]
    expected = [p["sequence"] for p in trajectory if p["sequence"] >= start]
    assert len(expected) >= 150
    for i, got in enumerate(received):
        seqs = [p.seq for p in got if p.seq >= start]
        assert seqs == expected, f"subscriber {i} missed or reordered poses"
        last = got[-1]
        assert (last.x_m, last.y_m, last.theta_rad) == (
            trajectory[-1]["x"],
            trajectory[-1]["y"],
            trajectory[-1]["theta"],
        )


def _peer_config(endpoint: str) -> zenoh.Config:
    from clients.zenoh_config import build_zenoh_config

    return build_zenoh_config(connect=[endpoint])


@pytest.mark.timeout(120)
def test_ten_thousand_malformed_scans_leave_the_service_healthy(service: ServiceProc) -> None:
    good_sid = service.create_session("good-bot")["id"]
    bad_sid = service.create_session("bad-bot")["id"]
    before = service.metrics()
    expected: Counter[str] = Counter()
    stop = threading.Event()
    good = SimRobot("good-bot", seed=5)

    def rejected(metrics: dict[str, float], **labels: str) -> float:
        return metric_sum(metrics, "mapping_scans_rejected_total", **labels) - metric_sum(
            before, "mapping_scans_rejected_total", **labels
        )

    # Separate sessions (separate links): the flood must not starve the good robot's link
    # inside the test process itself.
    with (
        zenoh_peer(service.zenoh_endpoint) as good_peer,
        zenoh_peer(service.zenoh_endpoint) as bad_peer,
    ):
        good_pub = good_peer.declare_publisher(scan_key("good-bot"))
        bad_pub = bad_peer.declare_publisher(
            scan_key("bad-bot"), congestion_control=zenoh.CongestionControl.BLOCK
        )

        def good_robot() -> None:
            while not stop.is_set():
                good_pub.put(good.next_payload())
                stop.wait(0.05)

        feeder = threading.Thread(target=good_robot, daemon=True)
        feeder.start()
        try:
            wait_for(lambda: service.json(f"/sessions/{good_sid}")["poses"] > 0, 30, "good robot")
            poses_at_start = service.json(f"/sessions/{good_sid}")["poses"]
            payloads = malformed_payloads("bad-bot", 10_000)
            for burst in range(1, 11):  # ten back-to-back bursts of 1,000
                for payload, reason in itertools.islice(payloads, 1000):
                    bad_pub.put(payload)
                    expected[reason] += 1
                wait_for(
                    lambda n=burst * 1000: rejected(service.metrics()) >= n,
                    30,
                    f"{burst * 1000} rejections",
                    period_s=0.1,
                )
            wait_for(
                lambda: service.json(f"/sessions/{good_sid}")["poses"] > poses_at_start + 5,
                30,
                "the good robot to keep mapping",
            )
        finally:
            stop.set()
            feeder.join(5)
            good_pub.undeclare()  # type: ignore[no-untyped-call]
            bad_pub.undeclare()  # type: ignore[no-untyped-call]
    after = service.metrics()
    by_reason = {reason: rejected(after, reason=reason) for reason in expected}
    assert by_reason == expected  # every payload, counted by its reason
    assert rejected(after) == 10_000
    assert metric_sum(after, "mapping_scans_dropped_total", robot="bad-bot") == 0
    health = service.json("/health")
    assert health["status"] == "ok"
    bad = service.json(f"/sessions/{bad_sid}")
    assert (bad["scans_accepted"], bad["poses"]) == (0, 0)
    good_session = service.json(f"/sessions/{good_sid}")
    assert good_session["scans_accepted"] == good_session["poses"] > poses_at_start
