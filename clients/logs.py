"""Read laser logs as wire `Scan`s: ROS 1 bags, ROS 2 bags, MCAP files and `.mrec` recordings.

Bags are read with `rosbags`: ROS 2 bag folders with either storage (SQLite or MCAP, the
default since Iron), and a bare `.mcap` file with ROS 2 (CDR) messages, as written by rosbag2,
rosbags or `mapping-service export --mcap`. A ROS 1 bag that `rosbags` refuses (damaged index
records, a missing index after a crash, a truncated file) is read again by a tolerant reader
that walks the records one by one, the way `rosbag reindex` would, and resynchronises after
damage.

Each `sensor_msgs/LaserScan` becomes a `Scan` whose `sensor_stamp_ns` and `host_stamp_ns` are
both the message header stamp: trajectories and the relation metric key on that stamp. Ranges
keep their exact float32 values (`ranges_encoding="f32_m"`). With `use_odom`, the robot's
`nav_msgs/Odometry` pose interpolated at the scan stamp is attached as `Scan.odom`.
"""

from __future__ import annotations

import bisect
import bz2
import dataclasses
import importlib
import logging
import math
import mmap
import struct
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from clients.recording import MAGIC as MREC_MAGIC
from clients.recording import RecordingError, iter_raw_records, read_messages
from clients.wire import OdometryPose, Scan

log = logging.getLogger(__name__)

LogKind = Literal["ros1", "ros2", "mcap", "mrec"]

ROS1_MAGIC: Final = b"#ROSBAG V2.0\n"
MCAP_MAGIC: Final = b"\x89MCAP0\r\n"
LASER_SCAN_TYPE: Final = "sensor_msgs/msg/LaserScan"
ODOMETRY_TYPE: Final = "nav_msgs/msg/Odometry"

# ROS 1 bag record op codes (http://wiki.ros.org/Bags/Format/2.0).
OP_MSG_DATA: Final = 0x02
OP_BAG_HEADER: Final = 0x03
OP_INDEX_DATA: Final = 0x04
OP_CHUNK: Final = 0x05
OP_CHUNK_INFO: Final = 0x06
OP_CONNECTION: Final = 0x07
_REQUIRED_FIELDS: Final[dict[int, tuple[str, ...]]] = {
    OP_MSG_DATA: ("conn", "time"),
    OP_BAG_HEADER: ("index_pos", "conn_count", "chunk_count"),
    OP_INDEX_DATA: ("ver", "conn", "count"),
    OP_CHUNK: ("compression", "size"),
    OP_CHUNK_INFO: ("ver", "chunk_pos", "start_time", "end_time", "count"),
    OP_CONNECTION: ("conn", "topic"),
}
_MAX_HEADER_BYTES: Final = 1 << 16
# How far before an `op=` field a record can start when resynchronising after damage.
_RESYNC_LOOKBACK_BYTES: Final = 512

# Odometry attachment: how long a scan may wait for an odometry message stamped after it, and
# how far from the nearest odometry a scan may be and still get that pose.
_ODOM_LOOKAHEAD_NS: Final = 2_000_000_000
_ODOM_MAX_PENDING: Final = 200
_ODOM_MAX_GAP_NS: Final = 500_000_000
_ODOM_HISTORY: Final = 4096


class LogError(Exception):
    """Base class of every error raised by this module."""


class LogReadError(LogError):
    """The log cannot be read (missing, not a supported format, damaged beyond use)."""


@dataclass(frozen=True, slots=True)
class LogInfo:
    """What `probe_log` found in a log."""

    path: str
    kind: LogKind
    scan_count: int
    has_odom: bool
    duration_s: float
    topics: dict[str, str] = field(default_factory=dict)  # topic -> message type
    tolerant: bool = False  # True when the tolerant ROS 1 reader had to be used


# ---------------------------------------------------------------------------------------------
# Public API


