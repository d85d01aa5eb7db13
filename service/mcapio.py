"""MCAP export of a session or a recording, with ROS 2 message schemas.

Topics (frames `map` and `<robot_id>/base_link`, stamps from the scans):
- `/scan`  `sensor_msgs/msg/LaserScan`, every recorded scan, ranges as float32 (bit-exact for
  scans that arrived as float32; the UTM-30LX's millimetres convert exactly as `f32(mm/1000)`);
- `/pose`  `geometry_msgs/msg/PoseStamped`, every recorded pose, stamped like its scan;
- `/tf`    `tf2_msgs/msg/TFMessage`, `map -> <robot_id>/base_link` at every pose;
- `/map`   `nav_msgs/msg/OccupancyGrid`, the final map, once, at the last scan's stamp.

Written with `mcap` (chunked, zstd) and `rosbags`' CDR serialiser, which encodes a float32
array in one numpy call; the message definitions registered as ROS 2 schemas are generated
by `rosbags` from the same types, so `mcap-ros2-support`, `rosbags` and Foxglove decode them.
Stamps outside ROS time (before 1970, after 2038: `service.app.limits.in_ros_time`) cannot be
written (ROS 2 `Time.sec` is an int32, MCAP log times are unsigned): the service refuses such
scans at ingest, and a message of an older recording that has one is left out of the export,
counted (`ExportCounts.skipped`) and logged, so that every recording exports.
The writer streams: messages are written as they are read, a chunk (1 MiB) at a time, so memory
does not grow with the session's length; `stream_mcap` yields the bytes as chunks complete, for
an HTTP response.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO, Final

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.typesys import Stores, get_typestore

from clients.wire import Pose, Scan
from service.app.limits import in_ros_time
from service.bridge import scan_to_laser
from service.core.maps.grid import OccupancyGrid
from service.core.types import Pose2D

log = logging.getLogger(__name__)

LASER_SCAN: Final = "sensor_msgs/msg/LaserScan"
POSE_STAMPED: Final = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE: Final = "tf2_msgs/msg/TFMessage"
OCCUPANCY_GRID: Final = "nav_msgs/msg/OccupancyGrid"
TOPICS: Final = {
    "/scan": LASER_SCAN,
    "/pose": POSE_STAMPED,
    "/tf": TF_MESSAGE,
    "/map": OCCUPANCY_GRID,
}
MAP_FRAME: Final = "map"
CHUNK_BYTES: Final = 1 << 20

_STORE = get_typestore(Stores.LATEST)


@dataclass
class ExportCounts:
    scans: int = 0
    poses: int = 0
    maps: int = 0
    first_stamp_ns: int = 0
    last_stamp_ns: int = 0
    skipped: int = 0  # scans and poses left out: their stamp is outside ROS time


class _Sink:
    """A write-only stream for `mcap.Writer` (which asks for `tell()`): counts bytes and hands
    them to `out`, a file or a buffer that `stream_mcap` drains."""

    def __init__(self, out: Callable[[bytes], Any]) -> None:
        self._out = out
        self._offset = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        self._out(bytes(data))
        self._offset += len(data)
        return len(data)

    def tell(self) -> int:
        return self._offset

    def flush(self) -> None:
        """Nothing buffered here."""


def _time(stamp_ns: int) -> Any:
    t = _STORE.types["builtin_interfaces/msg/Time"]
    return t(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


def _header(stamp_ns: int, frame_id: str) -> Any:
    return _STORE.types["std_msgs/msg/Header"](stamp=_time(stamp_ns), frame_id=frame_id)


def _quaternion(theta_rad: float) -> Any:
    return _STORE.types["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=math.sin(theta_rad / 2.0), w=math.cos(theta_rad / 2.0)
    )


def base_link(robot_id: str) -> str:
    return f"{robot_id}/base_link"


def laser_scan_msg(scan: Scan) -> Any:
    n = scan.beam_count
    intensities = (
        np.asarray(scan.intensities, dtype=np.float32)
        if scan.intensities is not None
        else np.empty(0, dtype=np.float32)
    )
    return _STORE.types[LASER_SCAN](
        header=_header(scan.stamp_ns, base_link(scan.robot_id)),
        angle_min=float(scan.angle_min_rad),
        angle_max=float(scan.angle_min_rad + scan.angle_increment_rad * max(n - 1, 0)),
        angle_increment=float(scan.angle_increment_rad),
        time_increment=0.0,
        scan_time=0.0,
        range_min=float(scan.range_min_m),
        range_max=float(scan.range_max_m),
        ranges=np.asarray(scan.ranges_m, dtype=np.float32),
        intensities=intensities,
    )


def _pose_msg(pose: Pose) -> Any:
    t = _STORE.types
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=pose.x_m, y=pose.y_m, z=0.0),
        orientation=_quaternion(pose.theta_rad),
    )


def pose_stamped_msg(pose: Pose) -> Any:
    return _STORE.types[POSE_STAMPED](
        header=_header(pose.stamp_ns, MAP_FRAME), pose=_pose_msg(pose)
    )


def tf_msg(pose: Pose) -> Any:
    t = _STORE.types
    transform = t["geometry_msgs/msg/TransformStamped"](
        header=_header(pose.stamp_ns, MAP_FRAME),
        child_frame_id=base_link(pose.robot_id),
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=pose.x_m, y=pose.y_m, z=0.0),
            rotation=_quaternion(pose.theta_rad),
        ),
    )
    return t[TF_MESSAGE](transforms=[transform])


def occupancy_grid_msg(image: Any, stamp_ns: int) -> Any:
    """A `GridImage` (row 0 = lowest y, -1 unknown, 0..100) is already nav_msgs' layout."""
    t = _STORE.types
    occupancy = np.ascontiguousarray(image.occupancy, dtype=np.int8)
    height, width = occupancy.shape
    return t[OCCUPANCY_GRID](
        header=_header(stamp_ns, MAP_FRAME),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=_time(stamp_ns),
            resolution=float(image.resolution_m),
            width=int(width),
            height=int(height),
            origin=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](
                    x=float(image.origin_x_m), y=float(image.origin_y_m), z=0.0
                ),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        ),
        data=occupancy.reshape(-1),
    )


