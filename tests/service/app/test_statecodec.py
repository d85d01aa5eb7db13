"""The checkpoint codec: exact round trips of the estimator and grid, and no code."""

from __future__ import annotations

import collections
import math
import time
from pathlib import Path

import numpy as np
import pytest
from svc_testkit import SimRobot

from service.app import statecodec
from service.app.mapper import Engine, LocalMapper
from service.core.frontend.paper import PaperFrontEnd
from service.core.maps.grid import GridImage
from service.core.slam import Tracker
from service.core.types import Pose2D

CORE = ("service.core",)


def _map(mapper: LocalMapper) -> GridImage:
    """The mapper's map, asking again while its back end draws it (`LocalMapper.snapshot`)."""
    deadline = time.monotonic() + 30.0
    while (image := mapper.snapshot()) is None:
        assert time.monotonic() < deadline, "the map was never drawn"
        time.sleep(0.005)
    assert isinstance(image, GridImage)
    return image


def test_estimator_and_grid_round_trip_exactly() -> None:
    """Poses after a restore are identical to those of the estimator that never stopped; the
    back end's graph comes back with its nodes, and the map with it."""
    robot = SimRobot("r1")
    scans = [robot.next_scan() for _ in range(160)]
    a = LocalMapper(Engine(), True, 0.05)
    for i, scan in enumerate(scans[:100]):
        a.map_scan(scan, None, i)
    assert a.wait_backend(60)
    b = LocalMapper(Engine(), True, 0.05)
    b.restore(a.state())
    for i, scan in enumerate(scans[100:], start=100):
        # The front end's fields: the back end's revisions depend on its thread's timing.
        assert a.map_scan(scan, None, i)[:7] == b.map_scan(scan, None, i)[:7]
    assert a.wait_backend(60)
    assert b.wait_backend(60)
    ga, gb = a.graph(), b.graph()
    assert ga is not None
    assert gb is not None
    assert ga.nodes > 5
    np.testing.assert_array_equal(ga.node_seq, gb.node_seq)
    np.testing.assert_allclose(ga.optimised, gb.optimised, atol=1e-6)
    np.testing.assert_array_equal(_map(a).occupancy, _map(b).occupancy)
    a.close()
    b.close()


def test_front_end_alone_round_trips_its_grid() -> None:
    robot = SimRobot("r1")
    scans = [robot.next_scan() for _ in range(120)]
    a = LocalMapper(Engine(loop_closure=False), True, 0.05)
    for scan in scans[:80]:
        a.map_scan(scan)
    b = LocalMapper(Engine(loop_closure=False), True, 0.05)
    b.restore(a.state())
    for scan in scans[80:]:
        assert a.map_scan(scan) == b.map_scan(scan)
    assert a.graph() is None
    np.testing.assert_array_equal(_map(a).occupancy, _map(b).occupancy)


def _paper(use_odometry: bool) -> Tracker:
    return PaperFrontEnd()


def test_a_checkpoint_of_another_front_end_is_refused() -> None:
    """A checkpoint restores only into the front end that wrote it (here the paper's, through
    the tests' `Engine.make_estimator`, against the matcher): refused by name either way."""
    robot = SimRobot("r1")
    scans = [robot.next_scan() for _ in range(30)]
    a = LocalMapper(Engine(loop_closure=False, make_estimator=_paper), True, 0.05)
    for scan in scans:
        a.map_scan(scan)
    matcher = LocalMapper(Engine(loop_closure=False), True, 0.05)  # the default
    with pytest.raises(statecodec.StateCodecError, match="another front end"):
        matcher.restore(a.state())
    with pytest.raises(statecodec.StateCodecError, match="another front end"):
        a.restore(matcher.state())


@pytest.mark.parametrize(
    "old", [(1, 2), {"version": 2, "estimator": None}, {"version": 3, "session": None}]
)
def test_older_state_versions_are_refused_by_name(old: object) -> None:
    """Versions 1 to 3 held the map another way: refused (the session replays instead)."""
    mapper = LocalMapper(Engine(loop_closure=False), True, 0.05)
    data = statecodec.encode(old, ("service.core",))
    refused = r"version [123] is not 4 \(versions 1 to 3 "
    with pytest.raises(statecodec.StateCodecError, match=refused):
        mapper.restore(data)


def test_values_containers_and_shared_references() -> None:
    shared = np.arange(6, dtype=np.float32).reshape(2, 3)
    inner: list[object] = [1, 2.5, None, "x", True, b"\x00\xff"]
    value = {
        "floats": [math.nan, math.inf, -0.0, 1e-300],
        "ints": [0, -1, 2**70],
        "np": [np.float64(1.5), np.int32(-3), np.bool_(True)],
        "arrays": (shared, shared),
        "q": collections.deque([1, 2], maxlen=5),
        "set": {3, 1, 2},
        "pose": Pose2D(1.0, 2.0, 0.5),
        "lists": [inner, inner],
        7: "int key",
    }
    back = statecodec.decode(statecodec.encode(value, CORE), CORE)
    assert back["arrays"][0] is back["arrays"][1]
    np.testing.assert_array_equal(back["arrays"][0], shared)
    assert back["arrays"][0].dtype == np.float32
    assert back["lists"][0] is back["lists"][1]
    assert back["lists"][0] == inner
    assert math.isnan(back["floats"][0])
    assert back["floats"][1:] == value["floats"][1:]
    assert math.copysign(1.0, back["floats"][2]) == -1.0
    assert back["ints"] == value["ints"]
    assert [type(v) for v in back["np"]] == [np.float64, np.int32, np.bool_]
    assert back["q"] == value["q"]
    assert back["q"].maxlen == 5
    assert back["set"] == {1, 2, 3}
    assert back["pose"] == value["pose"]
    assert type(back["pose"]) is Pose2D
    assert back[7] == "int key"


