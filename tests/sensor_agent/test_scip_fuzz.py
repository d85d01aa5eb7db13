"""Hypothesis: random and mutated byte streams get only typed events and `ScipError`s out."""

from __future__ import annotations

import contextlib
import itertools

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sensor_agent.scip import (
    CommandOk,
    Discarded,
    ReplyError,
    ScanData,
    ScanStarted,
    ScipCodec,
    ScipError,
    SensorParameters,
    SensorState,
    TimeReply,
    VersionInfo,
    checksum,
    decode_value,
)
from sensor_agent.scip import commands as c
from sensor_agent.scip.encoding import decode_values, encode_value, encode_values

EVENT_TYPES = (
    CommandOk,
    VersionInfo,
    SensorParameters,
    SensorState,
    TimeReply,
    ScanStarted,
    ScanData,
    ReplyError,
    Discarded,
)
FUZZ = settings(
    max_examples=100,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

STEPS = (100, 160)  # a 61-step scan: 183 data characters, a value split across lines


def with_sum(content: bytes) -> bytes:
    return content + bytes([checksum(content)])


def scan_reply(echo: bytes, ts_ms: int, values: list[int]) -> bytes:
    payload = encode_values(values, 3)
    lines = [echo, b"99b", with_sum(encode_value(ts_ms, 4))]
    lines += [with_sum(payload[i : i + 64]) for i in range(0, len(payload), 64)]
    return b"\n".join(lines) + b"\n\n"


def kv(key: str, value: str) -> bytes:
    body = f"{key}:{value}".encode()
    return body + b";" + bytes([checksum(body)])


PP = (
    b"\n".join(
        [
            b"PP",
            b"00P",
            *(
                kv(k, v)
                for k, v in [
                    ("MODL", "UTM-30LX"),
                    ("DMIN", "23"),
                    ("DMAX", "60000"),
                    ("ARES", "1440"),
                    ("AMIN", "0"),
                    ("AMAX", "1080"),
                    ("AFRT", "540"),
                    ("SCAN", "2400"),
                ]
            ),
        ]
    )
    + b"\n\n"
)

values_st = st.lists(st.integers(0, 262_143), min_size=61, max_size=61)
scans_st = st.lists(st.tuples(st.integers(0, (1 << 24) - 1), values_st), min_size=1, max_size=3)


def session_commands() -> list[c.Command]:
    return [c.qt(), c.pp(), c.md(*STEPS)]


def valid_stream(scans: list[tuple[int, list[int]]]) -> bytes:
    stream = b"QT\n00P\n\n" + PP + b"MD0100016001000\n00P\n\n"
    for ts, values in scans:
        stream += scan_reply(b"MD0100016001000", ts, values)
    return stream


def feed(codec: ScipCodec, data: bytes, cuts: list[int]) -> list[object]:
    events: list[object] = []
    points = sorted({min(max(0, x), len(data)) for x in cuts} | {0, len(data)})
    for a, b in itertools.pairwise(points):
        events += codec.receive(data[a:b])  # must never raise
    return events


def check(events: list[object]) -> None:
    for ev in events:
        assert isinstance(ev, EVENT_TYPES)
        if isinstance(ev, ReplyError):
            assert isinstance(ev.error, ScipError)
        if isinstance(ev, ScanData):
            assert ev.ranges_mm.dtype == np.uint32
            assert ev.ranges_mm.shape == (61,)


@FUZZ
@given(data=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 3000), max_size=20))
def test_random_bytes(data: bytes, cuts: list[int]) -> None:
    codec = ScipCodec()
    for cmd in session_commands():
        codec.send(cmd)
    check(feed(codec, data, cuts))


@FUZZ
@given(
    scans=scans_st,
    edits=st.lists(
        st.tuples(st.sampled_from(["flip", "insert", "delete", "dup"]), st.integers(0, 10**6)),
        max_size=12,
    ),
    junk=st.binary(max_size=40),
    cuts=st.lists(st.integers(0, 3000), max_size=10),
)
def test_mutated_streams(
    scans: list[tuple[int, list[int]]],
    edits: list[tuple[str, int]],
    junk: bytes,
    cuts: list[int],
) -> None:
    data = bytearray(valid_stream(scans))
    for op, k in edits:
        i = k % (len(data) + 1)
        if op == "flip" and i < len(data):
            data[i] ^= 1 << (k % 8)
        elif op == "insert":
            data[i:i] = junk[: k % (len(junk) + 1)] or b"\n"
        elif op == "delete":
            del data[i : i + k % 7 + 1]
        elif op == "dup":
            data[i:i] = data[i : i + k % 50]
    codec = ScipCodec()
    for cmd in session_commands():
        codec.send(cmd)
    check(feed(codec, bytes(data), cuts))


@FUZZ
@given(
    scans=scans_st,
    op=st.sampled_from(["substitute", "insert", "delete"]),
    position=st.integers(0, 10**6),
    byte=st.integers(0, 255),
)
def test_a_single_byte_error_never_yields_a_wrong_scan(
    scans: list[tuple[int, list[int]]], op: str, position: int, byte: int
) -> None:
    """Checksums plus the 0x30-0x6F alphabet and the length check catch any one-byte error."""
    data = bytearray(valid_stream(scans))
    i = position % len(data)
    if op == "substitute":
        data[i] = byte
    elif op == "insert":
        data[i:i] = bytes([byte])
    else:
        del data[i]
    codec = ScipCodec()
    for cmd in session_commands():
        codec.send(cmd)
    events = codec.receive(bytes(data))
    check(events)
    originals = {(ts, tuple(v)) for ts, v in scans}
    for ev in events:
        if isinstance(ev, ScanData):
            assert (ev.timestamp_raw_ms, tuple(ev.ranges_mm.tolist())) in originals


@FUZZ
@given(st.binary(max_size=16), st.integers(1, 4))
def test_decoders_raise_only_scip_errors(chars: bytes, n: int) -> None:
    with contextlib.suppress(ScipError):
        decode_value(chars)
    with contextlib.suppress(ScipError):
        decode_values(chars, n)
