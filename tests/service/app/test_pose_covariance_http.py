"""GET pose and the trajectory carry each pose's covariance (the real runtime and HTTP app)."""

from __future__ import annotations

from fastapi.testclient import TestClient
from svc_testkit import (  # noqa: F401  # runtime_*: pytest fixtures used by name
    SimRobot,
    feed,
    runtime_factory_fixture,
    runtime_fixture,
)

from service.app.api.app import create_app
from service.app.runtime import MappingRuntime


def test_the_service_serves_each_pose_with_its_covariance(runtime: MappingRuntime) -> None:
    """Through the real runtime and HTTP app: GET pose and the trajectory carry the matrix."""
    with TestClient(create_app(runtime)) as client:
        sid = client.post("/sessions", json={"robot_id": "amr-c"}).json()["id"]
        feed(runtime, SimRobot("amr-c"), 30)
        pose = client.get(f"/sessions/{sid}/pose").json()
        cov = pose["covariance"]
        assert len(cov) == 9
        assert min(cov[0], cov[4], cov[8]) > 0.0  # a pose after the first is uncertain
        poses = client.get(f"/sessions/{sid}/trajectory").json()["poses"]
        assert all(p["covariance"] is not None for p in poses[1:])
