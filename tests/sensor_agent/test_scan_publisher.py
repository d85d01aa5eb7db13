"""ScanPublisher: consecutive numbering, liveliness, BLOCK congestion, counted drops."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import zenoh
from conftest import wait_for

from clients.wire import Scan, decode_scan
from clients.zenoh_config import build_zenoh_config
from sensor_agent.publisher import ScanPublisher


def make_scan(i: int) -> Scan:
    return Scan(
        robot_id="placeholder",
        seq=999,
        sensor_stamp_ns=i * 25_000_000,
        host_stamp_ns=1_700_000_000_000_000_000 + i * 25_000_000,
        angle_min_rad=-2.356194490192345,
        angle_increment_rad=0.004363323129985824,
        range_min_m=0.023,
        range_max_m=60.0,
        ranges_m=np.full(1081, 1.0 + i / 1000.0),
    )


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    s = zenoh.open(build_zenoh_config())  # listens on nothing, no scouting: isolated
    try:
        yield s
    finally:
        s.close()


def alive_keys(session: zenoh.Session) -> list[str]:
    return [str(r.ok.key_expr) for r in session.liveliness().get("robots/**", timeout=2) if r.ok]


def test_scans_are_numbered_stamped_and_published(session: zenoh.Session) -> None:
    received: list[Scan] = []
    sources: list[tuple[str, int]] = []

    def on_scan(sample: zenoh.Sample) -> None:
        received.append(decode_scan(sample.payload.to_bytes()))
        info = sample.source_info
        assert info is not None
        sources.append((str(info.source_id.zid), info.source_sn))

    sub = session.declare_subscriber("robots/*/scan", on_scan)
    with ScanPublisher(session, "bot-7", "robots") as pub:
        assert pub.key == "robots/bot-7/scan"
        # The robot's presence, and this publisher's own token (a second agent is visible).
        zid = str(session.zid())
        assert sorted(alive_keys(session)) == ["robots/bot-7/alive", f"robots/bot-7/alive/{zid}"]
        for i in range(50):
            assert pub.submit(make_scan(i))
        # A local subscriber sees a scan before put() returns and the counter moves.
        wait_for(
            lambda: len(received) == 50 and pub.counters.published == 50,
            10,
            "50 scans received and counted",
        )
        assert pub.counters.dropped == 0
    sub.undeclare()
    assert [s.seq for s in received] == list(range(50))
    assert sources == [(zid, seq) for seq in range(50)]  # source id and sequence on every scan
    assert {s.robot_id for s in received} == {"bot-7"}
    assert received[3] == dataclasses.replace(make_scan(3), robot_id="bot-7", seq=3)
    assert alive_keys(session) == []  # the token went with close()


def test_prefix_is_configurable(session: zenoh.Session) -> None:
    with ScanPublisher(session, "bot-8", "site-a/robots") as pub:
        assert pub.key == "site-a/robots/bot-8/scan"
        assert alive_keys_for(session, "site-a/*/*/alive") == ["site-a/robots/bot-8/alive"]


def alive_keys_for(session: zenoh.Session, key: str) -> list[str]:
    return [str(r.ok.key_expr) for r in session.liveliness().get(key, timeout=2) if r.ok]


def test_congestion_control_is_block(session: zenoh.Session) -> None:
    with ScanPublisher(session, "bot-9") as pub:
        assert pub._publisher.congestion_control == zenoh.CongestionControl.BLOCK


class _GatedPublisher:
    """Stands in for a Zenoh publisher on a stalled network: put() waits for the gate."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.payloads: list[bytes] = []

    def put(self, payload: bytes, **_kw: Any) -> None:
        self.gate.wait()
        self.payloads.append(payload)

    def undeclare(self) -> None:
        pass

    matching_status = False  # nobody listens

    def declare_matching_listener(self, callback: Any) -> _GatedPublisher:
        return _GatedPublisher()


class _FakeSession:
    def __init__(self) -> None:
        self.publisher = _GatedPublisher()

    def declare_publisher(self, key: str, **_kw: Any) -> _GatedPublisher:
        return self.publisher

    def liveliness(self) -> _FakeSession:
        return self

    def zid(self) -> str:
        return "ab" * 16

    def declare_token(self, key: str) -> _GatedPublisher:
        return _GatedPublisher()


def test_a_stalled_network_drops_counted_scans_with_visible_gaps() -> None:
    fake = _FakeSession()
    pub = ScanPublisher(fake, "bot-1", queue_scans=3)  # type: ignore[arg-type]
    results = [pub.submit(make_scan(i)) for i in range(20)]  # never blocks
    assert not all(results)
    assert pub.counters.dropped >= 20 - 1 - 3
    fake.publisher.gate.set()
    pub.close()
    assert pub.counters.published + pub.counters.dropped == 20
    seqs = [decode_scan(p).seq for p in fake.publisher.payloads]
    assert seqs == sorted(seqs)
    assert seqs[0] == 0
    assert len(seqs) == pub.counters.published
