"""Shared fixtures: dataset location, free ports, the one `wait_for`.

Import these as `from conftest import ...` (pytest loads this file as the module `conftest`;
`tests.conftest` would be a second copy of it). The service test kit,
`tests/service/app/svc_testkit.py`, is put on the import path here so that tests in any folder
import it as `svc_testkit`.
"""

from __future__ import annotations

import os
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
# The public recordings: ../shared/datasets beside the checkout, or MAPPING_DATASETS (an empty
# folder there gives what a fresh clone without the datasets gives).
DATASETS = Path(os.environ.get("MAPPING_DATASETS") or REPO_ROOT.parent / "shared" / "datasets")

_KIT_DIR = str(Path(__file__).resolve().parent / "service" / "app")
if _KIT_DIR not in sys.path:
    sys.path.append(_KIT_DIR)

T = TypeVar("T")


def dataset_path(*parts: str) -> Path:
    """Path to a shared dataset file; skips the test when it is absent.

    Tests that call this carry `@pytest.mark.datasets`.
    """
    path = DATASETS.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"dataset {path} not present (../shared/datasets is absent on a fresh clone)")
    return path


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(condition: Callable[[], T], timeout_s: float, what: str, period_s: float = 0.05) -> T:
    """Poll `condition` until it returns something truthy, and return that; fail the test after
    the deadline (no bare sleeps as synchronisation).

    An `Exception` from `condition` means "not ready yet" (connection refused, a 404, ...) and
    is reported if the deadline passes; to stop waiting at once (a process died), call
    `pytest.fail` in the condition: its exception is not an `Exception` and goes through.
    """
    deadline = time.monotonic() + timeout_s
    last_error: Exception | None = None
    while True:
        try:
            result = condition()
        except Exception as err:
            last_error = err
        else:
            if result:
                return result
        if time.monotonic() >= deadline:
            break
        time.sleep(period_s)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what} (last error: {last_error!r})")
