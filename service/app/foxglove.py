"""Foxglove live view: the service's robots over the Foxglove WebSocket protocol (foxglove-sdk).

Per robot with a session, on topics under `/<robot_id>/`:
- `map` (`foxglove.Grid`, frame `map`): re-sent when the map changes, at most once per second;
- `scan` (`foxglove.LaserScan`, frame `<robot_id>/base_link`): the latest scan, at most 10 Hz;
- `pose` (`foxglove.PoseInFrame`, frame `map`) and the transform `map -> <robot_id>/base_link`
  on `/tf` (`foxglove.FrameTransforms`), so that a 3-D panel places the robot;
- `trajectory` (`foxglove.SceneUpdate`): the trajectory as a line strip and the accepted loop
  closures as lines, when the session exposes them (`loop_closures()`), at most once per second.

Where the scans come from: in the process that maps them, the ingest worker hands each one over
(`observe`). When the mapper processes take the scans in (`--mapper-processes K`), the service's
process has none, so the view is given a `scan_tap` instead: while (and only while) a viewer
subscribes to a robot's `scan` channel, the view subscribes to that robot's scan key on the
service's own Zenoh session, into a one-sample ring on Zenoh's side (no Python callback per
scan), and decodes only the sample it takes, at most every 100 ms. Nobody watching costs
nothing: no subscription, so Zenoh routes this process no scan. Having the mapper process
forward them instead would put a check and a pipe write on its per-scan path, the one that
limits the fleet. The poses come with the mapper processes' batched entries (`observe_pose`).

Why a publisher thread and not encoding on the ingest worker: the worker only hands the latest
scan and pose over (`observe`: a lock held for a dict assignment and a deque append, no
encoding), so a slow or absent viewer can never delay a pose. The publisher thread wakes every
50 ms, asks each channel whether anyone subscribes (`has_sinks`, a flag read in the SDK) and
encodes only for channels that have a subscriber. The SDK's server buffers a bounded number of
messages per client and drops the oldest for a slow one.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import foxglove
import numpy as np
from foxglove.channels import (
    FrameTransformsChannel,
    GridChannel,
    LaserScanChannel,
    PoseInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.messages import (
    Color,
    FrameTransform,
    FrameTransforms,
    Grid,
    LaserScan,
    LinePrimitive,
    LinePrimitiveLineType,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    Timestamp,
    Vector2,
    Vector3,
)
from foxglove.messages import Pose as FgPose
from foxglove.websocket import ServerListener

from clients.keyexpr import scan_key
from clients.wire import Pose, Scan, WireError, decode_scan

log = logging.getLogger(__name__)

MAP_FRAME = "map"
MAP_PERIOD_S = 1.0  # the map and the trajectory: at most once per second
SCAN_PERIOD_S = 0.1  # scans decimated to at most 10 Hz
TICK_S = 0.05
MAX_TRAJECTORY_POINTS = 5000  # a line strip of an hour at 40 Hz, decimated
MAX_POSES_PER_TICK = 64  # poses buffered per robot between ticks (oldest dropped)
# foxglove-sdk 0.30 rejects ("unknown channel") about one subscribe in five that arrives within
# milliseconds of the channel's advertisement, as a viewer's saved layout does when a robot
# appears (measured: 18 of 100 channels created with a client connected). A robot's channel
# that nobody subscribes to is advertised again (closed, created anew) at these ages; a viewer
# that wanted it subscribes to the new one: 5 more tries leave about 1 lost in 30,000.
READVERTISE_AT_S = (0.25, 0.5, 1.0, 2.0, 4.0)
# map.png's and the web page's trajectory colour (service/mapio.py _TRAJECTORY_RGB), and a
# distinct one for loop closures.
TRAJECTORY_RGBA = (222 / 255, 74 / 255, 44 / 255, 1.0)
LOOP_CLOSURE_RGBA = (0.15, 0.39, 0.92, 1.0)


def base_link(robot_id: str) -> str:
    return f"{robot_id}/base_link"


class _Session(Protocol):
    """What the view reads of a `MappingSession` (a Protocol: tests may pass their own)."""

    id: str
    robot_id: str
    map_revision: int

    @property
    def is_active(self) -> bool: ...

    def map_image(self) -> Any: ...

    def trajectory(self) -> list[Pose]: ...


class ScanFeed(Protocol):
    """One robot's scans taken for display only, held while a viewer watches its scans."""

    def latest(self) -> Scan | None:
        """The newest scan since the last call, if any (never blocks)."""
        ...

    def close(self) -> None: ...


