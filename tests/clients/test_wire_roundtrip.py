"""The wire contract: round trips, and strict decoding of every kind of malformed input."""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np
import pytest

from clients.wire import (
    ALL_POSE_FLAGS,
    DEFAULT_MAX_PAYLOAD_BYTES,
    MAX_BEAMS,
    DecodeError,
    EncodeError,
    InvalidRobotIdError,
    OdometryPose,
    Pose,
    PoseFlag,
    RangesEncoding,
    Scan,
    WireError,
    decode_pose,
    decode_scan,
    encode_pose,
    encode_scan,
)

UTM30LX_INCREMENT_RAD = math.radians(0.25)


def make_scan(
    beams: int = 1081,
    *,
    encoding: RangesEncoding = "u16_mm",
    intensities: bool = False,
    odom: bool = False,
    robot_id: str = "amr-07",
    seed: int = 0,
) -> Scan:
    rng = np.random.default_rng(seed)
    # Whole millimetres, which both encodings carry exactly (f32 after the cast below).
    ranges_m = rng.integers(0, 30_000, beams).astype(np.float64) / 1000.0
    if encoding == "f32_m":
        ranges_m = ranges_m.astype(np.float32).astype(np.float64)
    increment = UTM30LX_INCREMENT_RAD if beams > 1 else 0.01
    return Scan(
        robot_id=robot_id,
        seq=int(rng.integers(0, 1 << 40)),
        sensor_stamp_ns=123_456_000_000,
        host_stamp_ns=1_700_000_000_123_456_789,
        angle_min_rad=-increment * (beams - 1) / 2,
        angle_increment_rad=increment,
        range_min_m=0.1,
        range_max_m=30.0,
        ranges_m=ranges_m,
        intensities=rng.random(beams).astype(np.float32) * 5000 if intensities else None,
        odom=OdometryPose(1.5, -2.25, 0.75, 1_700_000_000_100_000_000) if odom else None,
        ranges_encoding=encoding,
    )


def make_pose(flags: PoseFlag = PoseFlag.NONE, quality: float = 0.8) -> Pose:
    return Pose(
        session_id="s-0001",
        robot_id="amr-07",
        seq=42,
        stamp_ns=1_700_000_000_123_456_789,
        x_m=12.5,
        y_m=-3.25,
        theta_rad=-1.5,
        quality=quality,
        flags=flags,
    )


def body_of(payload: bytes) -> dict[str, Any]:
    body = msgpack.unpackb(payload, raw=False)
    assert isinstance(body, dict)
    return body


def pack(obj: object) -> bytes:
    packed = msgpack.packb(obj, use_bin_type=True)
    assert isinstance(packed, bytes)
    return packed


def scan_body(**kwargs: Any) -> dict[str, Any]:
    return body_of(encode_scan(make_scan(**kwargs)))


def pose_body() -> dict[str, Any]:
    return body_of(encode_pose(make_pose()))


def reason_of_scan(body: object) -> str:
    with pytest.raises(DecodeError) as info:
        decode_scan(pack(body))
    return info.value.reason


def reason_of_pose(body: object) -> str:
    with pytest.raises(DecodeError) as info:
        decode_pose(pack(body))
    return info.value.reason


# ---------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize("beams", [1, 3, 181, 681, 1081])
@pytest.mark.parametrize("encoding", ["u16_mm", "f32_m"])
@pytest.mark.parametrize("intensities", [False, True], ids=["no-int", "int"])
@pytest.mark.parametrize("odom", [False, True], ids=["no-odom", "odom"])
def test_scan_round_trip(
    beams: int, encoding: RangesEncoding, intensities: bool, odom: bool
) -> None:
    scan = make_scan(beams, encoding=encoding, intensities=intensities, odom=odom)
    decoded = decode_scan(encode_scan(scan))
    assert decoded == scan
    assert decoded.beam_count == beams
    assert decoded.ranges_m.dtype == np.float64
    assert (decoded.intensities is None) == (not intensities)
    assert (decoded.odom is None) == (not odom)
    np.testing.assert_allclose(decoded.angles_rad(), scan.angles_rad())
    # Re-encoding the decoded scan gives the same bytes: the format is canonical.
    assert encode_scan(decoded) == encode_scan(scan)


def test_scan_round_trip_accepts_bytearray_and_memoryview() -> None:
    payload = encode_scan(make_scan(181))
    assert decode_scan(bytearray(payload)) == decode_scan(memoryview(payload))