def detect_log_kind(path: str | Path) -> LogKind:
    """`"ros1"`, `"ros2"` (a bag folder, or a file in one), `"mcap"` (a bare MCAP file) or
    `"mrec"` from the file's first bytes; `LogReadError` otherwise."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").exists():
            return "ros2"
        raise LogReadError(f"{p}: a directory without metadata.yaml is not a ROS 2 bag")
    try:
        with open(p, "rb") as f:
            head = f.read(len(ROS1_MAGIC))
    except FileNotFoundError:
        raise LogReadError(f"{p}: no such file") from None
    except OSError as err:
        raise LogReadError(f"{p}: cannot open: {err.strerror or err}") from None
    if head.startswith(MREC_MAGIC):
        return "mrec"
    if head == ROS1_MAGIC:
        return "ros1"
    if p.suffix in (".db3", ".mcap") and (p.parent / "metadata.yaml").exists():
        return "ros2"
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    raise LogReadError(f"{p}: not a ROS 1 bag, ROS 2 bag, MCAP file or .mrec recording")


def iter_log_scans(
    path: str | Path,
    *,
    scan_topic: str = "/scan",
    odom_topic: str = "/odom",
    use_odom: bool = True,
    robot_id: str = "replay",
) -> Iterator[Scan]:
    """Yield the log's scans in order. The kind is detected now; read errors raise on iteration.

    `.mrec` scans come back as recorded (their own robot id; odometry dropped unless
    `use_odom`). Every failure is a `LogError` with a one-line message.
    """
    p = Path(path)
    kind = detect_log_kind(p)
    if kind == "mrec":
        return _iter_mrec_scans(p, use_odom=use_odom)
    messages = _bag_messages(p, kind, scan_topic, odom_topic if use_odom else None)
    return _scans_from_messages(messages, robot_id=robot_id, use_odom=use_odom)


def count_log_scans(path: str | Path, *, scan_topic: str = "/scan") -> int:
    """Number of scans, cheaply where possible (bag index counts); for progress-bar totals."""
    p = Path(path)
    kind = detect_log_kind(p)
    if kind == "mrec":
        return _count_mrec_scans(p)
    try:
        with _open_any_reader(p, kind) as reader:
            return sum(c.msgcount for c in reader.connections if c.topic == scan_topic)
    except LogError:
        raise
    except Exception as err:
        if kind != "ros1":
            raise LogReadError(f"{p}: cannot read the bag: {_reason(err)}") from None
        log.debug(
            "%s: rosbags refused the bag (%s); counting with the tolerant reader", p, _reason(err)
        )
    return sum(1 for _ in _Ros1Walker(p).messages({scan_topic}, deserialize=False))


def probe_log(path: str | Path, *, scan_topic: str = "/scan", odom_topic: str = "/odom") -> LogInfo:
    """Kind, scan count, odometry presence, duration and topics of a log."""
    p = Path(path)
    kind = detect_log_kind(p)
    if kind == "mrec":
        return _probe_mrec(p)
    try:
        with _open_any_reader(p, kind) as reader:
            topics = {c.topic: c.msgtype for c in reader.connections}
            counts: dict[str, int] = {}
            for c in reader.connections:
                counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
            return LogInfo(
                path=str(p),
                kind=kind,
                scan_count=counts.get(scan_topic, 0),
                has_odom=counts.get(odom_topic, 0) > 0,
                duration_s=float(reader.duration) / 1e9 if counts else 0.0,
                topics=topics,
            )
    except LogError:
        raise
    except Exception as err:
        if kind != "ros1":
            raise LogReadError(f"{p}: cannot read the bag: {_reason(err)}") from None
        log.info(
            "%s: rosbags refused the bag (%s); probing with the tolerant reader", p, _reason(err)
        )
    walker = _Ros1Walker(p)
    scan_count = 0
    odom_count = 0
    first_ns: int | None = None
    last_ns = 0
    for msg in walker.messages(deserialize=False):
        first_ns = msg.time_ns if first_ns is None else min(first_ns, msg.time_ns)
        last_ns = max(last_ns, msg.time_ns)
        scan_count += msg.topic == scan_topic
        odom_count += msg.topic == odom_topic
    if not walker.topics:
        raise LogReadError(f"{p}: no readable connections or messages in the bag")
    return LogInfo(
        path=str(p),
        kind=kind,
        scan_count=scan_count,
        has_odom=odom_count > 0,
        duration_s=(last_ns - first_ns) / 1e9 if first_ns is not None else 0.0,
        topics=dict(walker.topics),
        tolerant=True,
    )


# ---------------------------------------------------------------------------------------------
# .mrec


def _iter_mrec_scans(path: Path, *, use_odom: bool) -> Iterator[Scan]:
    try:
        for message in read_messages(path):
            if isinstance(message, Scan):
                yield message if use_odom or message.odom is None else _without_odom(message)
    except RecordingError as err:
        raise LogReadError(str(err)) from None
    except OSError as err:
        raise LogReadError(f"{path}: {err.strerror or err}") from None


def _without_odom(scan: Scan) -> Scan:
    return dataclasses.replace(scan, odom=None)


def _count_mrec_scans(path: Path) -> int:
    try:
        return sum(1 for record in iter_raw_records(path) if record.kind == "scan")
    except RecordingError as err:
        raise LogReadError(str(err)) from None


def _probe_mrec(path: Path) -> LogInfo:
    count = 0
    has_odom = False
    first_ns: int | None = None
    last_ns = 0
    robots: set[str] = set()
    for scan in _iter_mrec_scans(path, use_odom=True):
        count += 1
        has_odom = has_odom or scan.odom is not None
        first_ns = scan.stamp_ns if first_ns is None else min(first_ns, scan.stamp_ns)
        last_ns = max(last_ns, scan.stamp_ns)
        robots.add(scan.robot_id)
    return LogInfo(
        path=str(path),
        kind="mrec",
        scan_count=count,
        has_odom=has_odom,
        duration_s=(last_ns - first_ns) / 1e9 if first_ns is not None else 0.0,
        topics={f"{robot}/scan": "clients.wire.Scan" for robot in sorted(robots)},
    )


# ---------------------------------------------------------------------------------------------
# Bags: a common stream of (topic role, stamp, message) items, from rosbags or the walker


@dataclass(frozen=True, slots=True)
class _BagMessage:
    role: Literal["scan", "odom"]
    time_ns: int  # bag receive time; the header stamp is inside `msg`
    msg: Any


def _open_any_reader(path: Path, kind: LogKind) -> Any:
    store = Stores.ROS1_NOETIC if kind == "ros1" else Stores.LATEST
    # Not opened here: `with reader:` opens it, and so does `_bag_messages`.
    return AnyReader([path], default_typestore=get_typestore(store))


def _bag_messages(
    path: Path, kind: LogKind, scan_topic: str, odom_topic: str | None
) -> Iterator[_BagMessage]:
    last_time_ns = -1
    try:
        reader = _open_any_reader(path, kind)
        reader.open()
    except Exception as err:
        if kind != "ros1":
            raise LogReadError(f"{path}: cannot read the bag: {_reason(err)}") from None
        log.warning(
            "%s: rosbags refused the bag (%s); reading it with the tolerant reader",
            path,
            _reason(err),
        )
    else:
        try:
            roles = _check_topics(
                path,
                {c.topic: c.msgtype for c in reader.connections},
                scan_topic,
                odom_topic,
            )
            connections = [c for c in reader.connections if c.topic in roles]
            for conn, time_ns, raw in reader.messages(connections=connections):
                msg = reader.deserialize(raw, conn.msgtype)
                yield _BagMessage(roles[conn.topic], int(time_ns), msg)
                last_time_ns = max(last_time_ns, int(time_ns))
            return
        except LogError:
            raise
        except Exception as err:
            if kind != "ros1":
                raise LogReadError(f"{path}: bag read failed: {_reason(err)}") from None
            # Resume after the last message delivered, in file order, with the walker.
            log.warning(
                "%s: rosbags failed mid-bag (%s); continuing with the tolerant reader",
                path,
                _reason(err),
            )
        finally:
            reader.close()
    yield from _tolerant_bag_messages(path, scan_topic, odom_topic, after_time_ns=last_time_ns)


def _tolerant_bag_messages(
    path: Path, scan_topic: str, odom_topic: str | None, *, after_time_ns: int = -1
) -> Iterator[_BagMessage]:
    wanted = {scan_topic} if odom_topic is None else {scan_topic, odom_topic}
    walker = _Ros1Walker(path)
    roles: dict[str, Literal["scan", "odom"]] | None = None
    for msg in walker.messages(topics=wanted, deserialize=True):
        if roles is None or msg.topic not in roles:
            roles = _check_topics(path, walker.topics, scan_topic, odom_topic, strict=False)
        role = roles.get(msg.topic)
        if role is not None and msg.time_ns > after_time_ns:
            yield _BagMessage(role, msg.time_ns, msg.msg)
    if not walker.topics:
        raise LogReadError(f"{path}: no readable connections or messages in the bag")
    _check_topics(path, walker.topics, scan_topic, odom_topic)


def _check_topics(
    path: Path,
    topics: dict[str, str],
    scan_topic: str,
    odom_topic: str | None,
    *,
    strict: bool = True,
) -> dict[str, Literal["scan", "odom"]]:
    """Map topic -> role; with `strict`, a missing or mistyped scan topic is an error."""
    roles: dict[str, Literal["scan", "odom"]] = {}
    scan_type = topics.get(scan_topic)
    if scan_type is not None and _normalise_type(scan_type) == LASER_SCAN_TYPE:
        roles[scan_topic] = "scan"
    elif strict:
        if scan_type is None:
            have = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "no topics"
            raise LogReadError(f"{path}: no {scan_topic} topic; the bag has {have}")
        raise LogReadError(f"{path}: {scan_topic} is {scan_type}, not sensor_msgs/LaserScan")
    if odom_topic is not None and odom_topic in topics:
        if _normalise_type(topics[odom_topic]) == ODOMETRY_TYPE:
            roles[odom_topic] = "odom"
        elif strict:
            log.warning(
                "%s: %s is %s, not nav_msgs/Odometry; ignoring odometry",
                path,
                odom_topic,
                topics[odom_topic],
            )
    return roles


def _normalise_type(msgtype: str) -> str:
    """ROS 1 `pkg/Name` -> `pkg/msg/Name` as rosbags' typestores spell it."""
    parts = msgtype.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype


