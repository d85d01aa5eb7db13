"""Small things a newcomer tripped on: `map --out` checked before the input is read, the
SPDX licence string, and MAPPING_DATASETS for the recordings' location."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

from conftest import REPO_ROOT


def _map(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", "map", *args, "--no-progress"],
        capture_output=True, text=True, cwd=REPO_ROOT, timeout=60, check=False,
    )  # fmt: skip


def test_map_out_is_checked_before_the_input_is_read(tmp_path: Path) -> None:
    missing = str(tmp_path / "no-such.bag")  # reading it would fail with exit 2
    done = _map(missing, "--out", "/etc/passwd")
    assert done.returncode == 1, done.stderr
    assert "/etc/passwd exists and is not a directory" in done.stderr
    assert "no-such.bag" not in done.stderr
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    done = _map(missing, "--out", str(a_file / "sub"))
    assert done.returncode == 1
    assert "is not a directory" in done.stderr
    done = _map(missing, "--out", str(tmp_path / "new" / "out"))
    assert done.returncode == 2  # a creatable folder: now the input is read, and is missing
    assert "no such file" in done.stderr


def test_pyproject_uses_the_spdx_license_string() -> None:
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
    assert project["project"]["license"] == "Apache-2.0"
    # setuptools reads the SPDX string from 77 on; older ones warn or refuse.
    assert "setuptools>=77" in project["build-system"]["requires"]


def test_mapping_datasets_points_the_tests_at_another_copy(tmp_path: Path) -> None:
    env = {**os.environ, "MAPPING_DATASETS": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "-c", "import conftest; print(conftest.DATASETS)"],
        capture_output=True, text=True, cwd=REPO_ROOT / "tests", env=env, timeout=60,
        check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(tmp_path)


def test_sensor_agent_zenoh_options_have_help() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "sensor_agent.cli", "--help"],
        capture_output=True, text=True, cwd=REPO_ROOT, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0
    text = " ".join(done.stdout.split())
    assert "--zenoh-connect ENDPOINT Zenoh router or service to connect to" in text
    assert "--zenoh-listen ENDPOINT endpoint to accept Zenoh peers on" in text