def test_scan_round_trip_numpy_integer_fields() -> None:
    # numpy ints are not msgpack-serialisable; the encoder must coerce them.
    scan = make_scan(3)
    scan = Scan(
        **{f: getattr(scan, f) for f in scan.__dataclass_fields__ if f != "seq"},
        seq=np.int64(7),  # type: ignore[arg-type]
    )
    assert decode_scan(encode_scan(scan)).seq == 7


def test_u16_mm_is_lossy_in_documented_ways() -> None:
    ranges = np.array([np.nan, np.inf, -1.0, 0.0, 0.0004, 0.0006, 1.2344, 70.0])
    scan = Scan("r1", 0, 0, 0, 0.0, 0.01, 0.0, 80.0, ranges)
    decoded = decode_scan(encode_scan(scan))
    np.testing.assert_array_equal(decoded.ranges_m, [0.0, 0.0, 0.0, 0.0, 0.0, 0.001, 1.234, 65.535])


def test_f32_m_keeps_nan_inf_and_negative() -> None:
    ranges = np.array([np.nan, np.inf, -1.0, 0.0, 1.5])
    scan = Scan("r1", 0, 0, 0, 0.0, 0.01, 0.0, 80.0, ranges, ranges_encoding="f32_m")
    decoded = decode_scan(encode_scan(scan))
    np.testing.assert_array_equal(decoded.ranges_m, ranges)
    assert decoded.valid_mask().tolist() == [False, False, False, False, True]


@pytest.mark.parametrize("flag", list(PoseFlag))
@pytest.mark.parametrize("quality", [0.0, 0.5, 1.0])
def test_pose_round_trip_each_flag(flag: PoseFlag, quality: float) -> None:
    pose = make_pose(flag, quality)
    decoded = decode_pose(encode_pose(pose))
    assert decoded == pose
    assert isinstance(decoded.flags, PoseFlag)


def test_pose_round_trip_all_flags() -> None:
    pose = make_pose(PoseFlag(ALL_POSE_FLAGS))
    decoded = decode_pose(encode_pose(pose))
    assert decoded == pose
    assert decoded.is_ambiguous
    assert decoded.is_degenerate


def test_pose_flag_bits_are_fixed() -> None:
    # These values are part of the wire format (docs/wire-format.md); never renumber.
    assert {f.name: int(f) for f in PoseFlag if f} == {
        "DEGENERATE": 1,
        "NO_DOMINANT_WALL": 2,
        "AMBIGUOUS_X": 4,
        "AMBIGUOUS_Y": 8,
        "NON_MANHATTAN": 16,
        "HEADING_SWITCH": 32,
        "ODOMETRY_PRIOR": 64,
        "RELOCALISED": 128,
    }


def test_encoded_key_sets() -> None:
    assert set(scan_body(intensities=True, odom=True)) == {
        "v",
        "type",
        "robot_id",
        "seq",
        "sensor_stamp_ns",
        "host_stamp_ns",
        "angle_min_rad",
        "angle_increment_rad",
        "beam_count",
        "range_min_m",
        "range_max_m",
        "ranges_encoding",
        "ranges",
        "intensities",
        "odom",
    }
    assert set(scan_body()) == set(scan_body(intensities=True, odom=True)) - {
        "intensities",
        "odom",
    }
    assert set(pose_body()) == {
        "v",
        "type",
        "session_id",
        "robot_id",
        "seq",
        "stamp_ns",
        "x_m",
        "y_m",
        "theta_rad",
        "quality",
        "flags",
    }


# ---------------------------------------------------------------------------------------------
# Invalid single beams are data, not errors


@pytest.mark.parametrize("encoding", ["u16_mm", "f32_m"])
def test_invalid_beams_are_allowed_and_masked(encoding: RangesEncoding) -> None:
    body = scan_body(beams=6, encoding=encoding)
    if encoding == "u16_mm":
        # 0 = no return; 5 mm and 19 mm are below range_min (UTM-30LX error codes); 31 m too far
        body["ranges"] = np.array([0, 5, 19, 1000, 31_000, 30_000], "<u2").tobytes()
        expected = [False, False, False, True, False, True]
    else:
        body["ranges"] = np.array([np.nan, 0.0, 0.05, 1.0, np.inf, -2.0], "<f4").tobytes()
        expected = [False, False, False, True, False, False]
    scan = decode_scan(pack(body))
    assert scan.valid_mask().tolist() == expected