# Opens a robot's `ScanFeed` (the view calls it when a viewer subscribes to its scans).
ScanTap = Callable[[str], ScanFeed]
SessionsSource = Callable[[], Iterable[_Session]]
# Loop closures of a session as pairs of (x_m, y_m) points in the map frame: by default the
# session's `loop_closures()` (none for a source without it, as tests may pass).
LoopClosureSource = Callable[[_Session], Sequence[tuple[tuple[float, float], tuple[float, float]]]]


def session_loop_closures(
    session: _Session,
) -> Sequence[tuple[tuple[float, float], tuple[float, float]]]:
    getter = getattr(session, "loop_closures", None)
    if getter is None:
        return ()
    try:
        return list(getter())
    except Exception as err:  # a hook must not stop the view
        log.debug("loop closures of %s: %s", session.id, err)
        return ()


def _stamp(stamp_ns: int) -> Timestamp:
    return Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)


def _yaw(theta_rad: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(theta_rad / 2.0), w=math.cos(theta_rad / 2.0))


def _color(rgba: tuple[float, float, float, float]) -> Color:
    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def grid_message(image: Any, stamp_ns: int) -> Grid:
    """A `GridImage` as a `foxglove.Grid` in the map frame: one INT8 field `occupancy` (-1
    unknown, 0..100 percent), row 0 at the lowest y like the image and nav_msgs/OccupancyGrid."""
    occupancy = np.ascontiguousarray(image.occupancy, dtype=np.int8)
    width = int(occupancy.shape[1])
    return Grid(
        timestamp=_stamp(stamp_ns),
        frame_id=MAP_FRAME,
        pose=FgPose(
            position=Vector3(x=float(image.origin_x_m), y=float(image.origin_y_m), z=0.0),
            orientation=Quaternion(w=1.0),
        ),
        column_count=int(width),
        cell_size=Vector2(x=float(image.resolution_m), y=float(image.resolution_m)),
        row_stride=int(width),
        cell_stride=1,
        fields=[
            PackedElementField(name="occupancy", offset=0, type=PackedElementFieldNumericType.Int8)
        ],
        data=occupancy.tobytes(),
    )


def scan_message(scan: Scan) -> LaserScan:
    n = scan.beam_count
    end = scan.angle_min_rad + scan.angle_increment_rad * max(n - 1, 0)
    return LaserScan(
        timestamp=_stamp(scan.stamp_ns),
        frame_id=base_link(scan.robot_id),
        pose=FgPose(position=Vector3(), orientation=Quaternion(w=1.0)),
        start_angle=float(scan.angle_min_rad),
        end_angle=float(end),
        ranges=scan.ranges_m.tolist(),
        intensities=scan.intensities.tolist() if scan.intensities is not None else [],
    )


def pose_message(pose: Pose) -> PoseInFrame:
    return PoseInFrame(
        timestamp=_stamp(pose.stamp_ns),
        frame_id=MAP_FRAME,
        pose=FgPose(
            position=Vector3(x=pose.x_m, y=pose.y_m, z=0.0), orientation=_yaw(pose.theta_rad)
        ),
    )


def transform_message(pose: Pose) -> FrameTransform:
    return FrameTransform(
        timestamp=_stamp(pose.stamp_ns),
        parent_frame_id=MAP_FRAME,
        child_frame_id=base_link(pose.robot_id),
        translation=Vector3(x=pose.x_m, y=pose.y_m, z=0.0),
        rotation=_yaw(pose.theta_rad),
    )


