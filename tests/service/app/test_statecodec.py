"""The checkpoint codec: exact round trips of the estimator and grid, and no code."""

from __future__ import annotations

import collections
import math

import numpy as np
import pytest
from svc_testkit import SimRobot

from service.app import statecodec
from service.app.mapper import Engine, LocalMapper
from service.core.types import Pose2D

CORE = ("service.core",)


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
    np.testing.assert_array_equal(a.snapshot().occupancy, b.snapshot().occupancy)
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
    np.testing.assert_array_equal(a.snapshot().occupancy, b.snapshot().occupancy)


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