def test_zero_is_no_return_even_with_zero_range_min() -> None:
    body = scan_body(beams=3)
    body["range_min_m"] = 0.0
    body["ranges"] = np.array([0, 1, 2], "<u2").tobytes()
    assert decode_scan(pack(body)).valid_mask().tolist() == [False, True, True]


# ---------------------------------------------------------------------------------------------
# Version, type, top level


@pytest.mark.parametrize(
    ("version", "reason"),
    [
        (None, "unsupported_version"),
        (0, "unsupported_version"),
        (2, "unsupported_version"),
        (-1, "unsupported_version"),
        ("1", "unsupported_version"),
        (1.0, "unsupported_version"),
        (True, "unsupported_version"),
        (b"\x01", "unsupported_version"),
    ],
)
def test_wrong_version(version: object, reason: str) -> None:
    body = scan_body(beams=3)
    body["v"] = version
    assert reason_of_scan(body) == reason
    pbody = pose_body()
    pbody["v"] = version
    assert reason_of_pose(pbody) == reason


def test_missing_version() -> None:
    body = scan_body(beams=3)
    del body["v"]
    assert reason_of_scan(body) == "missing_version"
    pbody = pose_body()
    del pbody["v"]
    assert reason_of_pose(pbody) == "missing_version"


def test_message_type_is_checked() -> None:
    with pytest.raises(DecodeError) as info:
        decode_pose(encode_scan(make_scan(3)))
    assert info.value.reason == "wrong_type"
    with pytest.raises(DecodeError) as info:
        decode_scan(encode_pose(make_pose()))
    assert info.value.reason == "wrong_type"
    body = scan_body(beams=3)
    del body["type"]
    assert reason_of_scan(body) == "wrong_type"


@pytest.mark.parametrize("top", [[1, 2], 1, -5, 1.5, "scan", b"scan", None, True, []], ids=repr)
def test_non_map_top_level(top: object) -> None:
    assert reason_of_scan(top) == "not_a_map"
    assert reason_of_pose(top) == "not_a_map"


def test_not_bytes_and_empty() -> None:
    for decode in (decode_scan, decode_pose):
        with pytest.raises(DecodeError) as info:
            decode("a string")  # type: ignore[arg-type]
        assert info.value.reason == "not_bytes"
        with pytest.raises(DecodeError) as info:
            decode(b"")
        assert info.value.reason == "empty"


def test_trailing_bytes_and_truncation_are_malformed() -> None:
    payload = encode_scan(make_scan(3))
    for bad in (payload + b"\x00", payload[:-1], b"\xc1"):
        with pytest.raises(DecodeError) as info:
            decode_scan(bad)
        assert info.value.reason == "malformed_msgpack"


def test_non_string_map_keys() -> None:
    # Integer keys are refused by the unpacker; bin keys simply do not name any field.
    assert reason_of_scan({1: 1}) == "malformed_msgpack"
    assert reason_of_scan({b"v": 1, b"type": b"scan"}) == "missing_version"


def test_extra_unknown_fields_are_ignored() -> None:
    # Forward compatibility: a newer minor revision may add fields (docs/wire-format.md).
    body = scan_body(beams=181, odom=True)
    body["future_field"] = {"nested": [1, 2.5, "x", None, b"\x00"]}
    body["odom"]["covariance"] = [0.1, 0.0, 0.1]
    assert decode_scan(pack(body)) == make_scan(181, odom=True)
    pbody = pose_body()
    pbody["covariance"] = [1.0] * 9
    assert decode_pose(pack(pbody)) == make_pose()


def test_nil_optional_fields_mean_absent() -> None:
    body = scan_body(beams=3, intensities=True, odom=True)
    body["intensities"] = None
    body["odom"] = None
    decoded = decode_scan(pack(body))
    assert decoded.intensities is None
    assert decoded.odom is None


# ---------------------------------------------------------------------------------------------
# Missing fields and wrong types, field by field

SCAN_REQUIRED = [
    "robot_id",
    "seq",
    "sensor_stamp_ns",
    "host_stamp_ns",
    "angle_min_rad",
    "angle_increment_rad",
    "beam_count",
    "range_min_m",
    "range_max_m",
    "ranges_encoding",
    "ranges",
]
POSE_REQUIRED = [
    "session_id",
    "robot_id",
    "seq",
    "stamp_ns",
    "x_m",
    "y_m",
    "theta_rad",
    "quality",
    "flags",
]
ODOM_REQUIRED = ["x_m", "y_m", "theta_rad", "stamp_ns"]

