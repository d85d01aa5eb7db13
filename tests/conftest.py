"""Shared fixtures: dataset location, free ports, isolated Zenoh sessions."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
# MAPPING_DATASETS points the tests at another copy of the recordings.
DATASETS = Path(os.environ.get("MAPPING_DATASETS") or REPO_ROOT.parent / "shared" / "datasets")


def dataset_path(*parts: str) -> Path:
    """Path to a shared dataset file; skips the test when the folder is absent."""
    path = DATASETS.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"dataset {path} not present (../shared/datasets is absent on a fresh clone)")
    return path


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(
    condition: Callable[[], object], timeout_s: float, what: str, period_s: float = 0.05
) -> object:
    """Poll `condition` until truthy; fail the test after the deadline (no bare sleeps).

    Exceptions from `condition` mean "not ready yet" (connection refused, 404, ...).
    """
    deadline = time.monotonic() + timeout_s
    last_error: Exception | None = None
    while time.monotonic() < deadline:
        try:
            result = condition()
        except Exception as err:
            last_error = err
        else:
            if result:
                return result
        time.sleep(period_s)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what} (last error: {last_error!r})")
