"""The live back end's thread (service/app/backend.py): it yields the cores to the pose path,
and composes the map only while somebody reads it."""

from __future__ import annotations

import math
import os
import sys
import threading
import time

import numpy as np
import pytest

from clients.wire import PoseFlag
from service.app import backend as backend_module
from service.app.backend import BACKEND_NICE, BackendScheduler, LiveBackend
from service.core.maps.grid import GridImage
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


def _read(backend: LiveBackend) -> GridImage:
    """The map as a reader gets it: asking again while the back end draws it."""
    deadline = time.monotonic() + 10.0
    while (image := backend.image()) is None:
        assert time.monotonic() < deadline
        time.sleep(0.005)
    return image


class _Clock:
    """The back end's `time`: the real clocks, with `monotonic` moved on by `offset_s`."""

    def __init__(self) -> None:
        self.offset_s = 0.0

    def monotonic(self) -> float:
        return time.monotonic() + self.offset_s

    def perf_counter(self) -> float:
        return time.perf_counter()


def _same_map(a: GridImage, b: GridImage) -> bool:
    return (a.origin_x_m, a.origin_y_m) == (b.origin_x_m, b.origin_y_m) and np.array_equal(
        a.occupancy, b.occupancy
    )


@pytest.mark.timeout(60)
def test_the_map_is_composed_only_while_somebody_reads_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """Nobody reads: the map's revision goes on, nothing is composed. A read has the back
    end's thread compose the map at its next turn (as the core has it then: never in the
    reader's thread); then the thread composes each revision for `WATCHED_S`, and the reads
    take that; after `WATCHED_S` without a read it stops again."""
    monkeypatch.setattr(backend_module, "RENDER_PERIOD_S", 0.05)
    monkeypatch.setattr(backend_module, "WATCHED_S", 1.0)
    clock = _Clock()  # the back end's: moved on past WATCHED_S below instead of slept through
    monkeypatch.setattr(backend_module, "time", clock)
    scheduler = BackendScheduler()
    session = SlamSession(map_resolution_m=0.05, keep_trajectory=False)
    compose = session.map_image
    composed: list[float] = []

    def counted() -> GridImage:
        composed.append(time.monotonic())
        return compose()

    session.map_image = counted  # type: ignore[method-assign]
    backend = LiveBackend(session, scheduler=scheduler)
    covariance = (1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-4)
    x_m = 0.0

    def drive(keyframes: int) -> None:
        nonlocal x_m
        for _ in range(keyframes):
            x_m += 0.4
            pose = Pose2D(x_m, 0.0, 0.0)
            estimate = PoseEstimate(1, pose, 1.0, PoseFlag.NONE, True, covariance)
            backend.submit(session.select(_room_scan(), estimate), 0)
        assert backend.wait_idle(30.0)

    try:
        drive(3)
        assert composed == []
        revision = backend.correction()[2]
        assert revision > 0  # the map's revision is published all the same

        reader = threading.get_ident()
        session.map_image = lambda: (  # type: ignore[method-assign]
            pytest.fail("composed in the reader's thread")
            if threading.get_ident() == reader
            else counted()
        )
        image = _read(backend)  # the first read: composed now, with every scan drawn
        assert len(composed) == 1
        assert _same_map(image, compose())
        assert backend.image() is image  # the same revision: not composed again
        assert len(composed) == 1

        drive(2)  # watched: the back end composes each new revision
        assert backend.correction()[2] > revision
        watched = len(composed)
        assert watched >= 2
        assert _same_map(_read(backend), compose())
        assert len(composed) == watched

        clock.offset_s += 1.2  # nobody read it for WATCHED_S
        drive(2)
        assert len(composed) == watched
        assert _same_map(_read(backend), compose())
        assert len(composed) == watched + 1
    finally:
        backend.close()
