"""Fault injection: random byte flips and truncations in recordings and checkpoints.

100 seeded trials on the in-process restore path (`SessionManager` over a copy of a data
directory), plus a few restarts of the real service. Each trial asserts that:

- the session is still listed (never silently dropped);
- every pose recorded before the first damaged byte is served, identical, and so is every pose
  of the files left untouched;
- damage other than a plain truncation (a crash's torn tail) is reported: the session is
  `degraded` with what was lost;
- a damaged checkpoint changes nothing that is served: same trajectory, same map.
"""

from __future__ import annotations

import random
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from svc_testkit import (  # noqa: F401  # *_fixture: pytest fixtures used by name
    RuntimeFactory,
    ServiceProc,
    SimRobot,
    feed,
    make_settings,
    runtime_factory_fixture,
)

from clients.recording import MAGIC, iter_raw_records
from clients.wire import Pose, decode_pose
from clients.zenoh_config import build_zenoh_config
from service.app.mapper import Engine
from service.app.runtime import MappingRuntime
from service.app.sessions import MappingSession, SessionManager
from service.app.store import DataDir, MapStore, parse_checkpoint, parse_segment

TRIALS = 100


@dataclass(frozen=True)
class Base:
    """A crash image of one session: three recording segments, two checkpoints."""

    data: Path
    session_id: str
    poses: list[Pose]  # what clients were served before the crash
    occupancy: np.ndarray


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Base:
    root = tmp_path_factory.mktemp("fault-base")
    patch = pytest.MonkeyPatch()
    patch.setattr(MappingSession, "checkpoint_every_scans", 20)
    try:
        runtime = MappingRuntime(make_settings(root / "live"), zenoh_config=build_zenoh_config())
        runtime.start()
        try:
            session = runtime.sessions.create("fi", 0.05, True)
            feed(runtime, SimRobot("fi"), 50)
            shutil.copytree(root / "live", root / "image")  # kill -9 image: 10 scans uncovered
            poses = session.trajectory()
            assert session.wait_backend(60)  # the back end draws the map in its own thread
            occupancy = session.map_image().image.occupancy.copy()
        finally:
            runtime.close()
    finally:
        patch.undo()
    folder = root / "image" / "sessions" / session.id
    assert len([p for p in folder.iterdir() if parse_segment(p.name)]) == 3
    assert len([p for p in folder.iterdir() if parse_checkpoint(p.name)]) == 2
    return Base(root / "image", session.id, poses, occupancy)


def restore(data: Path) -> SessionManager:
    data_dir = DataDir(data)
    data_dir.open()
    try:
        maps = MapStore(data_dir.maps_dir)
        maps.load()
        manager = SessionManager(data_dir, maps, engine=Engine())
        manager.load_all()
        manager.restore_all(background=False)
        for session in manager.list():
            session.close()
        return manager
    finally:
        data_dir.close()


def poses_in(path: Path, before: int | None = None) -> list[Pose]:
    """The pose records of a recording file, those ending before byte `before` if given."""
    out = []
    for record in iter_raw_records(path):
        end = record.offset + 8 + len(record.payload)
        if before is not None and end > before:
            break
        if record.kind == "pose":
            out.append(decode_pose(record.payload))
    return out


def segment_index(name: str) -> int:
    parsed = parse_segment(name)
    assert parsed is not None
    return parsed[1]


@dataclass(frozen=True)
class Mutation:
    file: str
    kind: str  # "flip" or "truncate"
    first_offset: int  # first byte changed or cut


def mutate(folder: Path, rng: random.Random) -> Mutation:
    files = sorted(p for p in folder.iterdir() if parse_segment(p.name) or parse_checkpoint(p.name))
    target = rng.choice(files)
    data = bytearray(target.read_bytes())
    if rng.random() < 0.6:
        # Flips: 1..16 bytes at random offsets, mostly after the header.
        offsets = sorted(
            rng.randrange(len(MAGIC) if rng.random() < 0.95 else 0, len(data))
            for _ in range(rng.randint(1, 16))
        )
        for offset in offsets:
            data[offset] ^= rng.randint(1, 255)
        target.write_bytes(bytes(data))
        return Mutation(target.name, "flip", offsets[0])
    cut = rng.randrange(len(MAGIC), len(data))
    target.write_bytes(bytes(data[:cut]))
    return Mutation(target.name, "truncate", cut)


