"""The wire contract: `Scan` and `Pose` messages, encoded as msgpack maps.

Every process imports these definitions; `docs/wire-format.md` describes the same bytes for
implementers in other languages. Decoding is strict: anything malformed raises `DecodeError`
(a `WireError`) with a short machine-readable `reason`, never a bare `KeyError`/`TypeError`.
"""

from __future__ import annotations

import enum
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, Literal

import msgpack
import numpy as np
import numpy.typing as npt

SCHEMA_VERSION: Final = 1
DEFAULT_MAX_PAYLOAD_BYTES: Final = 1 << 20  # 1 MiB
MAX_BEAMS: Final = 65_536
ROBOT_ID_PATTERN: Final = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
SESSION_ID_PATTERN: Final = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
_U64_MAX: Final = (1 << 64) - 1
_I64_MIN: Final = -(1 << 63)
_I64_MAX: Final = (1 << 63) - 1

RangesEncoding = Literal["u16_mm", "f32_m"]
RANGES_ENCODINGS: Final[tuple[RangesEncoding, ...]] = ("u16_mm", "f32_m")


class WireError(Exception):
    """Base class of every error raised by the wire contract."""


class DecodeError(WireError):
    """A payload is not a valid message. `reason` is a short stable token for counters."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


class EncodeError(WireError, ValueError):
    """A message that violates the contract; encoding refuses what decoding would reject."""


class InvalidRobotIdError(WireError, ValueError):
    """A robot id that cannot be used inside a Zenoh key expression or a file name."""


class PoseFlag(enum.IntFlag):
    """Why a pose is less trustworthy than usual. Bit values are part of the wire format."""

    NONE = 0
    DEGENERATE = 1 << 0  # too few valid points to match at all; pose is the motion prediction
    NO_DOMINANT_WALL = 1 << 1  # heading histogram has no clear peak
    AMBIGUOUS_X = 1 << 2  # translation along the x axis is unconstrained (e.g. corridor along x)
    AMBIGUOUS_Y = 1 << 3  # translation along the y axis is unconstrained
    NON_MANHATTAN = 1 << 4  # major structure follows no known wall family (first walls, wings)
    HEADING_SWITCH = 1 << 5  # the major wall changed to a perpendicular one (the ±45° rule)
    ODOMETRY_PRIOR = 1 << 6  # odometry was used to predict the motion
    RELOCALISED = 1 << 7  # estimate jumped after a period of low quality


ALL_POSE_FLAGS: Final = int(
    PoseFlag.DEGENERATE
    | PoseFlag.NO_DOMINANT_WALL
    | PoseFlag.AMBIGUOUS_X
    | PoseFlag.AMBIGUOUS_Y
    | PoseFlag.NON_MANHATTAN
    | PoseFlag.HEADING_SWITCH
    | PoseFlag.ODOMETRY_PRIOR
    | PoseFlag.RELOCALISED
)


def is_valid_robot_id(robot_id: object) -> bool:
    """True when `robot_id` is 1-64 chars of [A-Za-z0-9_.-], not starting with `.`, `-` or `_`."""
    return isinstance(robot_id, str) and ROBOT_ID_PATTERN.fullmatch(robot_id) is not None


def check_robot_id(robot_id: str) -> str:
    """Return `robot_id` unchanged, or raise `InvalidRobotIdError` saying why it is unsafe."""
    if not is_valid_robot_id(robot_id):
        raise InvalidRobotIdError(
            f"invalid robot id {robot_id!r}: use 1-64 characters from [A-Za-z0-9_.-], "
            "starting with a letter or digit (no '/', '*', '$', '?', '#' or spaces)"
        )
    return robot_id


@dataclass(frozen=True, slots=True)
class OdometryPose:
    """Odometry pose of the robot in its own `odom` frame (REP-105), with its stamp."""

    x_m: float
    y_m: float
    theta_rad: float
    stamp_ns: int


@dataclass(frozen=True, slots=True, eq=False)
class Scan:
    """One 2D laser scan as published by a sensor agent.

    `ranges_m` is `(beam_count,)` float64 in metres; invalid beams (no return, error codes,
    below `range_min_m`) are kept as they arrived and reported by `valid_mask()`.
    Beam `i` points at `angle_min_rad + i * angle_increment_rad` in the laser frame
    (x forward, y left, counter-clockwise).
    """

    robot_id: str
    seq: int
    sensor_stamp_ns: int  # sensor clock, unwrapped (Hokuyo: 24-bit ms counter * 1e6)
    host_stamp_ns: int  # host wall clock (Unix epoch) when the scan was received
    angle_min_rad: float
    angle_increment_rad: float
    range_min_m: float
    range_max_m: float
    ranges_m: npt.NDArray[np.float64]
    intensities: npt.NDArray[np.float32] | None = None
    odom: OdometryPose | None = None
    ranges_encoding: RangesEncoding = "u16_mm"
    version: int = SCHEMA_VERSION

    @property
    def beam_count(self) -> int:
        return int(self.ranges_m.shape[0])

    @property
    def stamp_ns(self) -> int:
        """The time the scan is referenced to by the estimator and the poses: host time."""
        return self.host_stamp_ns

    def angles_rad(self) -> npt.NDArray[np.float64]:
        """(beam_count,) float64 beam angles in the laser frame."""
        return self.angle_min_rad + self.angle_increment_rad * np.arange(
            self.beam_count, dtype=np.float64
        )

    def valid_mask(self) -> npt.NDArray[np.bool_]:
        """(beam_count,) True where the beam is a usable return within the range limits.

        Zero means "no return" in both encodings, whatever `range_min_m` says.
        """
        r = self.ranges_m
        with np.errstate(invalid="ignore"):
            return np.isfinite(r) & (r > 0.0) & (r >= self.range_min_m) & (r <= self.range_max_m)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Scan):
            return NotImplemented
        return (
            self.robot_id == other.robot_id
            and self.seq == other.seq
            and self.sensor_stamp_ns == other.sensor_stamp_ns
            and self.host_stamp_ns == other.host_stamp_ns
            and self.angle_min_rad == other.angle_min_rad
            and self.angle_increment_rad == other.angle_increment_rad
            and self.range_min_m == other.range_min_m
            and self.range_max_m == other.range_max_m
            and self.ranges_encoding == other.ranges_encoding
            and self.version == other.version
            and self.odom == other.odom
            and np.array_equal(self.ranges_m, other.ranges_m, equal_nan=True)
            and _optional_array_equal(self.intensities, other.intensities)
        )

    __hash__ = None  # type: ignore[assignment]


def _optional_array_equal(
    a: npt.NDArray[np.float32] | None, b: npt.NDArray[np.float32] | None
) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(np.array_equal(a, b, equal_nan=True))


@dataclass(frozen=True, slots=True)
class Pose:
    """The estimated pose of a robot in the map frame of its mapping session."""

    session_id: str
    robot_id: str
    seq: int
    stamp_ns: int
    x_m: float
    y_m: float
    theta_rad: float
    quality: float  # 0 = no confidence, 1 = fully constrained match
    flags: PoseFlag = PoseFlag.NONE
    version: int = SCHEMA_VERSION
    # Row-major 3×3 covariance of (x_m, y_m, theta_rad), relative to the latest keyframe, map
    # axes (docs/wire-format.md). Optional: older publishers send none, older decoders skip it.
    covariance: tuple[float, ...] | None = None

    @property
    def is_ambiguous(self) -> bool:
        return bool(self.flags & (PoseFlag.AMBIGUOUS_X | PoseFlag.AMBIGUOUS_Y))

    @property
    def is_degenerate(self) -> bool:
        return bool(self.flags & (PoseFlag.DEGENERATE | PoseFlag.NO_DOMINANT_WALL))


# ---------------------------------------------------------------------------------------------
# Encoding


def encode_scan(scan: Scan) -> bytes:
    """Encode a scan; raises `WireError` if the scan itself violates the contract.

    Every payload this returns decodes with `decode_scan` (geometry, counts and types are
    checked by the same code), so a bad scan fails at its source, not at every receiver.
    """
    check_robot_id(scan.robot_id)
    if scan.ranges_encoding == "u16_mm":
        ranges_bytes = _ranges_to_u16_mm(scan.ranges_m).tobytes()
    elif scan.ranges_encoding == "f32_m":
        ranges_bytes = np.asarray(scan.ranges_m, dtype="<f4").tobytes()
    else:
        raise EncodeError(f"unknown ranges encoding {scan.ranges_encoding!r}")
    body: dict[str, Any] = {
        "v": scan.version,
        "type": "scan",
        "robot_id": scan.robot_id,
        "seq": int(scan.seq),  # int(): numpy integers are not msgpack-serialisable
        "sensor_stamp_ns": int(scan.sensor_stamp_ns),
        "host_stamp_ns": int(scan.host_stamp_ns),
        "angle_min_rad": float(scan.angle_min_rad),
        "angle_increment_rad": float(scan.angle_increment_rad),
        "beam_count": scan.beam_count,
        "range_min_m": float(scan.range_min_m),
        "range_max_m": float(scan.range_max_m),
        "ranges_encoding": scan.ranges_encoding,
        "ranges": ranges_bytes,
    }
    if scan.intensities is not None:
        if scan.intensities.shape != (scan.beam_count,):
            raise EncodeError("intensities must have one value per beam")
        body["intensities"] = np.asarray(scan.intensities, dtype="<f4").tobytes()
    if scan.odom is not None:
        body["odom"] = {
            "x_m": float(scan.odom.x_m),
            "y_m": float(scan.odom.y_m),
            "theta_rad": float(scan.odom.theta_rad),
            "stamp_ns": int(scan.odom.stamp_ns),
        }
    _check_encodable(_scan_from_body, body)
    return _pack(body)


def encode_pose(pose: Pose) -> bytes:
    """Encode a pose; raises `WireError` if `decode_pose` would reject the result."""
    check_robot_id(pose.robot_id)
    body: dict[str, Any] = {
        "v": pose.version,
        "type": "pose",
        "session_id": pose.session_id,
        "robot_id": pose.robot_id,
        "seq": int(pose.seq),
        "stamp_ns": int(pose.stamp_ns),
        "x_m": float(pose.x_m),
        "y_m": float(pose.y_m),
        "theta_rad": float(pose.theta_rad),
        "quality": float(pose.quality),
        "flags": int(pose.flags),
    }
    if pose.covariance is not None:
        body["cov"] = [float(v) for v in pose.covariance]
    _check_encodable(_pose_from_body, body)
    return _pack(body)


def _check_encodable(validate: Callable[[dict[str, Any]], object], body: dict[str, Any]) -> None:
    try:
        validate(body)
    except DecodeError as err:
        raise EncodeError(f"message would not decode: {err}") from None


def _pack(body: dict[str, Any]) -> bytes:
    packed = msgpack.packb(body, use_bin_type=True, use_single_float=False)
    assert isinstance(packed, bytes)
    return packed


def _ranges_to_u16_mm(ranges_m: npt.NDArray[np.float64]) -> npt.NDArray[np.uint16]:
    """Metres to millimetres; NaN/inf/negative become 0 (invalid), and >65.535 m saturates."""
    r = np.asarray(ranges_m, dtype=np.float64)
    mm = np.where(np.isfinite(r) & (r > 0.0), np.rint(r * 1000.0), 0.0)
    return np.clip(mm, 0, 65535).astype("<u2")


# ---------------------------------------------------------------------------------------------
# Decoding


def decode_scan(
    payload: bytes | bytearray | memoryview, *, max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES
) -> Scan:
    """Decode and validate a scan. Raises `DecodeError` on anything malformed."""
    body = _unpack(payload, max_payload_bytes, "scan")
    try:
        return _scan_from_body(body)
    except DecodeError:
        raise
    except Exception as err:  # defence in depth: nothing else may leak out
        raise DecodeError("invalid", f"{type(err).__name__}: {err}") from err


def decode_pose(
    payload: bytes | bytearray | memoryview, *, max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES
) -> Pose:
    """Decode and validate a pose. Raises `DecodeError` on anything malformed."""
    body = _unpack(payload, max_payload_bytes, "pose")
    try:
        return _pose_from_body(body)
    except DecodeError:
        raise
    except Exception as err:
        raise DecodeError("invalid", f"{type(err).__name__}: {err}") from err


def _unpack(payload: object, max_payload_bytes: int, expected_type: str) -> dict[str, Any]:
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise DecodeError("not_bytes", f"payload is {type(payload).__name__}, not bytes")
    size = len(payload)
    if size > max_payload_bytes:
        raise DecodeError("too_large", f"payload is {size} bytes, cap is {max_payload_bytes}")
    if size == 0:
        raise DecodeError("empty", "payload is empty")
    try:
        # Limits bound allocation before any validation (the size itself was checked above;
        # `unpackb` takes no `max_buffer_size`). Nesting depth is bounded by msgpack's own
        # stack limit, which raises `StackError` rather than recursing.
        body = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            use_list=True,
            max_str_len=4096,
            max_bin_len=max_payload_bytes,
            max_array_len=1024,
            max_map_len=64,
            max_ext_len=0,
        )
    except Exception as err:  # msgpack raises ValueError, ExtraData, StackError, ...
        raise DecodeError("malformed_msgpack", f"{type(err).__name__}: {err}") from err
    if not isinstance(body, dict):
        raise DecodeError("not_a_map", f"top level is {type(body).__name__}, not a map")
    if "v" not in body:
        raise DecodeError("missing_version", "no schema version field 'v'")
    version = body["v"]
    if type(version) is not int or version != SCHEMA_VERSION:
        raise DecodeError(
            "unsupported_version", f"schema version {version!r}, expected {SCHEMA_VERSION}"
        )
    msg_type = body.get("type")
    if msg_type != expected_type:
        raise DecodeError("wrong_type", f"message type {msg_type!r}, expected {expected_type!r}")
    return body


def _field(body: dict[str, Any], name: str) -> Any:
    try:
        return body[name]
    except KeyError:
        raise DecodeError("missing_field", f"missing field {name!r}") from None


def _int(
    body: dict[str, Any], name: str, lo: int = _I64_MIN, hi: int = _I64_MAX, field_of: str = ""
) -> int:
    value = _field(body, name)
    label = f"{field_of}{name}"
    if type(value) is not int:
        raise DecodeError("wrong_type", f"{label} is {type(value).__name__}, expected int")
    if not lo <= value <= hi:
        raise DecodeError("out_of_range", f"{label}={value} outside [{lo}, {hi}]")
    return value


def _finite_float(body: dict[str, Any], name: str, field_of: str = "") -> float:
    value = _field(body, name)
    label = f"{field_of}{name}"
    if type(value) is not float and type(value) is not int:
        raise DecodeError("wrong_type", f"{label} is {type(value).__name__}, expected float")
    result = float(value)
    if not math.isfinite(result):
        raise DecodeError("non_finite", f"{label} is {result}")
    return result


def _str(body: dict[str, Any], name: str) -> str:
    value = _field(body, name)
    if type(value) is not str:
        raise DecodeError("wrong_type", f"{name} is {type(value).__name__}, expected str")
    return value


def _bytes(body: dict[str, Any], name: str) -> bytes:
    value = _field(body, name)
    if type(value) is not bytes:
        raise DecodeError("wrong_type", f"{name} is {type(value).__name__}, expected bin")
    return value


def _robot_id(body: dict[str, Any]) -> str:
    robot_id = _str(body, "robot_id")
    if not is_valid_robot_id(robot_id):
        raise DecodeError("bad_robot_id", f"robot_id {robot_id[:80]!r} is not a safe identifier")
    return robot_id


def _scan_from_body(body: dict[str, Any]) -> Scan:
    robot_id = _robot_id(body)
    seq = _int(body, "seq", 0, _U64_MAX)
    sensor_stamp_ns = _int(body, "sensor_stamp_ns")
    host_stamp_ns = _int(body, "host_stamp_ns")
    angle_min_rad = _finite_float(body, "angle_min_rad")
    angle_increment_rad = _finite_float(body, "angle_increment_rad")
    if not angle_increment_rad > 0.0:
        raise DecodeError("bad_geometry", f"angle_increment_rad={angle_increment_rad} must be > 0")
    if abs(angle_min_rad) > 2 * math.pi:
        raise DecodeError("bad_geometry", f"angle_min_rad={angle_min_rad} outside ±2π")
    beam_count = _int(body, "beam_count", 1, MAX_BEAMS)
    if angle_increment_rad * (beam_count - 1) > 2 * math.pi + 1e-6:
        raise DecodeError("bad_geometry", "beams span more than one revolution")
    range_min_m = _finite_float(body, "range_min_m")
    range_max_m = _finite_float(body, "range_max_m")
    if not 0.0 <= range_min_m < range_max_m:
        raise DecodeError(
            "bad_geometry", f"need 0 <= range_min_m < range_max_m, got {range_min_m}, {range_max_m}"
        )
    encoding = _str(body, "ranges_encoding")
    raw = _bytes(body, "ranges")
    if encoding == "u16_mm":
        if len(raw) != 2 * beam_count:
            raise DecodeError(
                "beam_count_mismatch", f"{len(raw)} range bytes for {beam_count} u16 beams"
            )
        ranges_m = np.frombuffer(raw, dtype="<u2").astype(np.float64) / 1000.0
    elif encoding == "f32_m":
        if len(raw) != 4 * beam_count:
            raise DecodeError(
                "beam_count_mismatch", f"{len(raw)} range bytes for {beam_count} f32 beams"
            )
        with np.errstate(invalid="ignore"):  # signalling NaNs from the wire stay NaN
            ranges_m = np.frombuffer(raw, dtype="<f4").astype(np.float64)
    else:
        raise DecodeError("bad_encoding", f"ranges_encoding {encoding!r} not in {RANGES_ENCODINGS}")
    intensities: npt.NDArray[np.float32] | None = None
    if body.get("intensities") is not None:
        raw_i = _bytes(body, "intensities")
        if len(raw_i) != 4 * beam_count:
            raise DecodeError(
                "beam_count_mismatch", f"{len(raw_i)} intensity bytes for {beam_count} beams"
            )
        intensities = np.frombuffer(raw_i, dtype="<f4").astype(np.float32)
    odom: OdometryPose | None = None
    raw_odom = body.get("odom")
    if raw_odom is not None:
        if not isinstance(raw_odom, dict):
            raise DecodeError("wrong_type", f"odom is {type(raw_odom).__name__}, expected map")
        odom = OdometryPose(
            x_m=_finite_float(raw_odom, "x_m", "odom."),
            y_m=_finite_float(raw_odom, "y_m", "odom."),
            theta_rad=_finite_float(raw_odom, "theta_rad", "odom."),
            stamp_ns=_int(raw_odom, "stamp_ns", field_of="odom."),
        )
    return Scan(
        robot_id=robot_id,
        seq=seq,
        sensor_stamp_ns=sensor_stamp_ns,
        host_stamp_ns=host_stamp_ns,
        angle_min_rad=angle_min_rad,
        angle_increment_rad=angle_increment_rad,
        range_min_m=range_min_m,
        range_max_m=range_max_m,
        ranges_m=ranges_m,
        intensities=intensities,
        odom=odom,
        ranges_encoding=encoding,  # type: ignore[arg-type]  # checked against RANGES_ENCODINGS
    )


def _pose_from_body(body: dict[str, Any]) -> Pose:
    session_id = _str(body, "session_id")
    if SESSION_ID_PATTERN.fullmatch(session_id) is None:
        raise DecodeError("bad_session_id", f"session_id {session_id[:80]!r} is not safe")
    quality = _finite_float(body, "quality")
    if not 0.0 <= quality <= 1.0:
        raise DecodeError("out_of_range", f"quality={quality} outside [0, 1]")
    flags = _int(body, "flags", 0, ALL_POSE_FLAGS)
    if flags & ~ALL_POSE_FLAGS:
        raise DecodeError("out_of_range", f"unknown flag bits in {flags:#x}")
    return Pose(
        session_id=session_id,
        robot_id=_robot_id(body),
        seq=_int(body, "seq", 0, _U64_MAX),
        stamp_ns=_int(body, "stamp_ns"),
        x_m=_finite_float(body, "x_m"),
        y_m=_finite_float(body, "y_m"),
        theta_rad=_finite_float(body, "theta_rad"),
        quality=quality,
        flags=PoseFlag(flags),
        covariance=_covariance(body),
    )


def _covariance(body: dict[str, Any]) -> tuple[float, ...] | None:
    """The optional `cov`: 9 finite floats, a symmetric 3×3 with a non-negative diagonal."""
    if "cov" not in body:
        return None
    cov = body["cov"]
    if not isinstance(cov, list) or len(cov) != 9:
        raise DecodeError("bad_covariance", "cov must be a list of 9 numbers (row-major 3x3)")
    if not all(type(v) in (int, float) and math.isfinite(v) for v in cov):
        raise DecodeError("bad_covariance", "cov values must be finite numbers")
    values = tuple(float(v) for v in cov)
    if min(values[0], values[4], values[8]) < 0.0:
        raise DecodeError("bad_covariance", "cov has a negative variance")
    if any(abs(values[i] - values[j]) > 1e-9 * (1.0 + abs(values[i])) for i, j in _SYMMETRIC):
        raise DecodeError("bad_covariance", "cov is not symmetric")
    return values


_SYMMETRIC = ((1, 3), (2, 6), (5, 7))


__all__ = [
    "ALL_POSE_FLAGS",
    "DEFAULT_MAX_PAYLOAD_BYTES",
    "RANGES_ENCODINGS",
    "SCHEMA_VERSION",
    "DecodeError",
    "EncodeError",
    "InvalidRobotIdError",
    "OdometryPose",
    "Pose",
    "PoseFlag",
    "RangesEncoding",
    "Scan",
    "WireError",
    "check_robot_id",
    "decode_pose",
    "decode_scan",
    "encode_pose",
    "encode_scan",
    "is_valid_robot_id",
]