class McapExporter:
    """Writes scans and poses as they come, then the final map; `finish()` closes the file."""

    def __init__(self, out: Callable[[bytes], Any]) -> None:
        self._writer = McapWriter(
            _Sink(out),  # type: ignore[arg-type]  # write/tell/flush is all it uses
            chunk_size=CHUNK_BYTES,
            compression=CompressionType.ZSTD,
        )
        self._writer.start(profile="ros2", library="manhattan-mapper")
        self._channels: dict[str, int] = {}
        for topic, msgtype in TOPICS.items():
            msgdef, _ = _STORE.generate_msgdef(msgtype, ros_version=2)
            schema_id = self._writer.register_schema(
                name=msgtype, encoding=SchemaEncoding.ROS2, data=msgdef.encode()
            )
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MessageEncoding.CDR, schema_id=schema_id
            )
        self._sequence: dict[str, int] = dict.fromkeys(TOPICS, 0)
        self.counts = ExportCounts()

    def _write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        data = _STORE.serialize_cdr(msg, TOPICS[topic])
        self._writer.add_message(
            channel_id=self._channels[topic],
            log_time=stamp_ns,
            publish_time=stamp_ns,
            sequence=self._sequence[topic],
            data=bytes(data),
        )
        self._sequence[topic] += 1

    def _stamp(self, stamp_ns: int) -> None:
        if not self.counts.first_stamp_ns:
            self.counts.first_stamp_ns = stamp_ns
        self.counts.last_stamp_ns = max(self.counts.last_stamp_ns, stamp_ns)

    def _writable(self, stamp_ns: int, what: str) -> bool:
        if in_ros_time(stamp_ns):
            return True
        if not self.counts.skipped:
            log.warning(
                "MCAP export: a %s stamped %d ns is outside ROS time (1970 to 2038): left out "
                "(further ones only counted)",
                what,
                stamp_ns,
            )
        self.counts.skipped += 1
        return False

    def scan(self, scan: Scan) -> None:
        if not self._writable(scan.stamp_ns, "scan"):
            return
        self._write("/scan", laser_scan_msg(scan), scan.stamp_ns)
        self._stamp(scan.stamp_ns)
        self.counts.scans += 1

    def pose(self, pose: Pose) -> None:
        if not self._writable(pose.stamp_ns, "pose"):
            return
        self._write("/pose", pose_stamped_msg(pose), pose.stamp_ns)
        self._write("/tf", tf_msg(pose), pose.stamp_ns)
        self._stamp(pose.stamp_ns)
        self.counts.poses += 1

    def final_map(self, image: Any) -> None:
        stamp_ns = self.counts.last_stamp_ns
        self._write("/map", occupancy_grid_msg(image, stamp_ns), stamp_ns)
        self.counts.maps += 1

    def finish(self) -> None:
        if self.counts.skipped:
            log.warning(
                "MCAP export: %d message(s) left out: stamps outside ROS time", self.counts.skipped
            )
        finish: Any = self._writer.finish  # untyped in mcap
        finish()


