"""Issue 40, ingest and time: junk on made-up robot keys exhausts nothing, a created session is
always served, silent robots are forgotten, stamps are a contract (out of ROS time, backwards,
duplicates refused and counted; gaps counted), and every session exports as MCAP. Real service
processes, real Zenoh sessions on loopback."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import zenoh
from conftest import REPO_ROOT, wait_for
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from svc_testkit import ServiceProc, SimRobot, metric_sum, zenoh_peer

from clients.keyexpr import scan_key
from clients.recording import RecordingWriter
from clients.wire import Pose, Scan, encode_pose, encode_scan

BLOCK = zenoh.CongestionControl.BLOCK


@contextmanager
def scan_publisher(peer: zenoh.Session, robot_id: str) -> Iterator[zenoh.Publisher]:
    pub = peer.declare_publisher(scan_key(robot_id), congestion_control=BLOCK)
    try:
        wait_for(lambda: pub.matching_status.matching, 30, "the service's scan subscriber")
        yield pub
    finally:
        pub.undeclare()  # type: ignore[no-untyped-call]


def accepted(svc: ServiceProc, sid: str) -> int:
    return int(svc.json(f"/sessions/{sid}")["scans_accepted"])  # type: ignore[call-overload]


def send_all(svc: ServiceProc, pub: zenoh.Publisher, sid: str, scans: list[Scan]) -> None:
    """Every scan, paced so that the robot's queue (32) never drops one."""
    base = accepted(svc, sid)
    for i, scan in enumerate(scans):
        wait_for(lambda i=i: i - (accepted(svc, sid) - base) < 16, 30, "room in the queue")  # type: ignore[misc]
        pub.put(encode_scan(scan))