def _reason(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0]}" if text else type(err).__name__


# ---------------------------------------------------------------------------------------------
# Message conversion and odometry attachment


def _header_stamp_ns(msg: Any, fallback_ns: int) -> int:
    stamp = msg.header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    # Some drivers leave the header stamp at zero; the bag receive time is the best we have.
    return ns if ns > 0 else fallback_ns


def _scan_from_msg(msg: Any, stamp_ns: int, seq: int, robot_id: str) -> Scan | None:
    ranges32 = np.asarray(msg.ranges, dtype=np.float32)
    n = int(ranges32.shape[0])
    if n == 0:
        return None
    angle_min = float(msg.angle_min)
    increment = float(msg.angle_increment)
    intensities: np.ndarray[Any, np.dtype[np.float32]] | None = None
    raw_intensities = np.asarray(msg.intensities, dtype=np.float32)
    if raw_intensities.shape == (n,):
        intensities = raw_intensities
    if increment < 0.0:
        # A laser mounted upside down publishes clockwise beams; the wire contract is CCW.
        angle_min += increment * (n - 1)
        increment = -increment
        ranges32 = ranges32[::-1]
        intensities = None if intensities is None else intensities[::-1].copy()
    return Scan(
        robot_id=robot_id,
        seq=seq,
        sensor_stamp_ns=stamp_ns,
        host_stamp_ns=stamp_ns,
        angle_min_rad=angle_min,
        angle_increment_rad=increment,
        range_min_m=float(msg.range_min),
        range_max_m=float(msg.range_max),
        ranges_m=ranges32.astype(np.float64),
        intensities=intensities,
        ranges_encoding="f32_m",
    )