def trajectory_message(
    poses: Sequence[Pose],
    closures: Sequence[tuple[tuple[float, float], tuple[float, float]]],
    stamp_ns: int,
) -> SceneUpdate:
    step = max(1, math.ceil(len(poses) / MAX_TRAJECTORY_POINTS))
    picked = list(poses[::step])
    if poses and picked[-1] is not poses[-1]:
        picked.append(poses[-1])
    lines = [
        LinePrimitive(
            type=LinePrimitiveLineType.LineStrip,
            pose=FgPose(position=Vector3(), orientation=Quaternion(w=1.0)),
            thickness=2.0,
            scale_invariant=True,
            points=[Point3(x=p.x_m, y=p.y_m, z=0.0) for p in picked],
            color=_color(TRAJECTORY_RGBA),
        )
    ]
    if closures:
        lines.append(
            LinePrimitive(
                type=LinePrimitiveLineType.LineList,
                pose=FgPose(position=Vector3(), orientation=Quaternion(w=1.0)),
                thickness=2.0,
                scale_invariant=True,
                points=[Point3(x=x, y=y, z=0.0) for pair in closures for (x, y) in pair],
                color=_color(LOOP_CLOSURE_RGBA),
            )
        )
    return SceneUpdate(
        entities=[
            SceneEntity(
                timestamp=_stamp(stamp_ns), frame_id=MAP_FRAME, id="trajectory", lines=lines
            )
        ]
    )


class ZenohScanFeed:
    """A robot's scan key on a Zenoh session, into a ring of one sample: Zenoh keeps the newest
    on its side (no GIL per scan); `latest` decodes only what it takes."""

    def __init__(self, session: Any, robot_id: str, prefix: str) -> None:
        from zenoh.handlers import RingChannel  # noqa: PLC0415  # only with a tap

        self._robot_id = robot_id
        self._sub = session.declare_subscriber(scan_key(robot_id, prefix), RingChannel(1))

    def latest(self) -> Scan | None:
        sample = self._sub.try_recv()
        if sample is None:
            return None
        try:
            scan = decode_scan(sample.payload.to_bytes())
        except WireError:
            return None  # the ingest counts the rejection; the view just skips it
        return scan if scan.robot_id == self._robot_id else None

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception as err:  # the session may be closing
            log.debug("undeclare of %s's scan feed: %s", self._robot_id, err)


def zenoh_scan_tap(session: Any, prefix: str) -> ScanTap:
    return lambda robot_id: ZenohScanFeed(session, robot_id, prefix)


@dataclass
class _Robot:
    """One robot's channels and what the publisher thread has sent of it."""

    robot_id: str
    map: GridChannel
    scan: LaserScanChannel
    pose: PoseInFrameChannel
    trajectory: SceneUpdateChannel
    created_s: float = 0.0  # when the channels were first advertised (monotonic)
    readvertised: int = 0  # re-advertisements done (READVERTISE_AT_S)
    session_id: str = ""
    session: Any = None  # the _Session the topics follow (set by the publisher thread)
    latest_scan: Scan | None = None  # guarded by FoxgloveView._lock
    feed: ScanFeed | None = None  # with a scan tap: open while the scan channel has a viewer
    poses: deque[Pose] = field(default_factory=lambda: deque(maxlen=MAX_POSES_PER_TICK))
    scan_sent: Scan | None = None
    scan_sent_s: float = -math.inf
    map_sent_s: float = -math.inf
    map_sent: tuple[str, int] | None = None  # (session, revision) of the last map sent
    trajectory_sent_s: float = -math.inf
    trajectory_sent_len: int = -1

    def channels(self) -> tuple[Any, ...]:
        return tuple(getattr(self, name) for name in _ROBOT_CHANNELS)


# A robot's channels: _Robot's field, the channel type, and the topic under `/<robot_id>/`.
_ROBOT_CHANNELS: dict[str, type] = {
    "map": GridChannel,
    "scan": LaserScanChannel,
    "pose": PoseInFrameChannel,
    "trajectory": SceneUpdateChannel,
}


@dataclass
class ViewCounters:
    grids: int = 0
    scans: int = 0
    poses: int = 0
    trajectories: int = 0
    errors: int = 0


class _Listener(ServerListener):
    """The SDK's server callbacks (on its own thread): note which topics gained a subscriber."""

    def __init__(self, view: FoxgloveView) -> None:
        self._view = view

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self._view._subscribed(str(channel.topic))