def read_mcap(path: Path) -> dict[str, list[int]]:
    """Log times per topic, decoded by mcap-ros2-support (every message) and by rosbags."""
    times: dict[str, list[int]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, ros_msg in reader.iter_decoded_messages():
            assert ros_msg is not None
            times.setdefault(channel.topic, []).append(message.log_time)
    with AnyReader([path], default_typestore=get_typestore(Stores.LATEST)) as bag:
        counts = {c.topic: c.msgcount for c in bag.connections}
        for conn, _, raw in bag.messages():
            bag.deserialize(raw, conn.msgtype)
    assert counts == {topic: len(t) for topic, t in times.items()}
    return times


@pytest.mark.timeout(240)
def test_junk_on_made_up_keys_locks_nobody_out(tmp_path: Path) -> None:
    """2,000 one-byte payloads on 2,000 made-up robot keys, then a new robot: its session maps
    every scan; nothing is kept per made-up id (queues, /metrics, /health); /health stays small
    and says what happened, by reason."""
    junk = 2000
    svc = ServiceProc(tmp_path / "data")
    svc.start()
    try:
        with zenoh_peer(svc.zenoh_endpoint) as peer, scan_publisher(peer, "probe"):
            for i in range(junk):
                peer.put(scan_key(f"junk-{i}"), b"\x00", congestion_control=BLOCK)

            def refused() -> float:
                m = svc.metrics()
                return metric_sum(m, "mapping_scans_rejected_total") + metric_sum(
                    m, "mapping_scans_dropped_total"
                )

            wait_for(lambda: refused() >= junk, 60, f"{junk} junk payloads refused or dropped")
            sid = svc.create_session("late-2")["id"]
            assert isinstance(sid, str)
            robot = SimRobot("late-2")
            scans = [robot.next_scan() for _ in range(40)]
            with scan_publisher(peer, "late-2") as pub:
                send_all(svc, pub, sid, scans)
                wait_for(lambda: accepted(svc, sid) >= 40, 30, "all 40 scans of late-2 mapped")
        assert accepted(svc, sid) == 40
        health = svc.get("/health")
        assert len(health.content) < 16 * 1024, len(health.content)
        body = health.json()
        assert [r["robot_id"] for r in body["robots"]] == ["late-2"]
        ingest = body["ingest"]
        assert ingest["robots_tracked"] == 1
        assert ingest["scans_accepted"] == 40
        assert (
            sum(ingest["scans_rejected"].values()) + sum(ingest["scans_dropped"].values()) == junk
        )
        assert ingest["scans_rejected"]["not_a_map"] > 0  # b"\x00" is msgpack's 0
        assert "junk-" not in svc.get("/metrics").text
        log = svc.log_path.read_text(errors="replace")
        assert log.count("[not_a_map;") == 1  # logged once, not once per made-up id
    finally:
        assert svc.stop() == 0, svc.log_tail()


@pytest.mark.timeout(180)
def test_a_created_session_is_served_when_robots_without_one_fill_the_limit(
    tmp_path: Path,
) -> None:
    """MAPPING_MAX_ROBOTS=4 robots without a session are tracked; a 5th without one is dropped
    (counted); a session created now is served in full (never a 201, then silent drops); once
    silent for MAPPING_ROBOT_IDLE_S, robots without a session are forgotten and newcomers fit."""
    svc = ServiceProc(tmp_path / "data")
    svc.start(env={"MAPPING_MAX_ROBOTS": "4", "MAPPING_ROBOT_IDLE_S": "3"})
    try:
        with zenoh_peer(svc.zenoh_endpoint) as peer:
            for i in range(5):
                with scan_publisher(peer, f"idle-{i}") as pub:
                    pub.put(SimRobot(f"idle-{i}").next_payload())
            wait_for(
                lambda: metric_sum(svc.metrics(), "mapping_scans_dropped_total") >= 1,
                30,
                "the 5th robot without a session dropped",
            )
            m = svc.metrics()
            assert metric_sum(m, "mapping_scans_unmapped_total") == 4
            assert metric_sum(m, "mapping_scans_dropped_total", reason="too_many_robots") == 1
            sid = svc.create_session("late-2")["id"]
            assert isinstance(sid, str)
            robot = SimRobot("late-2")
            with scan_publisher(peer, "late-2") as pub:
                send_all(svc, pub, sid, [robot.next_scan() for _ in range(40)])
                wait_for(lambda: accepted(svc, sid) >= 40, 30, "all 40 scans of late-2 mapped")

            def forgotten() -> float:
                return metric_sum(svc.metrics(), "mapping_ingest_robots_forgotten_total")

            wait_for(lambda: forgotten() >= 4, 30, "the silent robots without a session forgotten")
            health = svc.json("/health")
            assert [r["robot_id"] for r in health["robots"]] == ["late-2"]  # type: ignore[index]
            assert 'robot="idle-0"' not in svc.get("/metrics").text
            with scan_publisher(peer, "new-1") as pub:
                pub.put(SimRobot("new-1").next_payload())
                wait_for(
                    lambda: (
                        metric_sum(svc.metrics(), "mapping_scans_unmapped_total", robot="new-1")
                        == 1
                    ),
                    30,
                    "a newcomer tracked again",
                )
        assert accepted(svc, sid) == 40
    finally:
        assert svc.stop() == 0, svc.log_tail()


@pytest.mark.timeout(240)
def test_stamps_are_a_contract_and_the_session_still_exports(tmp_path: Path) -> None:
    """After a live stream: stamps out of ROS time (-2^63, 2^63-1, 2039), backwards (-1 s,
    -1000 s, 0) and a duplicate are refused, counted by reason, logged once each; a forward
    jump of 60 s is mapped and counted as a gap. The trajectory never goes backwards, and the
    session exports (HTTP and CLI) as MCAP that mcap and rosbags read back."""
    svc = ServiceProc(tmp_path / "data")
    svc.start()
    try:
        sid = svc.create_session("clock-1")["id"]
        assert isinstance(sid, str)
        robot = SimRobot("clock-1")
        live = [robot.next_scan() for _ in range(20)]
        last = live[-1].host_stamp_ns
        bad = [
            (-(2**63), "stamp_out_of_range"),
            (2**63 - 1, "stamp_out_of_range"),
            (2_200_000_000 * 10**9, "stamp_out_of_range"),  # 2039: past ROS time's int32
            (last - 10**9, "stamp_backwards"),
            (last - 1000 * 10**9, "stamp_backwards"),
            (0, "stamp_backwards"),
            (last, "stamp_duplicate"),
        ]
        wrong = [dataclasses.replace(robot.next_scan(), host_stamp_ns=s) for s, _ in bad]
        gap = robot.next_scan()
        gap = dataclasses.replace(gap, host_stamp_ns=last + 60 * 10**9)
        after = [
            dataclasses.replace(s, host_stamp_ns=s.host_stamp_ns + 60 * 10**9)
            for s in (robot.next_scan() for _ in range(10))
        ]
        with zenoh_peer(svc.zenoh_endpoint) as peer, scan_publisher(peer, "clock-1") as pub:
            send_all(svc, pub, sid, live)
            for scan in wrong:
                pub.put(encode_scan(scan))
            send_all(svc, pub, sid, [gap, *after])
            wait_for(lambda: accepted(svc, sid) >= 31, 30, "the 31 good scans mapped")

            def rejected(reason: str) -> float:
                return metric_sum(svc.metrics(), "mapping_scans_rejected_total", reason=reason)

            wait_for(lambda: rejected("stamp_duplicate") == 1, 30, "the duplicate refused")
        assert accepted(svc, sid) == 31
        m = svc.metrics()
        for reason in ("stamp_out_of_range", "stamp_backwards", "stamp_duplicate"):
            expected = sum(1 for _, r in bad if r == reason)
            assert rejected(reason) == expected, reason
            series = "mapping_scan_stamp_anomalies_total"
            assert metric_sum(m, series, robot="clock-1", reason=reason) == expected, reason
        assert metric_sum(m, "mapping_scan_stamp_anomalies_total", reason="stamp_gap") == 1
        robots = svc.json("/health")["robots"]
        assert isinstance(robots, list)
        assert robots[0]["stamps_refused"] == len(bad)
        assert robots[0]["stamp_gaps"] == 1
        log = svc.log_path.read_text(errors="replace")
        for reason in ("stamp_out_of_range", "stamp_backwards", "stamp_duplicate", "stamp_gap"):
            assert log.count(f"[{reason};") == 1, reason

        tum = svc.get(f"/sessions/{sid}/trajectory?format=tum&limit=10000").text.splitlines()
        stamps = [float(line.split()[0]) for line in tum if line and not line.startswith("#")]
        assert len(stamps) == 31
        assert stamps == sorted(stamps)
        assert len(set(stamps)) == len(stamps)
        assert 1.6e9 < stamps[0] < stamps[-1] < 2**31

        out = tmp_path / "http.mcap"
        with httpx.stream("GET", f"{svc.url}/sessions/{sid}/recording.mcap", timeout=30) as r:
            assert r.status_code == 200
            out.write_bytes(b"".join(r.iter_bytes()))
        times = read_mcap(out)
        assert len(times["/scan"]) == len(times["/pose"]) == 31
        assert times["/scan"] == sorted(times["/scan"])
    finally:
        assert svc.stop() == 0, svc.log_tail()
    cli_out = tmp_path / "cli.mcap"
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "export", sid, "--mcap", str(cli_out),
         "--data-dir", str(svc.data_dir)],
        capture_output=True, text=True, cwd=REPO_ROOT, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "31 scans, 31 poses, 1 map" in result.stdout
    assert len(read_mcap(cli_out)["/scan"]) == 31


