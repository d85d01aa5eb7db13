"""The live back end's thread yields the cores to the pose path (service/app/backend.py)."""

from __future__ import annotations

import math
import os
import sys
import threading

import numpy as np
import pytest

from clients.wire import PoseFlag
from service.app.backend import BACKEND_NICE, BackendScheduler, LiveBackend
from service.core.slam import SlamSession
from service.core.types import LaserScan, Pose2D, PoseEstimate


def _room_scan() -> LaserScan:
    """A 4 x 6 m room seen from its middle, 1,081 beams over 270 degrees."""
    angles = np.linspace(-0.75 * math.pi, 0.75 * math.pi, 1081)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        ranges = np.minimum(np.abs(3.0 / c), np.abs(2.0 / s))
    return LaserScan(1, float(angles[0]), float(angles[1] - angles[0]), ranges, 0.02, 30.0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a thread's own nice is Linux's")
def test_the_back_end_thread_runs_nicer_than_the_pose_path() -> None:
    scheduler = BackendScheduler()
    session = SlamSession(map_resolution_m=0.05, keep_trajectory=False)
    backend = LiveBackend(session, scheduler=scheduler)
    try:
        covariance = (1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-4)
        estimate = PoseEstimate(1, Pose2D(0.0, 0.0, 0.0), 1.0, PoseFlag.NONE, True, covariance)
        backend.submit(session.select(_room_scan(), estimate), 0)
        assert backend.wait_idle(30.0)
        assert backend.snapshot().nodes == 1
        thread = scheduler._thread
        assert thread is not None
        assert thread.native_id is not None
        ours = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        theirs = os.getpriority(os.PRIO_PROCESS, thread.native_id)
        assert theirs == min(19, ours + BACKEND_NICE)
    finally:
        backend.close()
