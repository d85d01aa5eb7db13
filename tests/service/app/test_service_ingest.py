"""Ingest and fan-out in process: validation, counting, queues, Zenoh path, slow subscribers."""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

import pytest
from svc_testkit import (  # noqa: F401  # *_fixture: pytest fixtures used by name
    RuntimeFactory,
    SimRobot,
    malformed_payloads,
    runtime_factory_fixture,
    runtime_fixture,
    wait_for,
)

from clients.keyexpr import pose_wildcard, scan_key
from clients.wire import Pose, decode_pose, encode_scan
from service.app.fanout import PoseFanout, PoseStream
from service.app.mapper import Engine, local_mapper_factory
from service.app.metrics import Metrics
from service.app.runtime import MappingRuntime
from service.core.slam import make_frontend
from service.core.types import LaserScan, PoseEstimate


def drain(runtime: MappingRuntime) -> None:
    wait_for(lambda: runtime.ingest.pending() == 0, 60, "the ingest queues to drain")


def test_malformed_scans_counted_by_reason_and_logged_once(
    runtime_factory: RuntimeFactory, caplog: pytest.LogCaptureFixture
) -> None:
    runtime = runtime_factory(queue_depth=256)  # all 120 queued at once: none dropped
    runtime.sessions.create("bad-robot", 0.05, True)
    expected: Counter[str] = Counter()
    with caplog.at_level(logging.WARNING, logger="service.app.ingest"):
        for payload, reason in malformed_payloads("bad-robot", 120):
            runtime.ingest.submit(scan_key("bad-robot"), payload)
            expected[reason] += 1
        drain(runtime)
    m = runtime.metrics
    for reason, count in expected.items():
        assert m.value("mapping_scans_rejected_total", reason=reason) == count, reason
    assert m.total("mapping_scans_accepted_total") == 0
    assert m.total("mapping_scans_dropped_total") == 0
    logged = [r for r in caplog.records if "bad-robot" in r.getMessage()]
    assert len(logged) == len(expected)  # once per (reason, robot), not per message
    assert runtime.sessions.active_for("bad-robot") is not None
    assert runtime.sessions.list()[0].info().scans_accepted == 0


def test_unsafe_keys_and_sample_kinds(runtime: MappingRuntime) -> None:
    runtime.ingest.submit("robots/a/b/scan", b"x")
    runtime.ingest.submit("elsewhere/a/scan", b"x")
    runtime.ingest.submit("robots/-dash/scan", b"x")
    assert runtime.metrics.value("mapping_scans_rejected_total", reason="bad_key") == 3

    @dataclass
    class Payload:
        data: bytes

        def __len__(self) -> int:
            return len(self.data)

        def to_bytes(self) -> bytes:
            return self.data

    @dataclass
    class Sample:
        key_expr: str
        payload: Payload
        kind: Any

    import zenoh

    big = Sample("robots/r1/scan", Payload(b"x" * (2 << 20)), zenoh.SampleKind.PUT)
    runtime.ingest.on_sample(big)
    assert runtime.metrics.value("mapping_scans_rejected_total", reason="too_large") == 1
    runtime.ingest.on_sample(Sample("robots/r1/scan", Payload(b""), zenoh.SampleKind.DELETE))
    runtime.ingest.on_sample(object())  # never raises out of the callback
    drain(runtime)
    assert runtime.metrics.total("mapping_scans_rejected_total") == 4


class BlockingEstimator:
    """The real estimator behind a gate, to hold a worker busy."""

    def __init__(self, gate: threading.Event, entered: threading.Event) -> None:
        self._inner = make_frontend(use_odometry=True)
        self._gate = gate
        self._entered = entered

    def process(self, scan: LaserScan) -> PoseEstimate:
        self._entered.set()
        self._gate.wait(30)
        return self._inner.process(scan)

    def reset(self) -> None:
        self._inner.reset()


