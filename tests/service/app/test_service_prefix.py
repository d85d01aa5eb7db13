"""A real `mapping-service serve --prefix site-b/robots`: scans, poses and liveliness all live
under the configured prefix, and the default prefix's traffic is not taken for this service's."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh
from svc_testkit import ServiceProc, SimRobot, wait_for, zenoh_peer

from clients.keyexpr import DEFAULT_PREFIX, alive_key, pose_key, scan_key
from clients.wire import decode_pose

PREFIX = "site-b/robots"
ROBOT = "pfx-1"
SCANS = 20

pytestmark = pytest.mark.slow


@pytest.mark.timeout(90)
def test_non_default_prefix_end_to_end(tmp_path: Path) -> None:
    assert PREFIX != DEFAULT_PREFIX
    svc = ServiceProc(tmp_path / "data", prefix=PREFIX)
    svc.start()
    try:
        sid = svc.create_session(ROBOT)["id"]
        robot = SimRobot(ROBOT)
        poses: dict[str, list[int]] = {PREFIX: [], DEFAULT_PREFIX: []}
        lock = threading.Lock()
        with zenoh_peer(svc.zenoh_endpoint) as peer:

            def on_pose(sample: Any, prefix: str) -> None:
                with lock:
                    poses[prefix].append(decode_pose(sample.payload.to_bytes()).seq)

            subs = [
                peer.declare_subscriber(pose_key(ROBOT, p), lambda s, p=p: on_pose(s, p))
                for p in poses
            ]
            block = zenoh.CongestionControl.BLOCK
            other = peer.declare_publisher(scan_key(ROBOT), congestion_control=block)
            mine = peer.declare_publisher(scan_key(ROBOT, PREFIX), congestion_control=block)
            token = peer.liveliness().declare_token(alive_key(ROBOT, PREFIX))
            try:

                def robot_alive() -> bool:
                    robots = svc.json("/health")["robots"]
                    assert isinstance(robots, list)
                    return any(r["robot_id"] == ROBOT and r["alive"] for r in robots)

                wait_for(robot_alive, 30, f"the liveliness token under {PREFIX}")
                # Scans under the default prefix: not this service's.
                stranger = SimRobot(ROBOT, seed=9)
                for _ in range(5):
                    other.put(stranger.next_payload())

                def accepted() -> int:
                    return int(svc.json(f"/sessions/{sid}")["scans_accepted"])  # type: ignore[call-overload]

                # The service's subscription matches the configured prefix only.
                wait_for(lambda: mine.matching_status.matching, 30, f"a subscriber on {PREFIX}")
                while robot.seq < SCANS:
                    wait_for(lambda: robot.seq - accepted() < 8, 30, "room in the queue")
                    mine.put(robot.next_payload())
                sent = robot.seq
                wait_for(lambda: accepted() >= sent, 30, f"{sent} scans accepted")
                wait_for(lambda: len(poses[PREFIX]) >= sent, 30, f"{sent} poses on {PREFIX}")
            finally:
                token.undeclare()  # type: ignore[no-untyped-call]
                other.undeclare()  # type: ignore[no-untyped-call]
                mine.undeclare()  # type: ignore[no-untyped-call]
                for sub in subs:
                    sub.undeclare()
        session = svc.json(f"/sessions/{sid}")
        # Exactly the scans published under the configured prefix, none of the others.
        assert session["scans_accepted"] == session["poses"] == sent
        with lock:
            assert poses[PREFIX] == list(range(sent))
            assert poses[DEFAULT_PREFIX] == []
        metrics = svc.metrics()
        assert not any(
            k.startswith("mapping_scans_rejected_total") and v for k, v in metrics.items()
        )
    finally:
        assert svc.stop() == 0, svc.log_tail()