INT_FIELDS = {"seq", "sensor_stamp_ns", "host_stamp_ns", "beam_count", "stamp_ns", "flags"}
FLOAT_FIELDS = {
    "angle_min_rad",
    "angle_increment_rad",
    "range_min_m",
    "range_max_m",
    "x_m",
    "y_m",
    "theta_rad",
    "quality",
}
STR_FIELDS = {"robot_id", "session_id", "ranges_encoding"}
BIN_FIELDS = {"ranges", "intensities"}

_ANY_WRONG: list[object] = [[1], {"a": 1}, True, False]


def wrong_values(field: str) -> list[object]:
    if field in INT_FIELDS:
        return [*_ANY_WRONG, None, 1.0, 2.5, "1", b"\x01"]
    if field in FLOAT_FIELDS:
        return [*_ANY_WRONG, None, "1.0", b"\x00\x00\x80\x3f"]
    if field in STR_FIELDS:
        return [*_ANY_WRONG, None, 7, 1.5, b"amr-07"]
    if field in BIN_FIELDS:
        # nil is "absent" for the optional intensities, so it is not wrong there
        return [*_ANY_WRONG, 7, 1.5, "\x00\x00\x00\x00" * 3] + ([None] if field == "ranges" else [])
    if field == "odom":
        return [*_ANY_WRONG[:1], 7, 1.5, "odom", b"odom"]
    raise AssertionError(field)


@pytest.mark.parametrize("field", SCAN_REQUIRED)
def test_scan_missing_field(field: str) -> None:
    body = scan_body(beams=3)
    del body[field]
    assert reason_of_scan(body) == "missing_field"


@pytest.mark.parametrize("field", ODOM_REQUIRED)
def test_scan_odom_missing_field(field: str) -> None:
    body = scan_body(beams=3, odom=True)
    del body["odom"][field]
    assert reason_of_scan(body) == "missing_field"


@pytest.mark.parametrize("field", POSE_REQUIRED)
def test_pose_missing_field(field: str) -> None:
    body = pose_body()
    del body[field]
    assert reason_of_pose(body) == "missing_field"


@pytest.mark.parametrize("field", [*SCAN_REQUIRED, "intensities", "odom"])
def test_scan_wrong_types(field: str) -> None:
    for value in wrong_values(field):
        body = scan_body(beams=3, intensities=True, odom=True)
        body[field] = value
        assert reason_of_scan(body) == "wrong_type", (field, value)


@pytest.mark.parametrize("field", ODOM_REQUIRED)
def test_scan_odom_wrong_types(field: str) -> None:
    for value in wrong_values(field):
        body = scan_body(beams=3, odom=True)
        body["odom"][field] = value
        assert reason_of_scan(body) == "wrong_type", (field, value)


@pytest.mark.parametrize("field", POSE_REQUIRED)
def test_pose_wrong_types(field: str) -> None:
    for value in wrong_values(field):
        body = pose_body()
        body[field] = value
        assert reason_of_pose(body) == "wrong_type", (field, value)


@pytest.mark.parametrize(
    ("field", "value"),
    [("angle_min_rad", 0), ("angle_increment_rad", 1), ("range_min_m", 0), ("range_max_m", 30)],
)
def test_integers_are_accepted_for_scan_float_fields(field: str, value: int) -> None:
    # Some msgpack encoders write whole numbers as ints; the contract accepts that.
    body = scan_body(beams=3)
    body[field] = value
    decoded = decode_scan(pack(body))
    assert type(getattr(decoded, field)) is float
    assert getattr(decoded, field) == value


@pytest.mark.parametrize("field", ["x_m", "y_m", "theta_rad", "quality"])
def test_integers_are_accepted_for_pose_and_odom_float_fields(field: str) -> None:
    body = pose_body()
    body[field] = 1
    assert type(getattr(decode_pose(pack(body)), field)) is float
    if field != "quality":
        sbody = scan_body(beams=3, odom=True)
        sbody["odom"][field] = -2
        odom = decode_scan(pack(sbody)).odom
        assert odom is not None
        assert getattr(odom, field) == -2.0


# ---------------------------------------------------------------------------------------------
# Beam count and geometry