class Foreign:
    """A class outside the allowed modules."""


@pytest.mark.parametrize(
    "bad",
    [
        print,
        lambda: None,
        Foreign(),
        np.array([object()], dtype=object),
        {"k": Foreign},
    ],
)
def test_anything_else_is_refused(bad: object) -> None:
    with pytest.raises(statecodec.StateCodecError):
        statecodec.encode(bad, CORE)


def test_foreign_class_names_are_not_loaded() -> None:
    """A tampered file naming another module's class is refused, not imported and built."""
    data = statecodec.encode(Pose2D(0.0, 0.0, 0.0), ("service.core",))
    with pytest.raises(statecodec.StateCodecError, match="not allowed"):
        statecodec.decode(data, ("clients",))
    with pytest.raises(statecodec.StateCodecError):
        statecodec.decode(b"PK\x03\x04 not a zip", CORE)


def test_checkpoint_file_rejects_any_changed_byte() -> None:
    """The SHA-256 covers the header too: a changed counter is refused, not restored."""
    from service.app import checkpoint

    header = checkpoint.CheckpointHeader(
        epoch=0, segment=3, scans_accepted=40, poses=40, map_revision=2
    )
    data = checkpoint.encode(header, b"state bytes")
    assert checkpoint.decode(data) == (header, b"state bytes")
    tampered = data.replace(b'"scans_accepted": 40', b'"scans_accepted": 41')
    assert tampered != data
    with pytest.raises(checkpoint.CheckpointError, match="checksum"):
        checkpoint.decode(tampered)
    for cut in (0, 7, len(data) // 2, len(data) - 1):
        with pytest.raises(checkpoint.CheckpointError):
            checkpoint.decode(data[:cut])


def test_frozen_arrays_go_to_the_pack_once(tmp_path: Path) -> None:
    """A read-only array that owns its data is appended to the pack by the first encode that
    holds it and referred to afterwards; everything else stays in the bytes. A pack opened
    for a restore knows what it read, so the next checkpoint appends nothing again."""
    from service.core.types import frozen_array

    big = frozen_array(np.arange(4096, dtype=np.float64).reshape(64, 64))
    small = frozen_array(np.arange(8, dtype=np.float64))  # under PACK_MIN_BYTES: inline
    live = np.zeros((64, 64))  # writeable: it may change, so it is written every time
    view = frozen_array(np.arange(1024.0))[:512]  # a view does not own its data: inline
    tree = {"big": big, "again": big, "small": small, "live": live, "view": view}
    pack = statecodec.ArrayPack(tmp_path / "frozen.mpack")
    first = statecodec.encode(tree, CORE, pack)
    size = pack.path.stat().st_size
    assert 0 < size < big.nbytes  # one entry, deflated
    assert len(first) < live.nbytes  # `big` is not in the bytes, `live` is
    assert statecodec.encode(tree, CORE, pack) == first
    assert pack.path.stat().st_size == size  # nothing appended twice
    with pytest.raises(statecodec.StateCodecError, match="array pack"):
        statecodec.decode(first, CORE)
    reopened = statecodec.ArrayPack(pack.path)
    back = statecodec.decode(first, CORE, reopened)
    np.testing.assert_array_equal(back["big"], big)
    assert back["again"] is back["big"]
    assert not back["big"].flags.writeable
    assert back["live"].flags.writeable
    np.testing.assert_array_equal(back["view"], view)
    statecodec.encode(back, CORE, reopened)
    assert pack.path.stat().st_size == size
    assert statecodec.check_pack(pack.path) == statecodec.PackReport(1, size, None)


def test_a_damaged_or_missing_pack_entry_is_refused(tmp_path: Path) -> None:
    from service.core.types import frozen_array

    tree = {"a": frozen_array(np.ones(1000)), "b": frozen_array(np.arange(2000.0))}
    path = tmp_path / "frozen.mpack"
    data = statecodec.encode(tree, CORE, statecodec.ArrayPack(path))
    good = path.read_bytes()
    damaged = bytearray(good)
    damaged[-10] ^= 0x5A  # inside the second entry's deflated bytes
    path.write_bytes(bytes(damaged))
    with pytest.raises(statecodec.StateCodecError, match="checksum"):
        statecodec.decode(data, CORE, statecodec.ArrayPack(path))
    report = statecodec.check_pack(path)
    assert (report.entries, report.damage) == (1, "checksum mismatch")
    path.write_bytes(good[:-10])  # cut by a crash: the entry is incomplete
    with pytest.raises(statecodec.StateCodecError, match="cut short"):
        statecodec.decode(data, CORE, statecodec.ArrayPack(path))
    assert statecodec.check_pack(path).torn_tail_bytes > 0
    path.unlink()
    with pytest.raises(statecodec.StateCodecError, match="unreadable"):
        statecodec.decode(data, CORE, statecodec.ArrayPack(path))
    # A pack cut or replaced under a live writer: its entries are written again, not assumed.
    pack = statecodec.ArrayPack(path)
    statecodec.encode(tree, CORE, pack)
    path.write_bytes(b"")
    again = statecodec.encode(tree, CORE, pack)
    np.testing.assert_array_equal(statecodec.decode(again, CORE, pack)["b"], tree["b"])