class FoxgloveView:
    """The Foxglove WebSocket server and its publisher thread; `observe` is the ingest hook."""

    def __init__(
        self,
        sessions: SessionsSource,
        *,
        host: str = "127.0.0.1",
        port: int = 8765,
        loop_closures: LoopClosureSource = session_loop_closures,
        name: str = "mapping-service",
        scan_tap: ScanTap | None = None,
    ) -> None:
        """`scan_tap`: where to take a watched robot's scans when no ingest worker calls
        `observe` in this process (the mapper processes take them in)."""
        self._sessions = sessions
        self._scan_tap = scan_tap
        self._host = host
        self._requested_port = port
        self._loop_closures = loop_closures
        self._name = name
        self._context = foxglove.Context()
        self._server: Any = None
        self._tf: FrameTransformsChannel | None = None
        self._robots: dict[str, _Robot] = {}
        self._lock = threading.Lock()
        self._fresh_topics: set[str] = set()  # subscribed since the last pass (guarded)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.counters = ViewCounters()

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        try:
            self._server = foxglove.start_server(
                name=self._name,
                host=self._host,
                port=self._requested_port,
                context=self._context,
                server_listener=_Listener(self),
            )
        except Exception as err:  # the SDK raises a RuntimeError subclass for a busy port
            raise OSError(f"cannot listen on {self._host}:{self._requested_port}: {err}") from err
        self._tf = FrameTransformsChannel("/tf", context=self._context)
        self._thread = threading.Thread(target=self._run, name="foxglove", daemon=True)
        self._thread.start()
        log.info("Foxglove WebSocket on %s", self.url)

    @property
    def port(self) -> int:
        return int(self._server.port) if self._server is not None else 0

    @property
    def url(self) -> str:
        shown = self._host if self._host not in ("0.0.0.0", "::", "") else "127.0.0.1"
        if ":" in shown:
            shown = f"[{shown}]"
        return f"ws://{shown}:{self.port}"

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        with self._lock:
            robots = list(self._robots.values())
            self._robots.clear()
        for robot in robots:
            if robot.feed is not None:
                robot.feed.close()
                robot.feed = None
            for channel in robot.channels():
                channel.close()
        if self._tf is not None:
            self._tf.close()
            self._tf = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    # -- ingest side (any worker thread; never blocks, never encodes) -----------------------

    def observe(self, scan: Scan, pose: Pose | None) -> None:
        robot = self._robots.get(scan.robot_id)  # dict reads are atomic
        if robot is None:
            return  # channels appear on the publisher's next pass over the sessions
        with self._lock:
            robot.latest_scan = scan
            if pose is not None:
                robot.poses.append(pose)

    def observe_pose(self, pose: Pose) -> None:
        """A pose mapped in another process (its scan is not here: see `scan_tap`)."""
        robot = self._robots.get(pose.robot_id)
        if robot is None:
            return
        with self._lock:
            robot.poses.append(pose)

    def _subscribed(self, topic: str) -> None:
        with self._lock:
            self._fresh_topics.add(topic)

    # -- publisher thread ------------------------------------------------------------------

    def _run(self) -> None:
        next_sessions_s = 0.0
        while not self._stop.wait(TICK_S):
            now_s = time.monotonic()
            try:
                if now_s >= next_sessions_s:
                    self._sync_robots()
                    next_sessions_s = now_s + MAP_PERIOD_S
                self._publish(now_s)
            except Exception:  # the view must keep running; the service does not depend on it
                self.counters.errors += 1
                if self.counters.errors == 1 or math.log2(self.counters.errors).is_integer():
                    log.exception("Foxglove pass failed (%d so far)", self.counters.errors)

    def _sync_robots(self) -> None:
        """Channels for every robot that has a session (its active one, else its latest)."""
        latest: dict[str, _Session] = {}
        for session in self._sessions():
            current = latest.get(session.robot_id)
            if current is None or session.is_active or not current.is_active:
                latest[session.robot_id] = session
        for robot_id, gone in self._robots.items():
            if robot_id not in latest:  # its sessions were deleted: nothing more to draw
                gone.session = None
        for robot_id, session in latest.items():
            robot = self._robots.get(robot_id)
            if robot is None:
                robot = self._new_robot(robot_id, time.monotonic())
                with self._lock:
                    self._robots[robot_id] = robot
            robot.session = session
            if robot.session_id != session.id:
                robot.session_id = session.id
                robot.map_sent = None
                robot.trajectory_sent_len = -1

    def _new_robot(self, robot_id: str, now_s: float) -> _Robot:
        channels = {
            name: kind(f"/{robot_id}/{name}", context=self._context)
            for name, kind in _ROBOT_CHANNELS.items()
        }
        return _Robot(robot_id=robot_id, created_s=now_s, **channels)

    def _readvertise(self, robot: _Robot, now_s: float) -> None:
        """Advertise again the young channels nobody subscribes to (READVERTISE_AT_S)."""
        done = robot.readvertised
        if done >= len(READVERTISE_AT_S) or now_s - robot.created_s < READVERTISE_AT_S[done]:
            return
        robot.readvertised += 1
        for name, kind in _ROBOT_CHANNELS.items():
            channel = getattr(robot, name)
            if not channel.has_sinks():
                topic = channel.topic()
                channel.close()
                setattr(robot, name, kind(topic, context=self._context))

    def _publish(self, now_s: float) -> None:
        tf = self._tf
        for robot in list(self._robots.values()):
            self._readvertise(robot, now_s)
            with self._lock:
                scan = robot.latest_scan
                poses = list(robot.poses)
                robot.poses.clear()
            if self._scan_tap is not None:
                scan = self._tapped_scan(robot, now_s)
            if (
                scan is not None
                and scan is not robot.scan_sent
                and now_s - robot.scan_sent_s >= SCAN_PERIOD_S
            ):
                robot.scan_sent = scan
                robot.scan_sent_s = now_s
                if robot.scan.has_sinks():
                    robot.scan.log(scan_message(scan), log_time=scan.stamp_ns)
                    self.counters.scans += 1
            if poses:
                if robot.pose.has_sinks():
                    for pose in poses:
                        robot.pose.log(pose_message(pose), log_time=pose.stamp_ns)
                    self.counters.poses += len(poses)
                if tf is not None and tf.has_sinks():
                    last = poses[-1]
                    tf.log(
                        FrameTransforms(transforms=[transform_message(last)]),
                        log_time=last.stamp_ns,
                    )
            self._publish_map(robot, now_s)

    def _tapped_scan(self, robot: _Robot, now_s: float) -> Scan | None:
        """The robot's newest scan from the tap when it is due, holding the robot's feed open
        only while its scan channel has a subscriber."""
        assert self._scan_tap is not None
        if not robot.scan.has_sinks():
            if robot.feed is not None:
                robot.feed.close()
                robot.feed = None
                log.info("Foxglove: no viewer of %s's scans: its scan key released", robot.robot_id)
            return None
        if robot.feed is None:
            robot.feed = self._scan_tap(robot.robot_id)
            log.info("Foxglove: a viewer watches %s's scans: its scan key taken", robot.robot_id)
            return None
        if now_s - robot.scan_sent_s < SCAN_PERIOD_S:
            return None
        return robot.feed.latest()

    def _publish_map(self, robot: _Robot, now_s: float) -> None:
        map_wanted = robot.map.has_sinks()
        trajectory_wanted = robot.trajectory.has_sinks()
        with self._lock:  # a new subscriber gets the map and the trajectory at once
            if self._fresh_topics:
                if robot.map.topic() in self._fresh_topics:
                    robot.map_sent = None
                if robot.trajectory.topic() in self._fresh_topics:
                    robot.trajectory_sent_len = -1
                self._fresh_topics.discard(robot.map.topic())
                self._fresh_topics.discard(robot.trajectory.topic())
        if not map_wanted and not trajectory_wanted:
            return
        session: _Session | None = robot.session
        if session is None or getattr(session, "status", "ok") == "restoring":
            return  # a restoring session has no map or trajectory to show yet
        stamp_ns = time.time_ns()
        if map_wanted and (
            robot.map_sent is None
            or (
                robot.map_sent != (session.id, session.map_revision)
                and now_s - robot.map_sent_s >= MAP_PERIOD_S
            )
        ):
            revision = session.map_revision
            image = session.map_image().image
            if image.width and image.height:  # before the first keyframe there is no map
                robot.map.log(grid_message(image, stamp_ns), log_time=stamp_ns)
                robot.map_sent = (session.id, revision)
                robot.map_sent_s = now_s
                self.counters.grids += 1
        if trajectory_wanted and (
            robot.trajectory_sent_len < 0 or now_s - robot.trajectory_sent_s >= MAP_PERIOD_S
        ):
            poses = session.trajectory()
            if len(poses) != robot.trajectory_sent_len:
                robot.trajectory.log(
                    trajectory_message(poses, self._loop_closures(session), stamp_ns),
                    log_time=stamp_ns,
                )
                robot.trajectory_sent_len = len(poses)
                robot.trajectory_sent_s = now_s
                self.counters.trajectories += 1
