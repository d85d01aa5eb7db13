"""bench.cpu_budget's exact per-thread CPU split."""

from __future__ import annotations

import os
import threading
import time

import pytest

from bench.cpu_budget import thread_cpu, thread_split

pytestmark = pytest.mark.timeout(60)


def test_thread_split_labels_python_threads_by_name_and_zenoh_as_one() -> None:
    before = {1: ("python", 1.0), 2: ("rx-0", 0.5), 3: ("tx-0", 0.25)}
    after = {1: ("python", 1.5), 2: ("rx-0", 1.0), 3: ("tx-0", 0.5), 4: ("python", 0.125)}
    split = thread_split(before, after, {1: "ingest", 4: "backend"})
    # A thread born between the snapshots counts whole; Zenoh's runtime threads as one.
    assert split == {"ingest": 0.5, "zenoh (native)": 0.75, "backend": 0.125}


def test_thread_cpu_sees_a_busy_thread_of_this_process() -> None:
    native: list[int] = []
    spun, release = threading.Event(), threading.Event()

    def spin() -> None:
        native.append(threading.get_native_id())
        end = time.thread_time() + 0.3
        while time.thread_time() < end:
            pass
        spun.set()
        release.wait(timeout=30)  # alive, so that /proc still lists it

    before = thread_cpu(os.getpid())
    worker = threading.Thread(target=spin, name="spinner")
    worker.start()
    try:
        assert spun.wait(timeout=30)
        after = thread_cpu(os.getpid())
    finally:
        release.set()
        worker.join(timeout=30)
    assert threading.get_native_id() in before
    assert native[0] not in before
    comm, cpu_s = after[native[0]]
    assert comm  # the OS's name for it
    assert 0.25 <= cpu_s < 5.0
    assert thread_split(before, after, {native[0]: "spinner"})["spinner"] == cpu_s
