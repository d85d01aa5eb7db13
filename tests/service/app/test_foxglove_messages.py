"""The Foxglove view's messages built from the service's types (no server: pure functions),
decoded with the protobuf schema each type declares, as a viewer would."""

from __future__ import annotations

import base64
import math
from typing import Any

import numpy as np
from foxglove_client import message_class

from clients.wire import Pose
from service.app.foxglove import (
    MAX_TRAJECTORY_POINTS,
    grid_message,
    pose_message,
    trajectory_message,
    transform_message,
)
from service.core.maps.grid import GridImage

LINE_LIST = 2  # foxglove.LinePrimitive.Type: LINE_STRIP 0, LINE_LOOP 1, LINE_LIST 2


def decoded(message: Any) -> Any:
    schema = type(message).get_schema()
    cls = message_class(schema.name, base64.b64encode(schema.data).decode())
    return cls.FromString(message.encode())


def _pose(seq: int, x: float = 0.0, theta: float = 0.0) -> Pose:
    return Pose("s-1", "r-1", seq, 1_000_000_000 + seq, x, 2.0, theta, 1.0)


def test_grid_keeps_the_image_layout_and_origin() -> None:
    occupancy = np.array([[-1, 0, 100], [50, 0, -1]], dtype=np.int8)  # row 0 = lowest y
    image = GridImage(occupancy, origin_x_m=-1.5, origin_y_m=2.0, resolution_m=0.05)
    grid = decoded(grid_message(image, 5))
    assert grid.frame_id == "map"
    assert grid.column_count == 3
    assert grid.row_stride == 3
    assert grid.data == occupancy.tobytes()
    assert (grid.pose.position.x, grid.pose.position.y) == (-1.5, 2.0)


def test_pose_and_transform_carry_the_heading() -> None:
    pose = _pose(1, x=3.0, theta=math.pi / 2)
    q = decoded(pose_message(pose)).pose.orientation
    assert math.isclose(2 * math.atan2(q.z, q.w), math.pi / 2)
    tf = decoded(transform_message(pose))
    assert (tf.parent_frame_id, tf.child_frame_id) == ("map", "r-1/base_link")
    assert tf.translation.x == 3.0


def test_trajectory_is_decimated_keeps_its_end_and_draws_loop_closures() -> None:
    poses = [_pose(i, x=0.01 * i) for i in range(3 * MAX_TRAJECTORY_POINTS + 7)]
    update = decoded(trajectory_message(poses, [((0.0, 2.0), (1.0, 2.0))], 9))
    strip, closures = update.entities[0].lines
    assert len(strip.points) <= MAX_TRAJECTORY_POINTS + 1
    assert math.isclose(strip.points[-1].x, poses[-1].x_m)
    assert closures.type == LINE_LIST
    assert [(p.x, p.y) for p in closures.points] == [(0.0, 2.0), (1.0, 2.0)]
    assert len(decoded(trajectory_message(poses[:3], [], 9)).entities[0].lines) == 1