def _odom_from_msg(msg: Any) -> tuple[float, float, float]:
    p = msg.pose.pose.position
    q = msg.pose.pose.orientation
    yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
    return float(p.x), float(p.y), yaw


class _OdomTrack:
    """Odometry poses by stamp; interpolates x, y and the (unwrapped) heading."""

    def __init__(self) -> None:
        self._t: list[int] = []
        self._x: list[float] = []
        self._y: list[float] = []
        self._yaw: list[float] = []  # unwrapped along the stamp order
        self.latest_ns = -1

    def add(self, stamp_ns: int, x: float, y: float, yaw: float) -> None:
        i = bisect.bisect_right(self._t, stamp_ns)
        if i > 0 and self._t[i - 1] == stamp_ns:
            return  # duplicate stamp: keep the first
        ref = self._yaw[i - 1] if i > 0 else (self._yaw[0] if self._yaw else yaw)
        yaw_unwrapped = ref + _wrap(yaw - ref)
        self._t.insert(i, stamp_ns)
        self._x.insert(i, x)
        self._y.insert(i, y)
        self._yaw.insert(i, yaw_unwrapped)
        self.latest_ns = max(self.latest_ns, stamp_ns)
        if len(self._t) > 2 * _ODOM_HISTORY:
            del self._t[:_ODOM_HISTORY], self._x[:_ODOM_HISTORY]
            del self._y[:_ODOM_HISTORY], self._yaw[:_ODOM_HISTORY]

    def at(self, stamp_ns: int) -> OdometryPose | None:
        if not self._t:
            return None
        i = bisect.bisect_left(self._t, stamp_ns)
        if i < len(self._t) and self._t[i] == stamp_ns:
            return OdometryPose(self._x[i], self._y[i], _wrap(self._yaw[i]), stamp_ns)
        if 0 < i < len(self._t):
            t0, t1 = self._t[i - 1], self._t[i]
            w = (stamp_ns - t0) / (t1 - t0)
            return OdometryPose(
                self._x[i - 1] + w * (self._x[i] - self._x[i - 1]),
                self._y[i - 1] + w * (self._y[i] - self._y[i - 1]),
                _wrap(self._yaw[i - 1] + w * (self._yaw[i] - self._yaw[i - 1])),
                stamp_ns,
            )
        j = 0 if i == 0 else len(self._t) - 1  # outside the track: nearest, if close
        if abs(self._t[j] - stamp_ns) > _ODOM_MAX_GAP_NS:
            return None
        return OdometryPose(self._x[j], self._y[j], _wrap(self._yaw[j]), self._t[j])