@pytest.mark.parametrize("seed", range(TRIALS))
def test_random_damage_is_survived_and_reported(base: Base, tmp_path: Path, seed: int) -> None:
    data = tmp_path / "data"
    shutil.copytree(base.data, data)
    folder = data / "sessions" / base.session_id
    original = {p.name: p for p in (base.data / "sessions" / base.session_id).iterdir()}
    mutation = mutate(folder, random.Random(seed))

    manager = restore(data)
    (session,) = manager.list()  # never silently dropped
    assert session.id == base.session_id
    assert session.status in ("ok", "degraded")
    served = {p.seq: p for p in session.trajectory()}

    # Every pose recorded before the first damaged byte, and every pose of the untouched
    # files, is served as it was.
    expected: list[Pose] = []
    for name, path in original.items():
        if parse_segment(name) is None:
            continue
        expected += poses_in(path, mutation.first_offset if name == mutation.file else None)
    for pose in expected:
        assert served.get(pose.seq) == pose, (mutation, pose.seq)
    seqs = [p.seq for p in session.trajectory()]
    assert seqs == sorted(set(seqs))  # in order, no sequence twice (paging relies on it)

    damage = session.damage
    is_checkpoint = parse_checkpoint(mutation.file) is not None
    if is_checkpoint:
        # A damaged checkpoint is never trusted and changes nothing that is served.
        assert session.trajectory() == base.poses
        assert session.wait_backend(60)
        np.testing.assert_array_equal(session.map_image().image.occupancy, base.occupancy)
        if (
            mutation.kind == "flip"
            or mutation.first_offset < original[mutation.file].stat().st_size
        ):
            assert damage.checkpoints_rejected == 1, mutation
            assert session.status == "degraded"
    elif mutation.kind == "flip":
        assert session.status == "degraded", mutation
        assert damage.regions >= 1
        assert damage.records_lost >= 1
        assert damage.bytes_lost > 0
    else:
        # Cutting the last segment looks like a crash's torn tail: cut quietly. Cutting poses
        # out of a segment a checkpoint covers is damage, and reported.
        last = max((n for n in original if parse_segment(n)), key=segment_index)
        path = original[mutation.file]
        cut_poses = len(poses_in(path)) - len(poses_in(path, mutation.first_offset))
        if mutation.file != last and cut_poses:
            assert session.status == "degraded", mutation


@pytest.mark.slow
@pytest.mark.timeout(120)
@pytest.mark.parametrize("seed", range(3))
def test_real_restart_reports_damage(base: Base, tmp_path: Path, seed: int) -> None:
    """The real process: the damaged session is listed, degraded, and `/health` and
    `/metrics` say so."""
    data = tmp_path / "data"
    shutil.copytree(base.data, data)
    folder = data / "sessions" / base.session_id
    rng = random.Random(1000 + seed)
    # Flip 4 bytes in the middle of a recording segment (the reproduction).
    segments = sorted(p for p in folder.iterdir() if parse_segment(p.name))
    target = segments[rng.randrange(len(segments))]
    raw = bytearray(target.read_bytes())
    middle = len(raw) // 2 + rng.randrange(-100, 100)
    for i in range(4):
        raw[middle + i] ^= 0xA5
    target.write_bytes(bytes(raw))

    svc = ServiceProc(data)
    svc.start()
    try:
        listed = svc.json("/sessions")["sessions"]
        assert isinstance(listed, list)
        (info,) = [s for s in listed if s["id"] == base.session_id]
        assert info["status"] == "degraded"
        assert info["damage"]["records_lost"] >= 1
        assert info["damage"]["bytes_lost"] > 0
        health = svc.json("/health")
        assert health["status"] == "degraded"
        assert health["sessions_degraded"] == [base.session_id]
        metrics = svc.metrics()
        assert metrics[f'mapping_session_records_lost{{session="{base.session_id}"}}'] >= 1
        assert metrics['mapping_sessions_status{status="degraded"}'] == 1
        served = svc.json(f"/sessions/{base.session_id}/trajectory")["poses"]
        assert isinstance(served, list)
        seqs = {p["sequence"] for p in served}
        before = poses_in(target, middle)
        assert {p.seq for p in before} <= seqs
    finally:
        assert svc.stop() == 0, svc.log_tail()
