"""PoseSubscriber: both forms, robot filtering, malformed payloads, restarts, clean exit."""

from __future__ import annotations

import logging
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from conftest import free_port, wait_for
from svc_testkit import ScanFeeder, ServiceProc

from clients import MappingClient, MappingError, Pose, PoseFlag, PoseSubscriber
from clients.http import Session
from clients.keyexpr import pose_key
from clients.subscriber import SubscriberClosedError
from clients.wire import encode_pose
from clients.zenoh_config import build_zenoh_config


def make_pose(robot_id: str, seq: int) -> Pose:
    return Pose(
        session_id="s1",
        robot_id=robot_id,
        seq=seq,
        stamp_ns=1_700_000_000_000_000_000 + seq,
        x_m=0.1 * seq,
        y_m=-0.2,
        theta_rad=0.3,
        quality=0.9,
        flags=PoseFlag.AMBIGUOUS_Y,
    )


class FakeService:
    """A Zenoh session standing in for the service: listens, publishes poses, can restart."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session: zenoh.Session | None = None

    def start(self) -> None:
        self.session = zenoh.open(build_zenoh_config(listen=[self.endpoint]))

    def stop(self) -> None:
        if self.session is not None:
            self.session.close()  # type: ignore[no-untyped-call]
            self.session = None

    def put(self, key: str, payload: bytes) -> None:
        assert self.session is not None
        self.session.put(key, payload)


@pytest.fixture
def fake() -> Iterator[FakeService]:
    service = FakeService()
    service.start()
    yield service
    service.stop()


def publish_until(fake: FakeService, robot_id: str, got: threading.Event | None = None) -> None:
    """Zenoh connects asynchronously: publish until something arrives (no fixed sleeps)."""
    seq = 0

    def attempt() -> bool:
        nonlocal seq
        fake.put(pose_key(robot_id), encode_pose(make_pose(robot_id, seq)))
        seq += 1
        return got is None or got.is_set()

    wait_for(attempt, 15, f"a pose of {robot_id} to arrive", period_s=0.1)


def test_iterator_form_filters_by_robot(fake: FakeService) -> None:
    with PoseSubscriber(connect=[fake.endpoint], robot_id="amr-1") as sub:
        seq = 0

        def arrived() -> Pose | None:
            nonlocal seq
            fake.put(pose_key("amr-2"), encode_pose(make_pose("amr-2", seq)))
            fake.put(pose_key("amr-1"), encode_pose(make_pose("amr-1", seq)))
            seq += 1
            return sub.try_recv()

        first = wait_for(arrived, 15, "the first pose")
        assert isinstance(first, Pose)
        assert first.robot_id == "amr-1"
        assert first.flags == PoseFlag.AMBIGUOUS_Y
        for i in range(5):
            fake.put(pose_key("amr-2"), encode_pose(make_pose("amr-2", 100 + i)))
            fake.put(pose_key("amr-1"), encode_pose(make_pose("amr-1", 100 + i)))
        got: list[Pose] = []
        while not got or got[-1].seq != 104:
            got.append(sub.recv(timeout=5))
        assert all(p.robot_id == "amr-1" for p in got)
        # Poses of the connection attempts may still be in flight before the burst.
        assert [p.seq for p in got if p.seq >= 100] == [100, 101, 102, 103, 104]
        with pytest.raises(TimeoutError):
            sub.recv(timeout=0.05)
    assert sub.closed
    with pytest.raises(SubscriberClosedError):
        sub.recv(timeout=1)


def test_callback_form_and_wildcard(fake: FakeService) -> None:
    robots: set[str] = set()
    both = threading.Event()

    def on_pose(pose: Pose) -> None:
        robots.add(pose.robot_id)
        if {"a-1", "b-2"} <= robots:
            both.set()

    with PoseSubscriber(connect=[fake.endpoint], on_pose=on_pose) as sub:

        def attempt() -> bool:
            fake.put(pose_key("a-1"), encode_pose(make_pose("a-1", 0)))
            fake.put(pose_key("b-2"), encode_pose(make_pose("b-2", 0)))
            return both.is_set()

        wait_for(attempt, 15, "poses of both robots", period_s=0.1)
        with pytest.raises(RuntimeError):
            sub.recv(timeout=0)


def test_malformed_payloads_are_counted_and_logged_once(
    fake: FakeService, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="clients.subscriber")
    with PoseSubscriber(connect=[fake.endpoint]) as sub:
        publish_until_received(fake, sub)
        for _ in range(3):
            fake.put(pose_key("amr-1"), b"\x00garbage")
        fake.put(pose_key("amr-1"), encode_pose(make_pose("amr-1", 999)))
        # Zenoh keeps per-publisher order, so the good pose arrives after the bad ones.
        wait_for(lambda: any_seq(sub, 999), 10, "the pose after the garbage")
        assert sub.malformed_count == 3
    warnings = [r for r in caplog.records if "malformed pose" in r.getMessage()]
    assert len(warnings) == 1


def publish_until_received(fake: FakeService, sub: PoseSubscriber) -> None:
    seq = 0

    def attempt() -> bool:
        nonlocal seq
        fake.put(pose_key("amr-1"), encode_pose(make_pose("amr-1", seq)))
        seq += 1
        return sub.received_count > 0

    wait_for(attempt, 15, "the first pose", period_s=0.1)


def any_seq(sub: PoseSubscriber, seq: int) -> bool:
    while (pose := sub.try_recv()) is not None:
        if pose.seq == seq:
            return True
    return False


def test_user_callback_errors_do_not_stop_delivery(fake: FakeService) -> None:
    calls: list[int] = []

    def on_pose(pose: Pose) -> None:
        calls.append(pose.seq)
        raise ValueError("user bug")

    with PoseSubscriber(connect=[fake.endpoint], on_pose=on_pose) as sub:
        wait_for(
            lambda: fake.put(pose_key("x"), encode_pose(make_pose("x", 1))) or len(calls) >= 3,
            15,
            "three callbacks",
            period_s=0.05,
        )
        assert sub.received_count >= 3


def test_survives_publisher_restart(fake: FakeService) -> None:
    with PoseSubscriber(connect=[fake.endpoint]) as sub:
        publish_until_received(fake, sub)
        fake.stop()
        while sub.try_recv() is not None:
            pass
        fake.start()
        before = sub.received_count
        seq = 10_000

        def attempt() -> bool:
            nonlocal seq
            fake.put(pose_key("amr-1"), encode_pose(make_pose("amr-1", seq)))
            seq += 1
            return sub.received_count > before

        wait_for(attempt, 30, "poses after the restart", period_s=0.1)


def test_opens_while_the_service_is_down_then_connects() -> None:
    fake = FakeService()
    with PoseSubscriber(connect=[fake.endpoint]) as sub:
        fake.start()
        try:
            publish_until_received(fake, sub)
        finally:
            fake.stop()


def test_interpreter_exits_with_an_unclosed_subscriber(tmp_path: Path) -> None:
    script = textwrap.dedent(
        """
        from clients import PoseSubscriber
        sub = PoseSubscriber(connect=["tcp/127.0.0.1:{port}"], on_pose=print)
        sub2 = PoseSubscriber(connect=["tcp/127.0.0.1:{port}"])
        print("opened", flush=True)
        """
    ).format(port=free_port())
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=30, check=False
    )
    assert done.returncode == 0, done.stderr
    assert "opened" in done.stdout


# ---------------------------------------------------------------------------------------------
# Against the real service


def ensure_active_session(client: MappingClient, robot_id: str) -> Session:
    for s in client.list_sessions():
        if s.robot_id == robot_id and s.active:
            return s
    try:
        return client.create_session(robot_id)
    except MappingError as err:
        if err.status != 409:
            raise
    return next(s for s in client.list_sessions() if s.robot_id == robot_id and s.active)


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_receives_from_live_service_across_restart(tmp_path: Path) -> None:
    service = ServiceProc(tmp_path / "data")
    service.start()
    try:
        with MappingClient(service.url) as client:
            ensure_active_session(client, "sub-1")
        with (
            PoseSubscriber(connect=[service.zenoh_endpoint], robot_id="sub-1") as sub,
            ScanFeeder(service.zenoh_endpoint, "sub-1"),
        ):
            first = sub.recv(timeout=30)
            assert first.robot_id == "sub-1"
            assert 0.0 <= first.quality <= 1.0

            service.stop()
            service.start()
            with MappingClient(service.url) as client:
                session = ensure_active_session(client, "sub-1")
            while sub.try_recv() is not None:
                pass

            def fresh_pose() -> bool:
                pose = sub.try_recv()
                return pose is not None and pose.session_id == session.id

            wait_for(fresh_pose, 45, "a pose from the restarted service", period_s=0.1)
    finally:
        service.stop()