def _wrap(theta_rad: float) -> float:
    return (theta_rad + math.pi) % (2.0 * math.pi) - math.pi


def _scans_from_messages(
    messages: Iterable[_BagMessage], *, robot_id: str, use_odom: bool
) -> Iterator[Scan]:
    track = _OdomTrack()
    pending: deque[Scan] = deque()
    seq = 0
    skipped = 0
    for item in messages:
        if item.role == "odom":
            stamp = _header_stamp_ns(item.msg, item.time_ns)
            track.add(stamp, *_odom_from_msg(item.msg))
        else:
            scan = _scan_from_msg(item.msg, _header_stamp_ns(item.msg, item.time_ns), seq, robot_id)
            if scan is None:
                skipped += 1
                continue
            seq += 1
            if not use_odom:
                yield scan
                continue
            pending.append(scan)
        # A scan waits for odometry stamped after it, so the pose can be interpolated.
        while pending and (
            track.latest_ns >= pending[0].stamp_ns
            or len(pending) > _ODOM_MAX_PENDING
            or item.time_ns - pending[0].stamp_ns > _ODOM_LOOKAHEAD_NS
        ):
            first = pending.popleft()
            yield dataclasses.replace(first, odom=track.at(first.stamp_ns))
    while pending:
        first = pending.popleft()
        yield dataclasses.replace(first, odom=track.at(first.stamp_ns))
    if skipped:
        log.warning("skipped %d scans without beams", skipped)


# ---------------------------------------------------------------------------------------------
# The tolerant ROS 1 reader


@dataclass(frozen=True, slots=True)
class _Record:
    op: int
    fields: dict[str, bytes]
    data_start: int
    data_end: int  # may exceed the buffer for a truncated last record

    @property
    def end(self) -> int:
        return self.data_end


@dataclass(frozen=True, slots=True)
class _RawMessage:
    topic: str
    msgtype: str
    time_ns: int
    msg: Any  # deserialised message, or the raw bytes when not deserialising


def _parse_fields(buf: bytes | mmap.mmap, start: int, end: int) -> dict[str, bytes] | None:
    fields: dict[str, bytes] = {}
    i = start
    while i < end:
        if i + 4 > end:
            return None
        (length,) = struct.unpack_from("<I", buf, i)
        i += 4
        if length == 0 or i + length > end:
            return None
        item = bytes(buf[i : i + length])
        i += length
        name, sep, value = item.partition(b"=")
        if not sep or not name or not name.isascii() or not name.decode().isidentifier():
            return None
        fields[name.decode()] = value
    return fields


def _parse_record(buf: bytes | mmap.mmap, pos: int, size: int) -> _Record | None:
    """The record at `pos`, or None when the bytes there are not a plausible record."""
    if pos + 4 > size:
        return None
    (header_len,) = struct.unpack_from("<I", buf, pos)
    if not 4 <= header_len <= _MAX_HEADER_BYTES or pos + 8 + header_len > size:
        return None
    fields = _parse_fields(buf, pos + 4, pos + 4 + header_len)
    if fields is None:
        return None
    op_raw = fields.get("op")
    if op_raw is None or len(op_raw) != 1 or op_raw[0] not in _REQUIRED_FIELDS:
        return None
    op = op_raw[0]
    if any(name not in fields for name in _REQUIRED_FIELDS[op]):
        return None
    (data_len,) = struct.unpack_from("<I", buf, pos + 4 + header_len)
    data_start = pos + 8 + header_len
    return _Record(op, fields, data_start, data_start + data_len)


