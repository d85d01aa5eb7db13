"""Fuzzing the decoders: only `DecodeError` may ever come out of `decode_scan`/`decode_pose`.

Each decoder gets at least 10,000 payloads drawn evenly from four families: random bytes,
random msgpack objects, valid messages with mutated bytes, and valid maps with fields
replaced, added or deleted. Runs are derandomised so CI is stable.
"""

from __future__ import annotations

import math
import random
import struct
from collections import Counter
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from clients.wire import (
    MAX_BEAMS,
    DecodeError,
    OdometryPose,
    Pose,
    PoseFlag,
    Scan,
    decode_pose,
    decode_scan,
    encode_pose,
    encode_scan,
)

EXAMPLES_PER_DECODER = 10_000

FUZZ_SETTINGS = settings(
    max_examples=EXAMPLES_PER_DECODER,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _scans() -> list[Scan]:
    rng = np.random.default_rng(7)
    scans = []
    for beams, encoding, with_extras in [
        (1, "u16_mm", False),
        (3, "f32_m", True),
        (10, "u16_mm", True),
        (181, "f32_m", False),
        (1081, "u16_mm", True),
    ]:
        ranges = rng.integers(0, 30_000, beams) / 1000.0
        ranges[::7] = 0.0  # some "no return" beams
        scans.append(
            Scan(
                robot_id=f"robot-{beams}",
                seq=beams,
                sensor_stamp_ns=1_000_000 * beams,
                host_stamp_ns=1_700_000_000_000_000_000 + beams,
                angle_min_rad=-math.radians(135.0),
                angle_increment_rad=math.radians(0.25),
                range_min_m=0.1,
                range_max_m=30.0,
                ranges_m=ranges,
                intensities=rng.random(beams).astype(np.float32) if with_extras else None,
                odom=OdometryPose(1.0, 2.0, 0.5, 123) if with_extras else None,
                ranges_encoding=encoding,  # type: ignore[arg-type]
            )
        )
    return scans


def _poses() -> list[Pose]:
    return [
        Pose("s1", "amr-07", 0, 0, 0.0, 0.0, 0.0, 0.0),
        Pose("session.2", "a", 99, -5, -1e6, 3.5, math.pi, 1.0, PoseFlag.AMBIGUOUS_X),
        Pose("s-3", "b_2", (1 << 64) - 1, 1 << 62, 1.25, -2.5, -3.0, 0.5, PoseFlag(0xFF)),
    ]


SCAN_PAYLOADS = [encode_scan(s) for s in _scans()]
POSE_PAYLOADS = [encode_pose(p) for p in _poses()]


def _body(payload: bytes) -> dict[str, Any]:
    body = msgpack.unpackb(payload, raw=False)
    assert isinstance(body, dict)
    return body


SCAN_BODIES = [_body(p) for p in SCAN_PAYLOADS]
POSE_BODIES = [_body(p) for p in POSE_PAYLOADS]
SCAN_KEYS = sorted({k for b in SCAN_BODIES for k in b} | {"odom.x_m", "odom.stamp_ns", "extra"})
POSE_KEYS = sorted({k for b in POSE_BODIES for k in b} | {"extra"})

# ---------------------------------------------------------------------------------------------
# Payload families. Hypothesis draws only (family, seed); the payload is built from the seed
# with `random.Random` in plain Python. Drawing rich nested objects through Hypothesis costs
# ~10-20 ms per example here, which would make 2 x 10,000 examples take minutes.

FAMILIES = ("bytes", "object", "mutated", "fields")

_INTERESTING: list[object] = [
    None,
    True,
    False,
    0,
    1,
    -1,
    2,
    3,
    255,
    65_535,
    65_536,
    (1 << 63) - 1,
    1 << 63,
    (1 << 64) - 1,
    -(1 << 63),
    0.0,
    -0.0,
    1e-12,
    0.1,
    0.5,
    1.0,
    1.5,
    math.pi,
    2 * math.pi + 1e-3,
    1e300,
    math.nan,
    math.inf,
    -math.inf,
    "",
    "scan",
    "pose",
    "u16_mm",
    "f32_m",
    "amr-07",
    "a/b",
    "*",
    "$*",
    "a b",
    "x" * 65,
    b"",
    b"\x00",
    b"\x00\x00" * 3,
    b"\x00\x00\x80\x7f" * 3,
    [],
    {},
]


def _leaf(rnd: random.Random) -> object:
    kind = rnd.randrange(6)
    if kind == 0:
        return rnd.choice(_INTERESTING)
    if kind == 1:
        return rnd.randint(-(1 << 63), (1 << 64) - 1)
    if kind == 2:
        return struct.unpack("<d", rnd.randbytes(8))[0]  # any double, NaNs included
    if kind == 3:
        return "".join(chr(rnd.randrange(0x20, 0x250)) for _ in range(rnd.randrange(12)))
    if kind == 4:
        return rnd.randbytes(rnd.randrange(0, 2 * 1081 + 3))
    return rnd.randrange(-5, 2000)


def _object(rnd: random.Random, keys: list[str], depth: int = 0) -> object:
    # Top level: a map half the time, since anything else stops at the first check.
    kind = (3 if rnd.random() < 0.5 else rnd.randrange(4)) if depth == 0 else rnd.randrange(4)
    kind = kind if depth < 4 else 0
    if kind <= 1:
        return _leaf(rnd)
    if kind == 2:
        return [_object(rnd, keys, depth + 1) for _ in range(rnd.randrange(6))]
    return {
        (rnd.choice(keys) if rnd.random() < 0.7 else str(_leaf(rnd))[:12]): _object(
            rnd, keys, depth + 1
        )
        for _ in range(rnd.randrange(8))
    }


def _random_bytes(rnd: random.Random) -> bytes:
    data = rnd.randbytes(rnd.randrange(0, 600))
    if data and rnd.random() < 0.5:
        # Start like a msgpack map half the time, so the unpacker gets past the first byte.
        data = bytes([rnd.choice([0x80 + rnd.randrange(16), 0xDE, 0xDF])]) + data[1:]
    return data


def _mutate(rnd: random.Random, payload: bytes) -> bytes:
    data = bytearray(payload)
    for _ in range(rnd.randint(1, 4)):
        if not data:
            break
        i = rnd.randrange(len(data))
        op = rnd.randrange(5)
        if op == 0:
            data[i] ^= 1 << rnd.randrange(8)
        elif op == 1:
            data[i] = rnd.randrange(256)
        elif op == 2:
            data[i:i] = rnd.randbytes(rnd.randint(1, 4))
        elif op == 3:
            del data[i : i + rnd.randint(1, 4)]
        else:
            del data[i:]
    return bytes(data)


def _edit_fields(rnd: random.Random, body: dict[str, Any], keys: list[str]) -> bytes:
    body = {k: (dict(v) if isinstance(v, dict) else v) for k, v in body.items()}
    for _ in range(rnd.randint(1, 3)):
        key = rnd.choice(keys)
        target = body
        if key.startswith("odom."):
            odom = body.get("odom")
            if not isinstance(odom, dict):
                continue
            target, key = odom, key.removeprefix("odom.")
        if rnd.random() < 0.2:
            target.pop(key, None)
        else:
            target[key] = _object(rnd, keys, depth=2)
    return _pack(body)


def _pack(obj: object) -> bytes:
    packed = msgpack.packb(obj, use_bin_type=True)
    assert isinstance(packed, bytes)
    return packed


def make_payload(
    family: str, seed: int, valid: list[bytes], bodies: list[dict[str, Any]], keys: list[str]
) -> bytes:
    rnd = random.Random(seed)
    if family == "bytes":
        return _random_bytes(rnd)
    if family == "object":
        return _pack(_object(rnd, keys))
    if family == "mutated":
        return _mutate(rnd, rnd.choice(valid))
    return _edit_fields(rnd, rnd.choice(bodies), keys)


cases = st.tuples(st.sampled_from(FAMILIES), st.integers(0, (1 << 64) - 1))


# ---------------------------------------------------------------------------------------------
# The property


def _run_fuzz(
    valid: list[bytes],
    bodies: list[dict[str, Any]],
    keys: list[str],
    decode: Callable[[bytes], Scan | Pose],
    encode: Callable[[Any], bytes],
) -> Counter[str]:
    seen: Counter[str] = Counter()

    @FUZZ_SETTINGS
    @given(cases)
    def check(case: tuple[str, int]) -> None:
        family, seed = case
        payload = make_payload(family, seed, valid, bodies, keys)
        note(f"payload = {payload.hex()}")
        seen[family] += 1
        try:
            message = decode(payload)
        except DecodeError as err:
            seen["rejected"] += 1
            seen[f"reason:{err.reason}"] += 1
            return
        seen["accepted"] += 1
        # Whatever decodes must encode again, to a payload that decodes to the same message.
        assert decode(encode(message)) == message

    check()
    return seen


@pytest.mark.timeout(300)
def test_fuzz_decode_scan() -> None:
    seen = _run_fuzz(SCAN_PAYLOADS, SCAN_BODIES, SCAN_KEYS, decode_scan, encode_scan)
    _check_volume(seen)


@pytest.mark.timeout(300)
def test_fuzz_decode_pose() -> None:
    seen = _run_fuzz(POSE_PAYLOADS, POSE_BODIES, POSE_KEYS, decode_pose, encode_pose)
    _check_volume(seen)


def _check_volume(seen: Counter[str]) -> None:
    total = sum(seen[f] for f in FAMILIES)
    assert total >= EXAMPLES_PER_DECODER, seen
    for family in FAMILIES:
        assert seen[family] >= EXAMPLES_PER_DECODER // 10, seen
    # Some mutants must still decode, or the fuzzer is not reaching the field validators;
    # and the rejections must come from the validators too, not only from the unpacker.
    assert seen["accepted"] > 0, seen
    assert seen["reason:wrong_type"] > 0, seen
    assert seen["reason:malformed_msgpack"] > 0, seen
    # "invalid" is the decoders' safety net for exceptions that escaped the explicit checks.
    assert seen["reason:invalid"] == 0, seen


# ---------------------------------------------------------------------------------------------
# The geometry property: a payload is accepted exactly when its declared geometry agrees with
# its arrays, and what is accepted has the declared shape. "Raises only DecodeError" and "round
# trips" both hold for a decoder that believes the arrays and ignores `beam_count`; this does not.

GEOMETRY_SETTINGS = settings(max_examples=2000, deadline=None, derandomize=True, database=None)
_WIDTH = {"u16_mm": 2, "f32_m": 4}


def _geometry_valid(g: dict[str, Any]) -> bool:
    """The contract of docs/wire-format.md, restated independently of `clients.wire`."""
    bc = g["beam_count"]
    return (
        1 <= bc <= MAX_BEAMS
        and g["angle_increment_rad"] > 0.0
        and abs(g["angle_min_rad"]) <= 2 * math.pi
        and g["angle_increment_rad"] * (bc - 1) <= 2 * math.pi + 1e-6
        and 0.0 <= g["range_min_m"] < g["range_max_m"]
        and g["ranges_len"] == _WIDTH[g["ranges_encoding"]] * bc
        and (g["intensities_len"] is None or g["intensities_len"] == 4 * bc)
    )


@st.composite
def geometries(draw: st.DrawFn) -> dict[str, Any]:
    """Declared geometry and array sizes; each part agrees most of the time, so that whole
    payloads that agree are common too, and disagreements sit near agreement (off by a beam,
    a byte, the other encoding's width), where a lax decoder goes wrong."""
    encoding = draw(st.sampled_from(["u16_mm", "f32_m"]))
    if draw(st.integers(0, 7)):
        beam_count = draw(st.integers(1, 1500))
    else:
        beam_count = draw(st.sampled_from([0, -1, MAX_BEAMS + 1]))
    width = _WIDTH[encoding]
    agree = max(beam_count, 0) * width
    if draw(st.booleans()):
        ranges_len = agree
    else:
        ranges_len = draw(
            st.one_of(
                st.integers(max(0, agree - 2 * width), agree + 2 * width),
                st.integers(0, 6000),
                st.just(max(beam_count, 0) * (6 - width)),  # the other encoding's width
            )
        )
    intensities_len = draw(
        st.sampled_from([None, None, 4 * max(beam_count, 0), 4 * max(beam_count, 0)])
        | st.integers(max(0, 4 * beam_count - 8), 4 * max(beam_count, 0) + 8)
    )
    return {
        "beam_count": beam_count,
        "ranges_encoding": encoding,
        "ranges_len": ranges_len,
        "intensities_len": intensities_len,
        "angle_min_rad": draw(st.sampled_from([-2.4, -0.5, 0.0, 2 * math.pi, -2 * math.pi - 1e-3])),
        # 2π/1000: beams past 1,001 span more than a revolution.
        "angle_increment_rad": draw(
            st.sampled_from([0.001, 0.002, 2 * math.pi / 1000, 0.0043, 0.0, -1e-3])
        ),
        "range_min_m": draw(st.sampled_from([0.0, 0.1, 30.0])),
        "range_max_m": draw(st.sampled_from([30.0, 0.1, 60.0])),
    }


def _geometry_payload(g: dict[str, Any]) -> bytes:
    body = dict(SCAN_BODIES[0])
    body.pop("intensities", None)
    body.pop("odom", None)
    for key in ("beam_count", "ranges_encoding", "angle_min_rad", "angle_increment_rad"):
        body[key] = g[key]
    body["range_min_m"], body["range_max_m"] = g["range_min_m"], g["range_max_m"]
    # Ranges of whole millimetres (valid in both encodings), intensities 0..1.
    rng = np.random.default_rng(g["ranges_len"])
    if g["ranges_encoding"] == "u16_mm":
        raw = rng.integers(0, 30_000, g["ranges_len"] // 2 + 1).astype("<u2").tobytes()
    else:
        raw = (rng.integers(0, 30_000, g["ranges_len"] // 4 + 1) / 1000).astype("<f4").tobytes()
    body["ranges"] = raw[: g["ranges_len"]]
    if g["intensities_len"] is not None:
        inten = rng.random(g["intensities_len"] // 4 + 1).astype("<f4").tobytes()
        body["intensities"] = inten[: g["intensities_len"]]
    return _pack(body)


def _check_geometry(g: dict[str, Any]) -> str:
    """Decode the payload of `g`; assert the property; return the outcome."""
    payload = _geometry_payload(g)
    note(f"geometry = {g}")
    if not _geometry_valid(g):
        with pytest.raises(DecodeError) as err:
            decode_scan(payload)
        assert err.value.reason in {"beam_count_mismatch", "bad_geometry", "out_of_range"}
        return err.value.reason
    scan = decode_scan(payload)
    assert scan.beam_count == g["beam_count"]
    assert scan.ranges_m.shape == (g["beam_count"],)
    assert scan.angles_rad().shape == (g["beam_count"],)
    if g["intensities_len"] is None:
        assert scan.intensities is None
    else:
        assert scan.intensities is not None
        assert scan.intensities.shape == (g["beam_count"],)
    assert (scan.angle_min_rad, scan.angle_increment_rad) == (
        g["angle_min_rad"],
        g["angle_increment_rad"],
    )
    assert (scan.range_min_m, scan.range_max_m) == (g["range_min_m"], g["range_max_m"])
    assert decode_scan(encode_scan(scan)) == scan
    return "accepted"


@pytest.mark.timeout(120)
def test_declared_geometry_must_agree_with_the_arrays() -> None:
    seen: Counter[str] = Counter()

    @GEOMETRY_SETTINGS
    @given(geometries())
    def check(g: dict[str, Any]) -> None:
        seen[_check_geometry(g)] += 1

    check()
    # The strategy reaches accepted payloads and every kind of rejection.
    for outcome in ("accepted", "beam_count_mismatch", "bad_geometry", "out_of_range"):
        assert seen[outcome] >= 50, seen
