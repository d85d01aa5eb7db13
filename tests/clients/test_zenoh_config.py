"""`build_zenoh_config`: isolated sessions that still deliver to their own subscribers."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from clients.keyexpr import scan_key, scan_wildcard
from clients.wire import Scan, decode_scan, encode_scan
from clients.zenoh_config import build_zenoh_config


def _get(conf: zenoh.Config, key: str) -> object:
    return json.loads(conf.get_json(key))


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    s = zenoh.open(build_zenoh_config(listen=[]))
    try:
        yield s
    finally:
        s.close()  # an unclosed session with a callback subscriber hangs the interpreter


def test_defaults_are_isolated() -> None:
    conf = build_zenoh_config()
    assert _get(conf, "mode") == "peer"
    assert _get(conf, "listen/endpoints") == []
    assert _get(conf, "scouting/multicast/enabled") is False
    assert _get(conf, "scouting/gossip/enabled") is False


def test_overrides() -> None:
    conf = build_zenoh_config(
        mode="client", connect=["tcp/127.0.0.1:7447"], listen=["tcp/127.0.0.1:0"]
    )
    assert _get(conf, "mode") == "client"
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:0"]


def test_config_file_passes_through(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text(
        '{\n  // a comment, as JSON5 allows\n  mode: "router",\n'
        "  scouting: { multicast: { enabled: false } },\n}\n"
    )
    conf = build_zenoh_config(config_file=path, connect=["tcp/127.0.0.1:7448"])
    assert _get(conf, "mode") == "router"
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7448"]


def test_put_reaches_a_subscriber_of_the_same_session(session: zenoh.Session) -> None:
    received: list[Scan] = []
    arrived = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        received.append(decode_scan(sample.payload.to_bytes()))
        arrived.set()

    scan = Scan("amr-07", 1, 2, 3, -1.0, 0.01, 0.1, 30.0, np.array([1.0, 0.0, 2.5]))
    sub = session.declare_subscriber(scan_wildcard(), on_sample)
    try:
        session.put(scan_key("amr-07"), encode_scan(scan))
        assert arrived.wait(timeout=10.0), "the sample never arrived"
    finally:
        sub.undeclare()
    assert received == [scan]