def _u32(value: bytes) -> int:
    return int.from_bytes(value[:4], "little") if len(value) >= 4 else -1


def _time_ns(value: bytes) -> int:
    if len(value) != 8:
        return 0
    sec, nsec = struct.unpack("<II", value)
    return int(sec) * 1_000_000_000 + int(nsec)


class _Ros1Walker:
    """Walks a ROS 1 bag record by record, ignoring the index; resynchronises after damage."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.topics: dict[str, str] = {}
        self._conns: dict[int, tuple[str, str]] = {}  # conn id -> (topic, type)
        self._typestore: Any = None
        self.damage: list[str] = []

    def messages(
        self, topics: set[str] | None = None, *, deserialize: bool = True
    ) -> Iterator[_RawMessage]:
        try:
            with open(self.path, "rb") as f:
                try:
                    buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
                except ValueError:
                    raise LogReadError(f"{self.path}: empty file") from None
                try:
                    yield from self._walk(buf, topics, deserialize)
                finally:
                    buf.close()
        except OSError as err:
            raise LogReadError(f"{self.path}: {err.strerror or err}") from None

    def _walk(
        self, buf: mmap.mmap, topics: set[str] | None, deserialize: bool
    ) -> Iterator[_RawMessage]:
        size = len(buf)
        if buf[: len(ROS1_MAGIC)] != ROS1_MAGIC:
            raise LogReadError(f"{self.path}: not a ROS 1 bag (format 2.0)")
        pos = len(ROS1_MAGIC)
        while pos < size:
            rec = _parse_record(buf, pos, size)
            if rec is None:
                new_pos = _resync(buf, pos + 1, size)
                if new_pos is None:
                    self._damaged(f"unreadable bytes from {pos} to the end ({size - pos} bytes)")
                    return
                self._damaged(f"skipped {new_pos - pos} unreadable bytes at {pos}")
                pos = new_pos
                continue
            if rec.op == OP_INDEX_DATA:
                rec = _fix_index_record(buf, rec, size)
            if rec.data_end > size:
                if rec.op == OP_CHUNK:
                    yield from self._chunk(buf[rec.data_start : size], rec, topics, deserialize)
                self._damaged(f"file truncated inside a record at {pos}")
                return
            if rec.op == OP_CHUNK:
                yield from self._chunk(buf[rec.data_start : rec.data_end], rec, topics, deserialize)
            elif rec.op == OP_CONNECTION:
                self._connection(rec, buf[rec.data_start : rec.data_end])
            elif rec.op == OP_MSG_DATA:  # unchunked bags keep messages at the top level
                data = buf[rec.data_start : rec.data_end]
                msg = self._message(rec, data, topics, deserialize)
                if msg is not None:
                    yield msg
            pos = rec.end

    def _damaged(self, what: str) -> None:
        self.damage.append(what)
        log.warning("%s: %s", self.path, what)

    def _chunk(
        self, data: bytes, rec: _Record, topics: set[str] | None, deserialize: bool
    ) -> Iterator[_RawMessage]:
        compression = rec.fields["compression"].decode(errors="replace")
        expected = _u32(rec.fields["size"])
        try:
            if compression == "none":
                inner = data
            elif compression == "bz2":
                # A decompressor object returns what it can from a truncated stream.
                inner = bz2.BZ2Decompressor().decompress(data)
            elif compression == "lz4":
                inner = _lz4_decompress(data)
            else:
                self._damaged(f"chunk at {rec.data_start} has unknown compression {compression!r}")
                return
        except ImportError:
            self._damaged(f"chunk at {rec.data_start} is lz4-compressed; install 'lz4' to read it")
            return
        except (OSError, ValueError, EOFError) as err:
            self._damaged(f"chunk at {rec.data_start} does not decompress: {err}")
            return
        if len(inner) != expected:
            log.debug("%s: chunk at %d: %d bytes, header says %d", self.path, rec.data_start,
                      len(inner), expected)  # fmt: skip
        pos = 0
        size = len(inner)
        while pos < size:
            sub = _parse_record(inner, pos, size)
            if sub is None or sub.data_end > size:
                self._damaged(f"chunk at {rec.data_start}: damaged record at chunk offset {pos}")
                return
            if sub.op == OP_CONNECTION:
                self._connection(sub, inner[sub.data_start : sub.data_end])
            elif sub.op == OP_MSG_DATA:
                msg = self._message(sub, inner[sub.data_start : sub.data_end], topics, deserialize)
                if msg is not None:
                    yield msg
            pos = sub.end

    def _connection(self, rec: _Record, data: bytes) -> None:
        conn_id = _u32(rec.fields["conn"])
        topic = rec.fields["topic"].decode(errors="replace")
        details = _parse_fields(data, 0, len(data)) or {}
        msgtype = details.get("type", b"").decode(errors="replace")
        if conn_id in self._conns:
            return
        self._conns[conn_id] = (topic, msgtype)
        self.topics.setdefault(topic, _normalise_type(msgtype))
        definition = details.get("message_definition")
        if definition is not None:
            self._register(msgtype, definition.decode(errors="replace"))

    def _register(self, msgtype: str, definition: str) -> None:
        store = self._store()
        name = _normalise_type(msgtype)
        if name in store.fielddefs:
            return
        try:
            store.register(get_types_from_msg(definition, name))
        except Exception as err:  # a bad definition only matters if we need that type
            log.debug("%s: cannot register %s: %s", self.path, name, err)

    def _store(self) -> Any:
        if self._typestore is None:
            self._typestore = get_typestore(Stores.ROS1_NOETIC)
        return self._typestore

    def _message(
        self, rec: _Record, data: bytes, topics: set[str] | None, deserialize: bool
    ) -> _RawMessage | None:
        conn = self._conns.get(_u32(rec.fields["conn"]))
        if conn is None:
            log.debug("%s: message on unknown connection", self.path)
            return None
        topic, msgtype = conn
        if topics is not None and topic not in topics:
            return None
        time_ns = _time_ns(rec.fields["time"])
        if not deserialize:
            return _RawMessage(topic, msgtype, time_ns, data)
        try:
            msg = self._store().deserialize_ros1(bytes(data), _normalise_type(msgtype))
        except Exception as err:
            log.warning("%s: %s message at %d s does not deserialise: %s", self.path, topic,
                        time_ns // 1_000_000_000, err)  # fmt: skip
            return None
        return _RawMessage(topic, msgtype, time_ns, msg)


def _fix_index_record(buf: mmap.mmap, rec: _Record, size: int) -> _Record:
    """Index data records in some bags declare a wrong data length; trust `count` if it fits."""
    if _u32(rec.fields["ver"]) != 1:
        return rec
    count = _u32(rec.fields["count"])
    computed_end = rec.data_start + 12 * count
    if computed_end == rec.data_end or computed_end > size:
        return rec
    declared_ok = rec.data_end == size or (
        rec.data_end < size and _parse_record(buf, rec.data_end, size) is not None
    )
    if declared_ok:
        return rec
    if computed_end == size or _parse_record(buf, computed_end, size) is not None:
        log.debug("index record at %d: data length %d, count says %d", rec.data_start,
                  rec.data_end - rec.data_start, 12 * count)  # fmt: skip
        return dataclasses.replace(rec, data_end=computed_end)
    return rec


def _resync(buf: mmap.mmap, start: int, size: int) -> int | None:
    """The first position at or after `start` holding a plausible record, or None."""
    search = start
    while True:
        k = buf.find(b"op=", search)
        if k < 0:
            return None
        # The `op` field's own length prefix is at k - 4; the record header starts before it.
        for candidate in range(max(start, k - 8 - _RESYNC_LOOKBACK_BYTES), k - 7):
            rec = _parse_record(buf, candidate, size)
            if rec is not None and candidate + 8 <= k < rec.data_start:
                return candidate
        search = k + 1


def _lz4_decompress(data: bytes) -> bytes:
    # Optional dependency, only for ROS 1 lz4 chunks; ImportError is reported per chunk.
    lz4_frame: Any = importlib.import_module("lz4.frame")
    out = lz4_frame.decompress(data)
    assert isinstance(out, bytes)
    return out


__all__ = [
    "LogError",
    "LogInfo",
    "LogKind",
    "LogReadError",
    "count_log_scans",
    "detect_log_kind",
    "iter_log_scans",
    "probe_log",
]