def test_full_queue_drops_oldest_and_never_blocks_the_callback(
    runtime_factory: RuntimeFactory,
) -> None:
    gate, entered = threading.Event(), threading.Event()
    depth = 8
    runtime = runtime_factory(queue_depth=depth)
    # Swap in a gated estimator for this robot's session.
    runtime.sessions._make_mapper = local_mapper_factory(
        Engine(make_estimator=lambda _: BlockingEstimator(gate, entered))
    )
    session = runtime.sessions.create("slow", 0.05, True)
    robot = SimRobot("slow")
    payloads = [robot.next_payload() for _ in range(41)]
    runtime.ingest.submit(scan_key("slow"), payloads[0])
    assert entered.wait(10), "the worker should be inside the estimator"
    for payload in payloads[1:]:  # the worker is stuck: these only queue up (or drop)
        runtime.ingest.submit(scan_key("slow"), payload)
    assert runtime.ingest.robots()[0].queue_depth == depth
    dropped = runtime.metrics.value(
        "mapping_scans_dropped_total", robot="slow", reason="queue_full"
    )
    assert dropped == 40 - depth
    gate.set()
    drain(runtime)
    info = session.info()
    assert info.scans_accepted == 1 + depth
    # The survivors are the newest scans (drop oldest), in order.
    stamps = [p.stamp_ns for p in session.trajectory()]
    robot_stamps = [1_700_000_000_000_000_000 + s * 25_000_000 for s in range(41)]
    assert stamps == [robot_stamps[0], *robot_stamps[41 - depth :]]


class RecordingEstimator:
    """The real estimator, noting which robot each scan belonged to; the first waits for a gate."""

    def __init__(self, robot_id: str, order: list[str], gate: threading.Event) -> None:
        self._inner = make_frontend(use_odometry=True)
        self._robot_id = robot_id
        self._order = order
        self._gate = gate

    def process(self, scan: LaserScan) -> PoseEstimate:
        self._order.append(self._robot_id)
        self._gate.wait(30)
        return self._inner.process(scan)

    def reset(self) -> None:
        self._inner.reset()


def test_one_worker_serves_robots_round_robin_each_in_order(
    runtime_factory: RuntimeFactory,
) -> None:
    runtime = runtime_factory(queue_depth=64, workers=1)
    # A robot is tracked (has its own queue) once a valid scan of it arrived; before that its
    # scans wait among the newcomers. One scan each, before the sessions: unmapped.
    for r in ("ra", "rb", "rc"):
        runtime.ingest.submit(scan_key(r), SimRobot(r).next_payload())
    drain(runtime)
    assert [s.robot_id for s in runtime.ingest.robots()] == ["ra", "rb", "rc"]
    order: list[str] = []
    gate = threading.Event()
    ids = iter(["ra", "rb", "rc"])
    runtime.sessions._make_mapper = local_mapper_factory(
        Engine(make_estimator=lambda _: RecordingEstimator(next(ids), order, gate))
    )
    sessions = {r: runtime.sessions.create(r, 0.05, True) for r in ("ra", "rb", "rc")}
    robots = {r: SimRobot(r) for r in sessions}
    payloads = {r: [robot.next_payload() for _ in range(10)] for r, robot in robots.items()}
    # ra's whole burst arrives first, while the worker is held inside ra's first scan.
    for r in ("ra", "rb", "rc"):
        for payload in payloads[r]:
            runtime.ingest.submit(scan_key(r), payload)
        if r == "ra":
            wait_for(lambda: order == ["ra"], 10, "the worker to start on ra's first scan")
    gate.set()
    drain(runtime)
    # One scan per turn, the robot just served goes to the back of the line.
    assert order == ["ra"] + ["rb", "rc", "ra"] * 9 + ["rb", "rc"]
    for r, session in sessions.items():
        poses = session.trajectory()
        assert [p.seq for p in poses] == list(range(10)), r
        assert [p.stamp_ns for p in poses] == sorted(p.stamp_ns for p in poses), r


def test_a_second_worker_serves_other_robots_while_one_is_busy(
    runtime_factory: RuntimeFactory,
) -> None:
    gate, entered = threading.Event(), threading.Event()
    runtime = runtime_factory(queue_depth=32, workers=2)
    runtime.sessions._make_mapper = local_mapper_factory(
        Engine(make_estimator=lambda _: BlockingEstimator(gate, entered))
    )
    slow = runtime.sessions.create("slow", 0.05, True)
    runtime.sessions._make_mapper = local_mapper_factory(Engine())
    fast = runtime.sessions.create("fast", 0.05, True)
    runtime.ingest.submit(scan_key("slow"), SimRobot("slow").next_payload())
    assert entered.wait(10), "one worker should be inside the gated estimator"
    robot = SimRobot("fast")
    for _ in range(5):
        runtime.ingest.submit(scan_key("fast"), robot.next_payload())
    wait_for(lambda: fast.info().scans_accepted == 5, 60, "the other worker to map 'fast'")
    gate.set()
    drain(runtime)
    assert slow.info().scans_accepted == 1