@pytest.mark.parametrize("encoding", ["u16_mm", "f32_m"])
@pytest.mark.parametrize("delta", [-1, 1, 100])
def test_beam_count_disagrees_with_ranges(encoding: RangesEncoding, delta: int) -> None:
    body = scan_body(beams=181, encoding=encoding)
    body["beam_count"] = 181 + delta
    assert reason_of_scan(body) == "beam_count_mismatch"


@pytest.mark.parametrize("nbytes", [0, 1, 361, 363, 724])
def test_odd_ranges_lengths(nbytes: int) -> None:
    body = scan_body(beams=181)
    body["ranges"] = b"\x01" * nbytes
    assert reason_of_scan(body) == "beam_count_mismatch"


def test_intensities_length_disagrees() -> None:
    body = scan_body(beams=181, intensities=True)
    body["intensities"] = body["intensities"][:-4]
    assert reason_of_scan(body) == "beam_count_mismatch"


@pytest.mark.parametrize("beam_count", [0, -1, MAX_BEAMS + 1, 1 << 40])
def test_beam_count_out_of_range(beam_count: int) -> None:
    body = scan_body(beams=3)
    body["beam_count"] = beam_count
    assert reason_of_scan(body) == "out_of_range"


def test_max_beams_is_accepted() -> None:
    body = scan_body(beams=3)
    body["beam_count"] = MAX_BEAMS
    body["angle_increment_rad"] = 2 * math.pi / MAX_BEAMS
    body["ranges_encoding"] = "f32_m"
    body["ranges"] = np.ones(MAX_BEAMS, "<f4").tobytes()
    body["intensities"] = np.ones(MAX_BEAMS, "<f4").tobytes()
    assert decode_scan(pack(body)).beam_count == MAX_BEAMS


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(
    "field", ["angle_min_rad", "angle_increment_rad", "range_min_m", "range_max_m"]
)
def test_non_finite_geometry(field: str, bad: float) -> None:
    body = scan_body(beams=3)
    body[field] = bad
    assert reason_of_scan(body) == "non_finite"


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("field", ["x_m", "y_m", "theta_rad"])
def test_non_finite_odometry_and_pose(field: str, bad: float) -> None:
    body = scan_body(beams=3, odom=True)
    body["odom"][field] = bad
    assert reason_of_scan(body) == "non_finite"
    pbody = pose_body()
    pbody[field] = bad
    assert reason_of_pose(pbody) == "non_finite"


@pytest.mark.parametrize("increment", [0.0, -0.0, -1e-9, -UTM30LX_INCREMENT_RAD, 0, -1])
def test_non_positive_increment(increment: float) -> None:
    body = scan_body(beams=3)
    body["angle_increment_rad"] = increment
    assert reason_of_scan(body) == "bad_geometry"


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("angle_min_rad", 7.0),
        ("angle_min_rad", -7.0),
        ("angle_increment_rad", 1.0),  # 2 gaps of 1 rad are fine ...
        ("range_min_m", -0.1),
        ("range_min_m", 30.0),
        ("range_max_m", 0.1),
        ("range_max_m", 0.05),
    ],
)
def test_bad_geometry(field: str, value: float) -> None:
    body = scan_body(beams=181 if field == "angle_increment_rad" else 3)
    body[field] = value  # ... but 180 gaps of 1 rad exceed one revolution
    assert reason_of_scan(body) == "bad_geometry"


def test_full_revolution_is_accepted() -> None:
    body = scan_body(beams=3)
    body["angle_increment_rad"] = math.pi
    body["angle_min_rad"] = -math.pi
    assert decode_scan(pack(body)).angles_rad()[-1] == pytest.approx(math.pi)


@pytest.mark.parametrize("encoding", ["u16", "f64_m", "", "U16_MM"])
def test_unknown_ranges_encoding(encoding: str) -> None:
    body = scan_body(beams=3)
    body["ranges_encoding"] = encoding
    assert reason_of_scan(body) == "bad_encoding"


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("seq", -1),
        ("sensor_stamp_ns", (1 << 63)),
        ("host_stamp_ns", (1 << 64) - 1),
    ],
)
def test_integer_ranges(field: str, value: int) -> None:
    body = scan_body(beams=3)
    body[field] = value
    assert reason_of_scan(body) == "out_of_range"


