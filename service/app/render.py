"""Map and trajectory files of a session (thin adapters over `service.mapio`)."""

from __future__ import annotations

from clients.wire import Pose
from service import mapio
from service.app.sessions import MapSnapshot
from service.core.types import Pose2D


def map_png(snapshot: MapSnapshot, *, trajectory: bool, robot: bool) -> bytes:
    last = snapshot.last_pose
    return mapio.render_png(
        snapshot.image,
        trajectory_xy=snapshot.trajectory_xy_m
        if trajectory and len(snapshot.trajectory_xy_m)
        else None,
        robot_pose=Pose2D(last.x_m, last.y_m, last.theta_rad) if robot and last else None,
    )


def map_pgm(snapshot: MapSnapshot) -> bytes:
    return mapio.to_pgm(snapshot.image)


def map_yaml(snapshot: MapSnapshot, image_file: str = "map.pgm") -> str:
    return mapio.to_yaml(snapshot.image, image_file)


def map_files(snapshot: MapSnapshot) -> dict[str, bytes]:
    """The files of a saved map: plain PNG, and the ROS map_server pair."""
    return {
        "map.png": map_png(snapshot, trajectory=False, robot=False),
        "map.pgm": map_pgm(snapshot),
        "map.yaml": map_yaml(snapshot).encode(),
    }


def trajectory_tum(poses: list[Pose]) -> str:
    return mapio.format_tum(
        [p.stamp_ns for p in poses], [Pose2D(p.x_m, p.y_m, p.theta_rad) for p in poses]
    )