def test_robot_limit(runtime_factory: RuntimeFactory) -> None:
    runtime = runtime_factory(max_robots=2)
    for rid in ("r1", "r2", "r3", "r4"):
        runtime.ingest.submit(scan_key(rid), SimRobot(rid).next_payload())
    drain(runtime)
    assert [r.robot_id for r in runtime.ingest.robots()] == ["r1", "r2"]
    assert (
        runtime.metrics.value("mapping_scans_dropped_total", robot="", reason="too_many_robots")
        == 2
    )
    assert runtime.metrics.value("mapping_scans_unmapped_total", robot="r1") == 1


def test_zenoh_path_in_process_and_pose_publication(runtime: MappingRuntime) -> None:
    """Scans put on the (isolated) Zenoh session reach the wildcard subscriber; poses go out."""
    assert runtime.zenoh is not None
    received: list[Pose] = []
    lock = threading.Lock()

    def on_pose(sample: Any) -> None:
        with lock:
            received.append(decode_pose(sample.payload.to_bytes()))

    sub = runtime.zenoh.declare_subscriber(pose_wildcard(), on_pose)
    try:
        session = runtime.sessions.create("zr", 0.05, True)
        robot = SimRobot("zr")
        for _ in range(20):
            runtime.zenoh.put(scan_key("zr"), encode_scan(robot.next_scan()))
        wait_for(lambda: session.info().poses == 20, 60, "20 poses")
        wait_for(lambda: len(received) == 20, 10, "20 published poses")
    finally:
        sub.undeclare()  # type: ignore[no-untyped-call]
    assert [p.seq for p in received] == list(range(20))
    assert received == session.trajectory()
    assert runtime.metrics.total("mapping_poses_published_total") == 20


def test_slow_stream_subscriber_loses_oldest_and_never_delays_others() -> None:
    metrics = Metrics()
    fanout = PoseFanout("robots", metrics, stream_queue_depth=5, stream_min_interval_s=0.0)
    total = 200
    encoded: list[int] = []

    def pose(seq: int) -> Pose:
        return Pose("s-1", "r1", seq, seq, 0.0, 0.0, 0.0, 1.0)

    def encode(p: Pose) -> bytes:
        encoded.append(p.seq)
        return f"{p.seq}\n".encode()

    def seqs(chunk: bytes) -> list[int]:
        return [int(x) for x in chunk.decode().split()]

    async def scenario() -> tuple[list[int], list[int], int]:
        fanout.bind_loop(asyncio.get_running_loop(), encode)
        fast = fanout.open_stream("s-1")
        slow = fanout.open_stream("s-1")  # never read until the end
        other = fanout.open_stream("s-2")
        done = threading.Event()
        acks = threading.Semaphore(0)

        def worker() -> None:  # publishes from a foreign thread, like an ingest worker
            for seq in range(total):
                fanout.publish(pose(seq))
                # Paced by the fast reader only: the slow one never holds anything up.
                assert acks.acquire(timeout=10)
            done.set()

        threading.Thread(target=worker).start()
        got_fast: list[int] = []
        while len(got_fast) < total:
            chunk = await asyncio.wait_for(fast.next_chunk(), 10)
            assert chunk is not None
            for seq in seqs(chunk):
                got_fast.append(seq)
                acks.release()
        await asyncio.to_thread(done.wait, 10)
        fanout.end_streams()
        got_slow: list[int] = []
        while (chunk := await slow.next_chunk()) is not None:
            got_slow.extend(seqs(chunk))
        assert done.is_set()
        assert await other.next_chunk() is None  # nothing for another session
        for stream in (fast, slow, other):
            fanout.close_stream(stream)
        return got_fast, got_slow, slow.dropped

    got_fast, got_slow, slow_dropped = asyncio.run(scenario())
    assert got_fast == list(range(total))
    assert got_slow == sorted(got_slow)
    assert got_slow[-1] == total - 1  # the newest survive
    assert slow_dropped == total - len(got_slow)
    assert metrics.total("mapping_pose_stream_dropped_total") == slow_dropped
    assert encoded == list(range(total))  # once per pose, not once per stream