def test_integer_extremes_are_accepted() -> None:
    body = scan_body(beams=3)
    body["seq"] = (1 << 64) - 1
    body["sensor_stamp_ns"] = -(1 << 63)
    body["host_stamp_ns"] = (1 << 63) - 1
    scan = decode_scan(pack(body))
    assert scan.seq == (1 << 64) - 1


# ---------------------------------------------------------------------------------------------
# Pose ranges


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("quality", -0.01, "out_of_range"),
        ("quality", 1.01, "out_of_range"),
        ("quality", math.nan, "non_finite"),
        ("flags", -1, "out_of_range"),
        ("flags", ALL_POSE_FLAGS + 1, "out_of_range"),
        ("flags", 1 << 40, "out_of_range"),
        ("seq", -1, "out_of_range"),
        ("stamp_ns", 1 << 63, "out_of_range"),
        ("session_id", "", "bad_session_id"),
        ("session_id", "a/b", "bad_session_id"),
        ("session_id", "a b", "bad_session_id"),
        ("session_id", "x" * 65, "bad_session_id"),
    ],
)
def test_pose_out_of_range(field: str, value: object, reason: str) -> None:
    body = pose_body()
    body[field] = value
    assert reason_of_pose(body) == reason


# ---------------------------------------------------------------------------------------------
# Robot ids

BAD_ROBOT_IDS = [
    "",
    "a/b",
    "robots/*",
    "*",
    "**",
    "a*",
    "$*",
    "a$b",
    "a b",
    " a",
    "a\t",
    "a\n",
    "a?b",
    "a#b",
    "-a",
    ".a",
    "_a",
    "..",
    "a" * 65,
    "ä",
    "a\x00",
    "@a",
]


@pytest.mark.parametrize("robot_id", BAD_ROBOT_IDS, ids=repr)
def test_bad_robot_id_is_refused_by_decoders(robot_id: str) -> None:
    body = scan_body(beams=3)
    body["robot_id"] = robot_id
    assert reason_of_scan(body) == "bad_robot_id"
    pbody = pose_body()
    pbody["robot_id"] = robot_id
    assert reason_of_pose(pbody) == "bad_robot_id"


@pytest.mark.parametrize("robot_id", BAD_ROBOT_IDS, ids=repr)
def test_bad_robot_id_is_refused_by_encoders(robot_id: str) -> None:
    with pytest.raises(InvalidRobotIdError):
        encode_scan(make_scan(3, robot_id=robot_id))
    pose = make_pose()
    with pytest.raises(InvalidRobotIdError):
        encode_pose(
            Pose(robot_id, robot_id, 0, 0, 0.0, 0.0, 0.0, 0.5)  # also a bad session id
            if robot_id
            else Pose(pose.session_id, robot_id, 0, 0, 0.0, 0.0, 0.0, 0.5)
        )


@pytest.mark.parametrize("robot_id", ["a", "A9", "amr-07", "warehouse-a.unit_3", "x" * 64])
def test_good_robot_ids(robot_id: str) -> None:
    assert decode_scan(encode_scan(make_scan(3, robot_id=robot_id))).robot_id == robot_id


# ---------------------------------------------------------------------------------------------
# Size caps and nesting bombs


def test_payload_over_default_cap() -> None:
    body = scan_body(beams=3)
    body["padding"] = b"\x00" * DEFAULT_MAX_PAYLOAD_BYTES
    payload = pack(body)
    assert len(payload) > DEFAULT_MAX_PAYLOAD_BYTES
    with pytest.raises(DecodeError) as info:
        decode_scan(payload)
    assert info.value.reason == "too_large"
    with pytest.raises(DecodeError) as info:
        decode_pose(b"\x00" * (DEFAULT_MAX_PAYLOAD_BYTES + 1))
    assert info.value.reason == "too_large"


def test_configurable_cap() -> None:
    payload = encode_scan(make_scan(181))
    assert decode_scan(payload, max_payload_bytes=len(payload)) == make_scan(181)
    with pytest.raises(DecodeError) as info:
        decode_scan(payload, max_payload_bytes=len(payload) - 1)
    assert info.value.reason == "too_large"
    pose_payload = encode_pose(make_pose())
    with pytest.raises(DecodeError) as info:
        decode_pose(pose_payload, max_payload_bytes=16)
    assert info.value.reason == "too_large"


def test_larger_cap_allows_larger_payloads() -> None:
    body = scan_body(beams=3)
    body["padding"] = b"\x00" * DEFAULT_MAX_PAYLOAD_BYTES
    assert decode_scan(pack(body), max_payload_bytes=4 * DEFAULT_MAX_PAYLOAD_BYTES).beam_count == 3


