"""MCAP out and in: the export read back by mcap-ros2-support and by rosbags (every scan and
pose, bit-exact ranges), the HTTP export streamed, and files written by other writers (rosbags'
rosbag2 writer with MCAP storage, a bare .mcap) replayed through the agent and mapped."""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO_ROOT, wait_for
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from svc_testkit import (
    ServiceProc,
    SimRobot,
    client_fixture,  # noqa: F401
    feed,
    runtime_factory_fixture,  # noqa: F401
    runtime_fixture,  # noqa: F401
)

from clients.recording import read_messages
from clients.wire import Pose, Scan
from service.mcapio import stream_mcap

SCANS = 60


def _recorded(runtime, sid: str) -> tuple[list[Scan], list[Pose]]:  # type: ignore[no-untyped-def]
    messages = list(read_messages(runtime.sessions.get(sid).recording_path()))
    scans = [m for m in messages if isinstance(m, Scan)]
    poses = [m for m in messages if isinstance(m, Pose)]
    return scans, poses


def _check_mcap_ros2(path: Path, scans: list[Scan], poses: list[Pose]) -> None:
    by_topic: dict[str, list[object]] = {}
    times: dict[str, list[int]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, ros_msg in reader.iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append(ros_msg)
            times.setdefault(channel.topic, []).append(message.log_time)
    assert len(by_topic["/scan"]) == len(scans)
    assert len(by_topic["/pose"]) == len(poses) == len(by_topic["/tf"])
    assert len(by_topic["/map"]) == 1
    for msg, scan, t in zip(by_topic["/scan"], scans, times["/scan"], strict=True):
        got = np.asarray(msg.ranges, dtype=np.float32)  # type: ignore[attr-defined]
        assert got.tobytes() == scan.ranges_m.astype(np.float32).tobytes()
        stamp = msg.header.stamp  # type: ignore[attr-defined]
        assert stamp.sec * 1_000_000_000 + stamp.nanosec == scan.stamp_ns == t
    for msg, pose in zip(by_topic["/pose"], poses, strict=True):
        assert msg.pose.position.x == pose.x_m  # type: ignore[attr-defined]
        assert msg.pose.position.y == pose.y_m  # type: ignore[attr-defined]
        assert msg.header.frame_id == "map"  # type: ignore[attr-defined]
    tf = by_topic["/tf"][-1].transforms[0]  # type: ignore[attr-defined]
    assert tf.child_frame_id == f"{poses[-1].robot_id}/base_link"
    grid = by_topic["/map"][0]
    assert grid.info.width * grid.info.height == len(grid.data) > 0  # type: ignore[attr-defined]
    assert max(grid.data) > 50  # type: ignore[attr-defined]


def _check_rosbags(path: Path, scans: list[Scan], poses: list[Pose]) -> None:
    store = get_typestore(Stores.LATEST)
    with AnyReader([path], default_typestore=store) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {
            "/scan": "sensor_msgs/msg/LaserScan",
            "/pose": "geometry_msgs/msg/PoseStamped",
            "/tf": "tf2_msgs/msg/TFMessage",
            "/map": "nav_msgs/msg/OccupancyGrid",
        }
        assert counts["/scan"] == len(scans)
        assert counts["/pose"] == len(poses)
        conns = [c for c in reader.connections if c.topic == "/scan"]
        for (conn, _, raw), scan in zip(reader.messages(connections=conns), scans, strict=True):
            msg = reader.deserialize(raw, conn.msgtype)
            assert msg.ranges.tobytes() == scan.ranges_m.astype(np.float32).tobytes()


def test_http_export_reads_back_in_both_readers(runtime, client, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    sid = client.post("/sessions", json={"robot_id": "mc-1"}).json()["id"]
    feed(runtime, SimRobot("mc-1"), SCANS)
    scans, poses = _recorded(runtime, sid)
    assert len(scans) == SCANS
    assert len(poses) == SCANS
    out = tmp_path / "http.mcap"
    with client.stream("GET", f"/sessions/{sid}/recording.mcap") as r:
        assert r.status_code == 200
        assert r.headers["content-type"] == "application/x-mcap"
        pieces = list(r.iter_bytes())
    out.write_bytes(b"".join(pieces))
    _check_mcap_ros2(out, scans, poses)
    _check_rosbags(out, scans, poses)


def test_cli_export_of_a_session_and_of_a_recording(runtime, client, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    sid = client.post("/sessions", json={"robot_id": "mc-2"}).json()["id"]
    feed(runtime, SimRobot("mc-2", seed=2), SCANS)
    scans, poses = _recorded(runtime, sid)
    data_dir = runtime.settings.storage.data_dir
    for source, out in (
        (sid, tmp_path / "session.mcap"),
        (str(runtime.sessions.get(sid).recording_path()), tmp_path / "recording.mcap"),
    ):
        result = subprocess.run(
            [sys.executable, "-m", "service.cli", "export", source, "--mcap", str(out),
             "--data-dir", str(data_dir)],
            capture_output=True, text=True, cwd=REPO_ROOT, timeout=60, check=False,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        assert f"{SCANS} scans, {SCANS} poses, 1 map" in result.stdout
        _check_mcap_ros2(out, scans, poses)
        _check_rosbags(out, scans, poses)
        assert not out.with_name(out.name + ".partial").exists()


def test_cli_export_refuses_an_unwritable_output_first(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "export", "s-nosuch", "--mcap",
         str(tmp_path / "missing" / "x.mcap"), "--data-dir", str(tmp_path)],
        capture_output=True, text=True, cwd=REPO_ROOT, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 1
    assert "no such directory" in result.stderr


def _peak_bytes(count: int) -> int:
    base = SimRobot("mem", seed=3).next_scan()
    pose = Pose("s", "mem", 0, base.stamp_ns, 0.0, 0.0, 0.0, 1.0)
    rng = np.random.default_rng(0)

    def messages():  # type: ignore[no-untyped-def]
        for _ in range(count):  # made one at a time: the input holds one scan at once
            noise = rng.uniform(0.0, 0.01, base.beam_count)
            yield dataclasses.replace(base, ranges_m=base.ranges_m + noise)
            yield pose

    tracemalloc.start()
    try:
        total = sum(len(piece) for piece in stream_mcap(messages(), lambda: None))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert total > count * 2000  # the file really grew with the input
    return peak


def test_export_memory_does_not_grow_with_length() -> None:
    short, long = _peak_bytes(300), _peak_bytes(3000)
    # Chunks are 1 MiB: the peak is a chunk or two whatever the length, not the file.
    assert long < short * 1.5 + (1 << 20), (short, long)


def _write_rosbag2_mcap(folder: Path, scans: list[Scan]) -> None:
    """A bag written by another tool: rosbags' rosbag2 writer, MCAP storage."""
    store = get_typestore(Stores.LATEST)
    t = store.types
    laser = t["sensor_msgs/msg/LaserScan"]
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/scan", laser.__msgtype__, typestore=store)
        for scan in scans:
            n = scan.beam_count
            msg = laser(
                header=t["std_msgs/msg/Header"](
                    stamp=t["builtin_interfaces/msg/Time"](
                        sec=scan.stamp_ns // 10**9, nanosec=scan.stamp_ns % 10**9
                    ),
                    frame_id="laser",
                ),
                angle_min=scan.angle_min_rad,
                angle_max=scan.angle_min_rad + scan.angle_increment_rad * (n - 1),
                angle_increment=scan.angle_increment_rad,
                time_increment=0.0,
                scan_time=0.025,
                range_min=scan.range_min_m,
                range_max=scan.range_max_m,
                ranges=scan.ranges_m.astype(np.float32),
                intensities=np.empty(0, dtype=np.float32),
            )
            writer.write(conn, scan.stamp_ns, store.serialize_cdr(msg, laser.__msgtype__))


@pytest.mark.slow
def test_a_foreign_rosbag2_mcap_replays_through_the_agent_and_maps(tmp_path: Path) -> None:
    robot = SimRobot("rb-1", seed=1)
    scans = [robot.next_scan() for _ in range(40)]
    bag = tmp_path / "bag"
    _write_rosbag2_mcap(bag, scans)
    bare = tmp_path / "alone.mcap"  # the bag's file without its metadata.yaml beside it
    shutil.copyfile(next(bag.glob("*.mcap")), bare)

    svc = ServiceProc(tmp_path / "data")
    svc.start()
    try:
        sid = svc.create_session("rb-1", use_odometry=False)["id"]
        agent = subprocess.run(
            [sys.executable, "-m", "sensor_agent.cli", "--robot-id", "rb-1", "--replay",
             str(bag), "--rate", "4", "--zenoh-connect", svc.zenoh_endpoint],
            capture_output=True, text=True, cwd=REPO_ROOT, timeout=90, check=False,
        )  # fmt: skip
        assert agent.returncode == 0, agent.stderr[-2000:]
        assert f"replay finished: {len(scans)} scans" in agent.stderr

        def last_stamp_ns() -> int:
            pose = svc.json(f"/sessions/{sid}")["last_pose"]
            return int(pose["stamp_ns"]) if isinstance(pose, dict) else 0

        # The first puts may precede the route to the service; the rest all arrive.
        wait_for(lambda: last_stamp_ns() == scans[-1].stamp_ns, 30, "the last scan's pose")
        assert int(svc.json(f"/sessions/{sid}")["scans_accepted"]) >= len(scans) // 2
    finally:
        assert svc.stop() == 0, svc.log_tail()

    for source in (bag, bare):  # the folder and the bare .mcap inside it
        out = tmp_path / f"out-{source.name}"
        result = subprocess.run(
            [sys.executable, "-m", "service.cli", "map", str(source), "--out", str(out),
             "--no-progress"],
            capture_output=True, text=True, cwd=REPO_ROOT, timeout=90, check=False,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr[-2000:]
        assert len((out / "trajectory.tum").read_text().splitlines()) == len(scans)