def write_mcap(
    messages: Iterable[Scan | Pose],
    out: BinaryIO,
    final_map: Callable[[], Any] | None = None,
) -> ExportCounts:
    """Write `messages` (in recording order) and then `final_map()` (a `GridImage`, or None
    for no map) to the binary file `out`."""
    exporter = McapExporter(out.write)
    for message in messages:
        if isinstance(message, Scan):
            exporter.scan(message)
        else:
            exporter.pose(message)
    image = final_map() if final_map is not None else None
    if image is not None:
        exporter.final_map(image)
    exporter.finish()
    return exporter.counts


def stream_mcap(
    messages: Iterable[Scan | Pose], final_map: Callable[[], Any] | None = None
) -> Iterator[bytes]:
    """The same file as `write_mcap`, yielded in pieces as the writer completes them (about a
    chunk at a time): for a streamed HTTP response."""
    pending: list[bytes] = []
    exporter = McapExporter(pending.append)

    def drain() -> Iterator[bytes]:
        if pending:
            data = b"".join(pending)
            pending.clear()
            yield data

    yield from drain()
    for message in messages:
        if isinstance(message, Scan):
            exporter.scan(message)
        else:
            exporter.pose(message)
        yield from drain()
    image = final_map() if final_map is not None else None
    if image is not None:
        exporter.final_map(image)
    exporter.finish()
    yield from drain()


class MapBuilder:
    """The final map of a recording from its scans at their recorded poses (the CLI export has
    no live session): a grid that takes a scan whenever the robot moved 0.2 m or turned 10°
    since the last one it took, as the service's keyframes do."""

    def __init__(self, resolution_m: float = 0.05) -> None:
        self._grid = OccupancyGrid(resolution_m=resolution_m)
        self._scan: Scan | None = None
        self._last: tuple[float, float, float] | None = None
        self.integrated = 0

    def add(self, message: Scan | Pose) -> None:
        if isinstance(message, Scan):
            self._scan = message
            return
        scan, self._scan = self._scan, None
        if scan is None or scan.stamp_ns != message.stamp_ns:
            return
        here = (message.x_m, message.y_m, message.theta_rad)
        if self._last is not None:
            dx, dy = here[0] - self._last[0], here[1] - self._last[1]
            dth = abs((here[2] - self._last[2] + math.pi) % (2 * math.pi) - math.pi)
            if math.hypot(dx, dy) < 0.2 and dth < math.radians(10.0):
                return
        self._last = here
        self._grid.integrate(
            scan_to_laser(scan, use_odometry=False),
            Pose2D(message.x_m, message.y_m, message.theta_rad),
        )
        self.integrated += 1

    def snapshot(self) -> Any:
        return self._grid.snapshot() if self.integrated else None


def with_map(messages: Iterable[Scan | Pose], builder: MapBuilder) -> Iterator[Scan | Pose]:
    for message in messages:
        builder.add(message)
        yield message