@pytest.mark.parametrize(
    "bomb",
    [
        b"\x91" * 100_000 + b"\xc0",  # [[[[...nil...]]]]
        b"\x81\xa1k" * 100_000 + b"\xc0",  # {"k": {"k": ...}}
        b"\xdd\xff\xff\xff\xff",  # array32 claiming 4 billion items
        b"\xdf\xff\xff\xff\xff",  # map32 claiming 4 billion pairs
        b"\xc6\xff\xff\xff\xff",  # bin32 claiming 4 GiB
        b"\xdb\xff\xff\xff\xff",  # str32 claiming 4 GiB
        b"\xc9\x00\x00\x00\x10\x01" + b"\x00" * 16,  # ext32
    ],
    ids=["deep-array", "deep-map", "array32", "map32", "bin32", "str32", "ext"],
)
def test_nesting_and_allocation_bombs(bomb: bytes) -> None:
    for decode in (decode_scan, decode_pose):
        with pytest.raises(DecodeError) as info:
            decode(bomb)
        assert info.value.reason == "malformed_msgpack"


def test_nesting_bomb_inside_a_valid_message() -> None:
    body = scan_body(beams=3)
    body["x"] = None
    payload = pack(body)
    # Replace the trailing nil of field "x" with 100k levels of nesting.
    bomb = payload[:-1] + b"\x91" * 100_000 + b"\xc0"
    with pytest.raises(DecodeError) as info:
        decode_scan(bomb)
    assert info.value.reason == "malformed_msgpack"


def test_wide_array_in_unknown_field_hits_the_array_limit() -> None:
    body = scan_body(beams=3)
    body["x"] = [0] * 5000
    with pytest.raises(DecodeError) as info:
        decode_scan(pack(body))
    assert info.value.reason == "malformed_msgpack"


@pytest.mark.parametrize(
    ("limit", "fits", "too_big"),
    [
        # A map of 64 entries unpacks, 65 do not (the scan's own fields are 13 of them).
        ("map", lambda b: {**b, **{f"x{i}": 0 for i in range(64 - len(b))}}, None),
        ("array", lambda b: {**b, "x": [0] * 1024}, lambda b: {**b, "x": [0] * 1025}),
        ("str", lambda b: {**b, "x": "a" * 4096}, lambda b: {**b, "x": "a" * 4097}),
    ],
)
def test_unpacker_limits_are_exact(limit: str, fits: Any, too_big: Any) -> None:
    """The limits that bound allocation before validation: at the limit accepted, one past it
    rejected as malformed (a limit lifted would let a small payload allocate a lot)."""
    body = scan_body(beams=3)
    assert decode_scan(pack(fits(body))).beam_count == 3
    big = too_big(body) if too_big else {**fits(body), "x_last": 0}
    with pytest.raises(DecodeError) as info:
        decode_scan(pack(big))
    assert info.value.reason == "malformed_msgpack", limit


# ---------------------------------------------------------------------------------------------
# The encoder refuses what the decoder would reject


def test_encoder_refuses_what_decoders_reject() -> None:
    scan = make_scan(3)
    fields = {f: getattr(scan, f) for f in scan.__dataclass_fields__}
    for change in (
        {"angle_increment_rad": 0.0},
        {"angle_min_rad": math.nan},
        {"range_max_m": 0.0},
        {"ranges_m": np.zeros(0)},
        {"seq": -1},
        {"ranges_encoding": "f64"},
        {"intensities": np.zeros(2, np.float32)},
    ):
        with pytest.raises(EncodeError):
            encode_scan(Scan(**{**fields, **change}))
    pose = make_pose()
    pfields = {f: getattr(pose, f) for f in pose.__dataclass_fields__}
    for change in ({"quality": 2.0}, {"x_m": math.inf}, {"session_id": "a/b"}):
        with pytest.raises(EncodeError):
            encode_pose(Pose(**{**pfields, **change}))
    assert issubclass(EncodeError, WireError)
    assert issubclass(DecodeError, WireError)


def test_decode_error_carries_reason_and_detail() -> None:
    with pytest.raises(DecodeError) as info:
        decode_scan(b"\x93\x01\x02\x03")
    err = info.value
    assert err.reason == "not_a_map"
    assert "list" in err.detail
    assert str(err).startswith("not_a_map: ")
