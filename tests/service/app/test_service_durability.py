"""Durable state: restart, crash images (torn tails), resets, deletes, saved maps, kill -9."""

from __future__ import annotations

import io
import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import psutil
import pytest
import zenoh
from PIL import Image
from svc_testkit import (  # noqa: F401  # *_fixture: pytest fixtures used by name
    RuntimeFactory,
    ServiceProc,
    SimRobot,
    feed,
    runtime_factory_fixture,
    wait_for,
    zenoh_peer,
)

from clients.keyexpr import scan_key
from clients.recording import RecordingWriter, iter_raw_records
from clients.wire import Pose, Scan
from service.app import checkpoint, statecodec
from service.app.errors import StoreError
from service.app.sessions import MappingSession, SessionInfo
from service.app.store import SessionMeta


def recording_of(session: MappingSession) -> Path:
    return session._store.recording_path


@dataclass(frozen=True)
class Seen:
    """What a session showed (taken before its runtime closes: with mapper processes, a
    closed runtime's sessions can no longer render their maps)."""

    info: SessionInfo
    trajectory: list[Pose]
    occupancy: np.ndarray


def seen(session: MappingSession | Seen) -> Seen:
    if isinstance(session, Seen):
        return session
    # The back end draws the map in its own thread: every node in it first.
    assert session.wait_backend(60)
    return Seen(session.info(), session.trajectory(), session.map_snapshot().image.occupancy)


def assert_same_session(a: MappingSession | Seen, b: MappingSession | Seen) -> None:
    assert seen(a).info == seen(b).info
    assert_same_session_data(a, b)


def assert_same_session_data(a: MappingSession | Seen, b: MappingSession | Seen) -> None:
    """Counters, trajectory and map equal (the restore status may differ)."""
    sa, sb = seen(a), seen(b)
    ia, ib = sa.info, sb.info
    assert (ia.scans_accepted, ia.poses, ia.last_pose) == (
        ib.scans_accepted,
        ib.poses,
        ib.last_pose,
    )
    assert sa.trajectory == sb.trajectory
    np.testing.assert_array_equal(sa.occupancy, sb.occupancy)


# The same guarantees with the estimators in mapper processes (`--mapper-processes`), which
# then hold a lease of each active session's recording: they record scans and poses themselves.
# In process, fed by `ingest.submit`: the layout with the scans through the service's process
# (svc_testkit.make_settings); the kill -9 test below runs both layouts as real processes.
MAPPERS = pytest.mark.parametrize("mappers", [0, 2], ids=["in-process", "mapper-processes"])


@MAPPERS
def test_clean_restart_restores_everything(
    tmp_path: Path, runtime_factory: RuntimeFactory, mappers: int
) -> None:
    data = tmp_path / "data"
    first = runtime_factory(data, mapper_processes=mappers)
    active = first.sessions.create("r1", 0.05, True)
    robot = SimRobot("r1")
    feed(first, robot, 30)
    stopped = first.sessions.create("r2", 0.1, False)
    feed(first, SimRobot("r2"), 5)
    first.sessions.stop(stopped.id)
    saved = first.sessions.save(active.id)
    gone = first.sessions.create("r3", 0.05, True)
    first.sessions.delete(gone.id)
    was_active, was_stopped = seen(active), seen(stopped)
    first.close()

    second = runtime_factory(data, mapper_processes=mappers)
    assert_same_session(was_active, second.sessions.get(active.id))
    assert_same_session(was_stopped, second.sessions.get(stopped.id))
    assert second.sessions.get(stopped.id).state == "stopped"
    assert second.sessions.active_for("r1") is not None
    assert second.sessions.active_for("r2") is None
    assert {s.id for s in second.sessions.list()} == {active.id, stopped.id}
    assert second.maps.list() == [saved]
    assert second.maps.file(saved.map_id, saved.version, "map.png").read_bytes()
    # The restored session goes on mapping with continuing sequence numbers.
    feed(second, robot, 3)
    restored = second.sessions.get(active.id)
    assert [p.seq for p in restored.trajectory()] == list(range(33))