def _recording_with_extreme_stamps(path: Path) -> int:
    """A recording as an older service wrote it: good scans and poses, then a scan and its
    pose stamped -2^63, 2^63-1 and in 2039. Returns the number of good scans."""
    robot = SimRobot("old-1")
    writer = RecordingWriter(path)
    good = 30
    for i in range(good + 3):
        scan = robot.next_scan()
        if i >= good:
            stamp = (-(2**63), 2**63 - 1, 2_200_000_000 * 10**9)[i - good]
            scan = dataclasses.replace(scan, host_stamp_ns=stamp)
        writer.append(encode_scan(scan))
        writer.append(
            encode_pose(Pose("s-old", "old-1", i, scan.stamp_ns, 0.05 * i, 0.0, 0.0, 1.0))
        )
    writer.close()
    return good


@pytest.mark.timeout(120)
def test_cli_export_of_a_recording_with_extreme_stamps_leaves_them_out(tmp_path: Path) -> None:
    recording = tmp_path / "old.mrec"
    good = _recording_with_extreme_stamps(recording)
    out = tmp_path / "old.mcap"
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "export", str(recording), "--mcap", str(out),
         "--data-dir", str(tmp_path)],
        capture_output=True, text=True, cwd=REPO_ROOT, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert f"{good} scans, {good} poses, 1 map" in result.stdout
    assert "6 left out (stamps outside ROS time)" in result.stdout
    times = read_mcap(out)
    assert len(times["/scan"]) == len(times["/pose"]) == good


@pytest.mark.timeout(120)
def test_an_export_that_fails_after_the_headers_is_an_error_not_a_short_file(
    tmp_path: Path,
) -> None:
    """The recording becomes unreadable (its magic overwritten) after the session mapped: the
    HTTP export has sent its 200 before it reads; the client must see a broken transfer."""
    svc = ServiceProc(tmp_path / "data")
    svc.start()
    try:
        sid = svc.create_session("broken-1")["id"]
        assert isinstance(sid, str)
        robot = SimRobot("broken-1")
        with zenoh_peer(svc.zenoh_endpoint) as peer, scan_publisher(peer, "broken-1") as pub:
            send_all(svc, pub, sid, [robot.next_scan() for _ in range(10)])
            wait_for(lambda: accepted(svc, sid) >= 10, 30, "10 scans mapped")
        segments = sorted((svc.data_dir / "sessions" / sid).glob("epoch-*.mrec"))
        assert segments
        with segments[0].open("r+b") as f:
            f.write(b"NOTMREC\n")
        with httpx.stream("GET", f"{svc.url}/sessions/{sid}/recording.mcap", timeout=30) as r:
            assert r.status_code == 200
            with pytest.raises(httpx.RemoteProtocolError):  # not a short file read as complete
                r.read()
    finally:
        svc.stop()
