import subprocess
import sys

import pytest


@pytest.mark.parametrize("module", ["service.cli", "sensor_agent.cli", "clients.cli"])
def test_help_works(module: str) -> None:
    out = subprocess.run(
        [sys.executable, "-m", module, "--help"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert "usage:" in out.stdout