@MAPPERS
def test_crash_image_with_torn_tail_and_missing_pose(
    tmp_path: Path, runtime_factory: RuntimeFactory, mappers: int
) -> None:
    """What kill -9 leaves: every flushed record, maybe half a record, maybe a scan w/o pose."""
    data = tmp_path / "data"
    live = runtime_factory(data, mapper_processes=mappers)
    session = live.sessions.create("r1", 0.05, True)
    robot = SimRobot("r1")
    feed(live, robot, 25)
    crash = tmp_path / "crash"
    shutil.copytree(data, crash)  # the files as the kernel has them, service still running
    copy_rec = crash / "sessions" / session.id / recording_of(session).name
    live.close()

    with RecordingWriter(copy_rec) as writer:  # one more scan recorded, its pose never was
        writer.append(robot.next_payload())
    with copy_rec.open("ab") as f:  # and half a record after it
        f.write(b"\x40\x00\x00\x00\x12\x34")

    restored = runtime_factory(crash, mapper_processes=mappers).sessions.get(session.id)
    info = restored.info()
    assert info.scans_accepted == 26
    assert info.poses == 26
    assert restored.trajectory()[:25] == session.trajectory()
    kinds = [r.kind for r in iter_raw_records(copy_rec)]
    assert kinds == ["scan", "pose"] * 26  # torn tail cut, missing pose recorded


