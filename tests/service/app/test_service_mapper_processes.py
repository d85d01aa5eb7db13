"""Mapper processes: the same poses and maps as in-process, restarts, and a killed process."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from svc_testkit import (  # noqa: F401  # *_fixture: pytest fixtures used by name
    RuntimeFactory,
    SimRobot,
    feed,
    runtime_factory_fixture,
    wait_for,
)

from clients.keyexpr import scan_key
from clients.recording import iter_raw_records
from service.app import checkpoint
from service.app.mapper import RemoteMapper
from service.app.runtime import MappingRuntime
from service.app.sessions import MappingSession


def poses(session: MappingSession) -> list[tuple[object, ...]]:
    """The trajectory without the session id (the two services name sessions differently)."""
    return [
        (p.seq, p.stamp_ns, p.x_m, p.y_m, p.theta_rad, p.quality, p.flags)
        for p in session.trajectory()
    ]


def assert_same_session(a: MappingSession, b: MappingSession) -> None:
    """Same counters, poses (exactly) and map."""
    assert a.wait_backend(60)  # the back end draws the map in its own thread
    assert b.wait_backend(60)
    assert a.info().scans_accepted == b.info().scans_accepted
    assert poses(a) == poses(b)
    np.testing.assert_array_equal(a.map_image().image.occupancy, b.map_image().image.occupancy)


def mapper_pid(runtime: MappingRuntime, session: MappingSession) -> int:
    mapper = session._mapper
    assert isinstance(mapper, RemoteMapper)
    pid = mapper._proc.pid
    assert pid is not None
    return pid


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_mapper_processes_map_exactly_as_in_process_and_restart_from_checkpoints(
    tmp_path: Path, runtime_factory: RuntimeFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(MappingSession, "checkpoint_every_scans", 20)
    local = runtime_factory(tmp_path / "local")
    remote = runtime_factory(tmp_path / "remote", mapper_processes=2)
    assert remote.settings.ingest.worker_threads == 4
    pairs = []
    for robot_id in ("r1", "r2", "r3"):
        pair = [rt.sessions.create(robot_id, 0.05, False) for rt in (local, remote)]
        for rt in (local, remote):
            feed(rt, SimRobot(robot_id, seed=2), 45)
        pairs.append(pair)
    # Least-loaded placement: the three sessions use both processes.
    assert len({mapper_pid(remote, s) for _, s in pairs}) == 2
    for a, b in pairs:
        assert a.info().poses == 45
        assert_same_session(a, b)
    # Reset happens in the process too.
    for rt, session in zip((local, remote), pairs[0], strict=True):
        rt.sessions.reset(session.id)
        feed(rt, SimRobot("r1", seed=3), 10)
    assert_same_session(*pairs[0])

    # A restart of the remote service restores from its checkpoints (taken in the processes).
    remote.close()
    restarted = runtime_factory(tmp_path / "remote", mapper_processes=2)
    for a, b in pairs:
        assert_same_session(a, restarted.sessions.get(b.id))


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_killed_mapper_process_is_started_again_and_its_maps_rebuilt(
    tmp_path: Path, runtime_factory: RuntimeFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(MappingSession, "checkpoint_every_scans", 20)
    local = runtime_factory(tmp_path / "local")
    remote = runtime_factory(tmp_path / "remote", mapper_processes=1)
    pair = [rt.sessions.create("r1", 0.05, False) for rt in (local, remote)]
    robots = [SimRobot("r1", seed=2) for _ in pair]
    for rt, robot in zip((local, remote), robots, strict=True):
        feed(rt, robot, 30)  # a checkpoint at 20, 10 scans after it
    pid = mapper_pid(remote, pair[1])
    process = pair[1]._mapper._proc._process  # type: ignore[attr-defined]
    os.kill(pid, signal.SIGKILL)
    wait_for(lambda: not process.is_alive(), 10, "the mapper process to die")
    for rt, robot in zip((local, remote), robots, strict=True):
        feed(rt, robot, 15)
    # Every scan got its pose, and the rebuilt map continues exactly where the lost one was.
    assert pair[1].info().scans_accepted == 45
    assert mapper_pid(remote, pair[1]) != pid
    assert_same_session(*pair)
    assert "mapping_mapper_restarts 1" in remote.metrics.render().splitlines()
    assert pair[1].estimator_errors == 0


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_leased_recordings_stay_whole_under_checkpoints_idle_closes_and_a_stop(
    tmp_path: Path, runtime_factory: RuntimeFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Scans keep coming while the lease is taken back again and again (a checkpoint every 7
    scans, idle closes from another thread, then a stop): every recording holds exactly scan,
    pose, scan, pose..., each checkpoint covers exactly the scans before its segment, the
    stopped session's recording is closed in its mapper process, and a restart serves the
    same trajectories."""
    monkeypatch.setattr(MappingSession, "checkpoint_every_scans", 7)
    runtime = runtime_factory(tmp_path / "data", mapper_processes=2)
    robots = [SimRobot(f"w{i}", seed=1 + i) for i in range(3)]
    sessions = [runtime.sessions.create(r.robot_id, 0.05, False) for r in robots]
    payloads = {r.robot_id: [r.next_payload() for _ in range(60)] for r in robots}
    stop = threading.Event()

    def closer() -> None:  # housekeeping's idle close, as often as it can get the lock
        while not stop.is_set():
            runtime.sessions.close_idle(0.0)
            time.sleep(0.003)

    thread = threading.Thread(target=closer)
    thread.start()
    try:
        for k in range(60):
            for robot in robots:
                wait_for(lambda: runtime.ingest.pending() < 6, 60, "room", 0.002)
                runtime.ingest.submit(scan_key(robot.robot_id), payloads[robot.robot_id][k])
            if k == 40:
                stop.set()  # no more idle closes: the stop alone must close the lease
                thread.join()
            if k == 45:  # mid-stream: its last scan may be queued, in flight or answered
                runtime.sessions.stop(sessions[0].id)
        wait_for(lambda: runtime.ingest.pending() == 0, 60, "the queues to drain")
    finally:
        stop.set()
        thread.join()
    expected = {}
    for session in sessions:
        info = session.info()
        assert info.scans_accepted == info.poses
        if session is sessions[0]:
            assert 40 <= info.scans_accepted <= 46
        else:
            assert info.scans_accepted == 60
        kinds = [
            record.kind for path in session.recording_paths() for record in iter_raw_records(path)
        ]
        assert kinds == ["scan", "pose"] * info.scans_accepted
        assert [p.seq for p in session.trajectory()] == list(range(info.poses))
        # Each checkpoint covers exactly the scans recorded in the segments before its own.
        store = session._store
        checkpoints = store.checkpoint_paths()
        assert checkpoints
        for segment, path in checkpoints:
            header, _ = checkpoint.read(path)
            covered = sum(
                1
                for seg in store.segments()
                if seg.index < segment
                for record in iter_raw_records(seg.path)
                if record.kind == "scan"
            )
            assert covered == header.scans_accepted, (path.name, covered, header)
        expected[session.id] = poses(session)
    # The stopped session's recording is closed everywhere, its mapper process included.
    stopped_files = {str(seg.path) for seg in sessions[0]._store.segments()}
    for pid in runtime.mapper_pool.pids if runtime.mapper_pool else []:
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            with contextlib.suppress(OSError):
                assert os.readlink(fd) not in stopped_files
    runtime.close()
    again = runtime_factory(tmp_path / "data", mapper_processes=2)
    for session_id, trajectory in expected.items():
        assert poses(again.sessions.get(session_id)) == trajectory