def test_stream_fanout_work_per_pose_does_not_grow_with_the_streams(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """200 streams of one session: each pose is encoded once and appended once to the
    session's shared frame log (not once per stream), and every stream gets every pose."""
    from service.app.fanout import FrameLog

    appends: list[int] = []
    real_append = FrameLog.append

    def counting(self: FrameLog, key: tuple[int, int], frame: bytes) -> None:
        appends.append(key[0])
        real_append(self, key, frame)

    monkeypatch.setattr(FrameLog, "append", counting)
    fanout = PoseFanout("robots", Metrics(), stream_queue_depth=64, stream_min_interval_s=0.0)
    poses = 30

    async def scenario() -> list[list[int]]:
        fanout.bind_loop(asyncio.get_running_loop(), lambda p: f"{p.seq}\n".encode())
        streams = [fanout.open_stream("s-1") for _ in range(200)]
        for seq in range(poses):
            fanout.publish(Pose("s-1", "r1", seq, seq, 0.0, 0.0, 0.0, 1.0))
        got: list[list[int]] = []
        for stream in streams:
            seqs: list[int] = []
            while len(seqs) < poses:
                chunk = await asyncio.wait_for(stream.next_chunk(), 10)
                assert chunk is not None
                seqs.extend(int(x) for x in chunk.decode().split())
            got.append(seqs)
            fanout.close_stream(stream)
        return got

    got = asyncio.run(scenario())
    assert all(seqs == list(range(poses)) for seqs in got)
    assert appends == list(range(poses))


def test_stream_writes_stay_within_the_write_budget() -> None:
    """With more streams than the budget allows at the configured interval, each stream
    writes less often: all of them together stay within `max_writes_per_s`, and every stream
    still gets every pose (batched into fewer writes)."""
    fanout = PoseFanout(
        "robots",
        Metrics(),
        stream_queue_depth=512,
        stream_min_interval_s=0.01,
        max_writes_per_s=200.0,
    )
    streams_count, poses = 20, 200
    writes = 0

    async def reader(stream: PoseStream) -> list[int]:
        nonlocal writes
        seqs: list[int] = []
        while len(seqs) < poses:
            chunk = await asyncio.wait_for(stream.next_chunk(), 10)
            assert chunk is not None
            writes += 1
            seqs.extend(int(x) for x in chunk.decode().split())
        return seqs

    async def scenario() -> tuple[list[list[int]], float]:
        fanout.bind_loop(asyncio.get_running_loop(), lambda p: f"{p.seq}\n".encode())
        streams = [fanout.open_stream("s-1") for _ in range(streams_count)]
        assert fanout.interval_s() == pytest.approx(streams_count / 200)  # not 0.01 s
        tasks = [asyncio.create_task(reader(s)) for s in streams]
        t0 = time.monotonic()
        for seq in range(poses):  # 200 poses over ~1 s
            fanout.publish(Pose("s-1", "r1", seq, seq, 0.0, 0.0, 0.0, 1.0))
            await asyncio.sleep(0.005)
        got = await asyncio.gather(*tasks)
        elapsed = time.monotonic() - t0
        for stream in streams:
            fanout.close_stream(stream)
        return got, elapsed

    got, elapsed = asyncio.run(scenario())
    assert all(seqs == list(range(poses)) for seqs in got)
    # At most one write per stream per 0.1 s (the last poses' write may come one tick late);
    # without the budget each would write every 0.01 s: ~2,000 writes.
    assert writes <= 200 * elapsed * 1.2 + streams_count


def test_recording_failure_is_counted_and_the_worker_survives(
    runtime: MappingRuntime, monkeypatch: pytest.MonkeyPatch
) -> None:
    session = runtime.sessions.create("disk", 0.05, True)
    robot = SimRobot("disk")

    def full_disk(payload: bytes) -> None:
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(session._store, "append", full_disk)
        runtime.ingest.submit(scan_key("disk"), robot.next_payload())
        drain(runtime)
    assert session.info().scans_accepted == 0  # not recorded, so not accepted
    assert runtime.metrics.value("mapping_scans_dropped_total", robot="disk", reason="store_error")
    assert runtime.ingest.store_errors == 1
    runtime.ingest.submit(scan_key("disk"), robot.next_payload())  # the disk is back
    drain(runtime)
    assert session.info().scans_accepted == 1