@MAPPERS
def test_restart_from_checkpoint_replays_only_the_tail(
    tmp_path: Path, runtime_factory: RuntimeFactory, monkeypatch: pytest.MonkeyPatch, mappers: int
) -> None:
    """A checkpoint every 10 scans: a crash after 25 re-estimates only the last 5."""
    monkeypatch.setattr(MappingSession, "checkpoint_every_scans", 10)
    data = tmp_path / "data"
    live = runtime_factory(data, mapper_processes=mappers)
    session = live.sessions.create("r1", 0.05, True)
    robot = SimRobot("r1")
    feed(live, robot, 25)
    crash = tmp_path / "crash"
    shutil.copytree(data, crash)  # a kill -9 image: checkpoint at scan 20, 5 scans after it
    expected = seen(session)
    live.close()

    estimated: list[int] = []
    original = MappingSession._estimate

    def counting(self: MappingSession, scan: Scan) -> Pose | None:
        estimated.append(scan.seq)
        return original(self, scan)

    monkeypatch.setattr(MappingSession, "_estimate", counting)
    second = runtime_factory(crash)
    assert len(estimated) == 5
    assert_same_session(expected, second.sessions.get(session.id))
    second.close()  # a clean shutdown checkpoints the rest
    estimated.clear()
    runtime_factory(crash).close()
    assert estimated == []
    folder = crash / "sessions" / session.id
    newest, older = sorted(folder.glob("checkpoint-*.mck"), reverse=True)
    # The newest checkpoint fails its checksum: the one before it is used, and it is said.
    damaged = bytearray(newest.read_bytes())
    damaged[len(damaged) // 2] ^= 0x5A
    newest.write_bytes(bytes(damaged))
    third = runtime_factory(crash)
    restored = third.sessions.get(session.id)
    assert_same_session_data(expected, restored)
    assert len(estimated) == 5  # from the checkpoint at scan 20
    assert restored.status == "degraded"
    assert restored.damage.checkpoints_rejected == 1
    assert restored.damage.records_lost == 0
    third.close()  # checkpoints the 5 scans: the damaged checkpoint is superseded and goes
    estimated.clear()
    newest, older = sorted(folder.glob("checkpoint-*.mck"), reverse=True)
    # A checkpoint whose estimator does not restore (another version's, say) is replayed past;
    # so is one that is not a checkpoint at all.
    older_header, _ = checkpoint.read(older)
    older.write_bytes(checkpoint.encode(older_header, b"not a state"))
    newest.write_bytes(checkpoint.encode(older_header, b"not a state"))  # names another segment
    (folder / "checkpoint.pickle").write_bytes(b"an old pickle: never loaded")
    fourth = runtime_factory(crash)
    assert_same_session_data(expected, fourth.sessions.get(session.id))
    assert len(estimated) == 25
    fourth.close()
    estimated.clear()
    for path in folder.glob("checkpoint-*.mck"):
        path.write_bytes(b"not a checkpoint")
    assert_same_session_data(expected, runtime_factory(crash).sessions.get(session.id))
    assert len(estimated) == 25


@MAPPERS
@pytest.mark.parametrize("named", ["manhattan", None], ids=["manhattan", "none"])
def test_a_session_of_the_deleted_cascade_restores_with_the_matcher(
    tmp_path: Path,
    runtime_factory: RuntimeFactory,
    *,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    mappers: int,
    named: str | None,
) -> None:
    """A `session.json` naming the deleted front end "manhattan", or naming none (written when
    the cascade was every session's), restores with the matcher: its checkpoints hold the
    cascade's state, so they are never loaded (by the session's recorded front end, not by a
    failure to decode: here they would load, or not even decode) and every recorded scan is
    re-estimated. Nothing is lost or counted as damage; one WARNING says why; `session.json`
    then names the matcher and the old checkpoints are gone, so the next start restores it as
    any other session, from a checkpoint of its own."""
    monkeypatch.setattr(MappingSession, "checkpoint_every_scans", 10)
    data = tmp_path / "data"
    first = runtime_factory(data, mapper_processes=mappers)
    session = first.sessions.create("r1", 0.05, True)
    feed(first, SimRobot("r1"), 20)  # checkpoints at scans 10 and 20
    expected = seen(session)
    first.close()
    folder = data / "sessions" / session.id
    meta_path = folder / "session.json"
    meta = json.loads(meta_path.read_bytes())
    if named is None:
        del meta["front_end"]
        # The checkpoints pass their checksum, but their state is none of ours.
        for path in folder.glob("checkpoint-*.mck"):
            header, _ = checkpoint.read(path)
            path.write_bytes(checkpoint.encode(header, b"the cascade's state"))
    else:
        meta["front_end"] = named
    meta_path.write_text(json.dumps(meta))
    assert list(folder.glob("checkpoint-*.mck"))

    estimated: list[str] = []  # the sessions of the scans re-estimated
    original = MappingSession._estimate

    def counting(self: MappingSession, scan: Scan) -> Pose | None:
        estimated.append(self.id)
        return original(self, scan)

    monkeypatch.setattr(MappingSession, "_estimate", counting)
    caplog.set_level(logging.WARNING, logger="service.app.sessions")
    second = runtime_factory(data, mapper_processes=mappers)
    restored = second.sessions.get(session.id)
    assert restored.front_end == "matcher"
    assert restored.status == "ok", restored.damage
    assert restored.damage.checkpoints_rejected == 0
    assert estimated.count(session.id) == 20  # every scan of the recording, none from a state
    assert_same_session_data(expected, restored)  # counters, recorded poses, the matcher's map
    warnings = [r.getMessage() for r in caplog.records if session.id in r.getMessage()]
    assert len(warnings) == 1, warnings
    assert "'manhattan'" in warnings[0]
    assert "replaying its whole recording" in warnings[0]
    assert json.loads(meta_path.read_bytes())["front_end"] == "matcher"
    assert not list(folder.glob("checkpoint-*.mck"))
    assert not list(folder.glob("frozen-*.mpack"))
    if not mappers:
        frontend = restored._mapper._session.frontend  # type: ignore[union-attr]
        assert type(frontend).__name__ == "ScanMatcherFrontEnd"
    second.close()  # an active session: a checkpoint of its own

    estimated.clear()
    caplog.clear()
    third = runtime_factory(data, mapper_processes=mappers)
    again = third.sessions.get(session.id)
    assert again.front_end == "matcher"
    assert again.status == "ok", again.damage
    assert session.id not in estimated  # restored from the matcher's checkpoint
    assert_same_session_data(expected, again)
    assert not [r for r in caplog.records if session.id in r.getMessage()]
    third.close()


def test_a_session_json_naming_an_unknown_front_end_is_refused() -> None:
    """An unknown front end (or "paper", offline only) keeps its clear error."""
    meta = SessionMeta("s-0123456789abcdef", "r1", 1, "active", 0.05, True, "matcher")
    for name in ("karto", "paper"):
        obj = json.loads(meta.to_json())
        obj["front_end"] = name
        with pytest.raises(StoreError, match=f"unknown front end '{name}'"):
            SessionMeta.from_json(json.dumps(obj).encode())
    for name in ("manhattan", None):
        obj = json.loads(meta.to_json())
        if name is None:
            del obj["front_end"]
        else:
            obj["front_end"] = name
        legacy = SessionMeta.from_json(json.dumps(obj).encode())
        assert (legacy.front_end, legacy.retired_front_end) == ("matcher", "manhattan")
        # Written back as it was read until the restore retires it.
        assert json.loads(legacy.to_json())["front_end"] == "manhattan"


@MAPPERS
def test_checkpoints_write_frozen_data_once(
    tmp_path: Path, runtime_factory: RuntimeFactory, monkeypatch: pytest.MonkeyPatch, mappers: int
) -> None:
    """With loop closure, what never changes again (finished submaps, the nodes' points, the
    frozen map chunks) goes to the epoch's array pack once: a checkpoint appends what froze
    since the one before, not the whole session. A restart restores from the pack; a damaged
    pack makes its checkpoints restore by replay instead, and nothing is lost."""
    monkeypatch.setattr(MappingSession, "checkpoint_every_scans", 400)
    data = tmp_path / "data"
    live = runtime_factory(data, mapper_processes=mappers)
    session = live.sessions.create("r1", 0.05, True)
    folder = data / "sessions" / session.id
    robot = SimRobot("r1")
    pack_sizes = []
    for k in range(4):
        # Every 400th scan checkpoints (with mapper processes, before the next is forwarded).
        feed(live, robot, 400 if k else 401)
        packs = list(folder.glob("frozen-*.mpack"))
        assert len(packs) == 1
        pack_sizes.append(packs[0].stat().st_size)
    assert 0 < pack_sizes[0] < pack_sizes[1] < pack_sizes[2] < pack_sizes[3]
    # The last checkpoint appended less than the pack held: the earlier arrays stayed. (Not
    # the third: a map chunk freezes whole when the next stretch of travel begins, so what a
    # checkpoint appends comes in lumps, a stretch later when the back end lags.)
    assert pack_sizes[3] - pack_sizes[2] < pack_sizes[2]
    assert statecodec.check_pack(packs[0]).damaged_at is None
    newest = max(folder.glob("checkpoint-*.mck"))
    _, state = checkpoint.read(newest)
    with pytest.raises(statecodec.StateCodecError, match="array pack"):
        statecodec.decode(state, ("service.core",))  # the frozen arrays are not in it
    crash = tmp_path / "crash"
    shutil.copytree(data, crash)  # a kill -9 image
    expected = seen(session)
    live.close()

    estimated: list[int] = []
    original = MappingSession._estimate

    def counting(self: MappingSession, scan: Scan) -> Pose | None:
        estimated.append(scan.seq)
        return original(self, scan)

    monkeypatch.setattr(MappingSession, "_estimate", counting)
    damaged = tmp_path / "damaged"
    shutil.copytree(crash, damaged)
    second = runtime_factory(crash)
    assert len(estimated) == 1  # from the checkpoint at scan 1,600
    assert_same_session(expected, second.sessions.get(session.id))
    second.close()

    # A flipped byte in the pack: every checkpoint refers to its first entries.
    pack = next((damaged / "sessions" / session.id).glob("frozen-*.mpack"))
    raw = bytearray(pack.read_bytes())
    raw[100] ^= 0x5A
    pack.write_bytes(bytes(raw))
    assert statecodec.check_pack(pack).damaged_at == 0
    third = runtime_factory(damaged)
    restored = third.sessions.get(session.id)
    assert len(estimated) == 1 + 1601  # replayed from the recording
    assert_same_session_data(expected, restored)
    assert restored.damage.checkpoints_rejected == 2
    assert restored.damage.records_lost == 0
    third.close()


@MAPPERS
def test_reset_survives_restart_and_stale_epochs_go(
    tmp_path: Path, runtime_factory: RuntimeFactory, mappers: int
) -> None:
    data = tmp_path / "data"
    first = runtime_factory(data, mapper_processes=mappers)
    session = first.sessions.create("r1", 0.05, True)
    robot = SimRobot("r1")
    feed(first, robot, 10)
    old_recording = recording_of(session)
    first.sessions.reset(session.id)
    assert not old_recording.exists()
    feed(first, robot, 4)
    first.close()
    stale = old_recording.parent / "epoch-000007.mrec"
    stale.write_bytes(b"left over by an interrupted reset")
    (data / "sessions" / "s-half-created").mkdir()

    second = runtime_factory(data)
    info = second.sessions.get(session.id).info()
    assert (info.scans_accepted, info.poses) == (4, 4)
    assert not stale.exists()
    assert [s.id for s in second.sessions.list()] == [session.id]


def test_one_service_per_data_dir(tmp_path: Path, runtime_factory: RuntimeFactory) -> None:
    runtime_factory(tmp_path / "data")
    with pytest.raises(StoreError, match="in use"):
        runtime_factory(tmp_path / "data")


@MAPPERS
def test_group_commit_fsyncs_only_changed_recordings(
    runtime_factory: RuntimeFactory, monkeypatch: pytest.MonkeyPatch, mappers: int
) -> None:
    runtime = runtime_factory(mapper_processes=mappers)
    runtime._stop.set()  # park the periodic syncer first: it would race the counting below
    session = runtime.sessions.create("r1", 0.05, True)
    runtime.sessions.create("idle", 0.05, True)
    feed(runtime, SimRobot("r1"), 2)
    synced: list[int] = []
    real_fsync = __import__("os").fsync

    def counting_fsync(fd: int) -> None:
        synced.append(fd)
        real_fsync(fd)

    monkeypatch.setattr("service.app.store.os.fsync", counting_fsync)
    runtime._sync_once()  # driven by hand
    assert len(synced) == 1  # only the session with new records
    runtime._sync_once()
    assert len(synced) == 1  # nothing new since
    assert session.info().scans_accepted == 2


# Real processes: the default layout with mapper processes has them take the scans from Zenoh;
# `--no-ingest-in-mappers` is the older one (scans through the service's process).
@pytest.mark.slow
@pytest.mark.timeout(90)
@pytest.mark.parametrize(
    ("mappers", "layout"),
    [(0, []), (2, []), (2, ["--no-ingest-in-mappers"])],
    ids=["in-process", "mapper-processes", "scans-through-the-service"],
)
def test_kill_9_right_after_an_acknowledgement_loses_nothing(
    tmp_path: Path, mappers: int, layout: list[str]
) -> None:
    """Every scan and pose the service has acknowledged (in its counters and trajectory) was
    written to the kernel before it showed: kill -9 at that moment, with nothing else in flight,
    and a restart has all of them, identical. Deterministic: which records are acknowledged does
    not depend on timing, so a writer that leaves them in a user-space buffer fails every run.
    With mapper processes (which then write the recording), they die with the service."""
    data = tmp_path / "data"
    token = "k9-token"
    args = ["--mapper-processes", str(mappers), *layout]
    svc = ServiceProc(data, token=token, extra_args=args)
    svc.start()
    scans = 60
    try:
        # Control without the token is refused by the real process.
        assert httpx.post(svc.url + "/sessions", json={"robot_id": "k9"}).status_code == 401
        sid = svc.create_session("k9")["id"]
        robot = SimRobot("k9")
        with zenoh_peer(svc.zenoh_endpoint) as peer:
            pub = peer.declare_publisher(
                scan_key("k9"), congestion_control=zenoh.CongestionControl.BLOCK
            )
            wait_for(lambda: pub.matching_status.matching, 30, "the service's subscription")

            def accepted() -> int:
                return int(svc.json(f"/sessions/{sid}")["scans_accepted"])  # type: ignore[call-overload]

            while robot.seq < scans:
                wait_for(lambda: robot.seq - accepted() < 8, 30, "room in the queue")
                pub.put(robot.next_payload())
            wait_for(lambda: accepted() == scans, 30, f"{scans} scans acknowledged")
            pub.undeclare()  # type: ignore[no-untyped-call]
        before = svc.json(f"/sessions/{sid}")
        traj_before = svc.json(f"/sessions/{sid}/trajectory")["poses"]
        assert before["scans_accepted"] == before["poses"] == scans
        assert isinstance(traj_before, list)
        assert len(traj_before) == scans
        assert svc.proc is not None
        children = [psutil.Process(c.pid) for c in psutil.Process(svc.proc.pid).children()]
        assert len(children) >= mappers
        svc.kill9()  # right after the acknowledgement
        # No orphan mapper process goes on writing the recording the restart replays.
        _gone, alive = psutil.wait_procs(children, timeout=10)
        assert alive == []
    finally:
        svc.stop()

    again = ServiceProc(data, token=token, extra_args=args)
    again.start()
    try:
        after = again.json(f"/sessions/{sid}")
        traj_after = again.json(f"/sessions/{sid}/trajectory")["poses"]
        assert after["state"] == "active"
        # Everything acknowledged before the kill is back, identical, and nothing else.
        assert after["scans_accepted"] == after["poses"] == scans
        assert traj_after == traj_before
        png = again.get(f"/sessions/{sid}/map.png")
        assert png.status_code == 200
        Image.open(io.BytesIO(png.content)).verify()
        # And mapping goes on where it stopped.
        with zenoh_peer(again.zenoh_endpoint) as peer:
            pub = peer.declare_publisher(
                scan_key("k9"), congestion_control=zenoh.CongestionControl.BLOCK
            )
            target = after["scans_accepted"] + 5

            def more() -> bool:
                pub.put(robot.next_payload())
                return bool(again.json(f"/sessions/{sid}")["scans_accepted"] >= target)

            wait_for(more, 30, "mapping to continue after the restart", period_s=0.05)
            pub.undeclare()  # type: ignore[no-untyped-call]
        seqs = [p["sequence"] for p in again.json(f"/sessions/{sid}/trajectory")["poses"]]
        assert seqs == list(range(len(seqs)))
    finally:
        assert again.stop() == 0, again.log_tail()


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_serve_logs_what_its_shutdown_made_durable(tmp_path: Path) -> None:
    """SIGTERM used to end `serve` without a word: the log must say the shutdown started and
    what it flushed and closed."""
    svc = ServiceProc(tmp_path / "data")
    svc.start()
    try:
        sid = svc.create_session("bye-1")["id"]
        robot = SimRobot("bye-1")
        with zenoh_peer(svc.zenoh_endpoint) as peer:
            pub = peer.declare_publisher(
                scan_key("bye-1"), congestion_control=zenoh.CongestionControl.BLOCK
            )

            def mapped() -> bool:
                pub.put(robot.next_payload())
                return bool(svc.json(f"/sessions/{sid}")["scans_accepted"] >= 5)

            wait_for(mapped, 30, "5 scans mapped", period_s=0.05)
            pub.undeclare()  # type: ignore[no-untyped-call]
    finally:
        assert svc.stop() == 0, svc.log_tail()
    text = svc.log_path.read_text(errors="replace")
    assert "SIGTERM: shutting down" in text, text[-3000:]
    line = next((ln for ln in text.splitlines() if "shut down in" in ln), "")
    assert "1 session(s) fsynced and closed, 1 checkpoint(s) written" in line, text[-3000:]
    assert "Zenoh session closed" in line
    assert "unlocked" in line
    assert text.index("SIGTERM: shutting down") < text.index("shut down in")
