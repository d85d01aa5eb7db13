import subprocess
import sys
from pathlib import Path

import pytest

import service.cli as service_cli


def _help(module: str, *args: str) -> subprocess.CompletedProcess[str]:
    """`python -m module [args] --help`, run for real."""
    return subprocess.run(
        [sys.executable, "-m", module, *args, "--help"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize("module", ["service.cli", "sensor_agent.cli", "clients.cli"])
def test_help_works(module: str) -> None:
    out = _help(module)
    assert out.returncode == 0, out.stderr
    assert "usage:" in out.stdout


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("argv", "verbosity"),
    [
        (["fsck", "{dir}", "-v"], 1),  # after the command, as the docs write `serve ... -v`
        (["-v", "fsck", "{dir}"], 1),
        (["-v", "fsck", "{dir}", "-v"], 2),  # both places count
        (["fsck", "{dir}"], 0),
    ],
)
def test_verbose_is_accepted_before_and_after_the_command(
    argv: list[str], verbosity: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[int] = []
    monkeypatch.setattr(service_cli, "configure_logging", seen.append)
    code = service_cli.main([a.format(dir=tmp_path) for a in argv])
    assert code == 0  # an empty data directory: nothing damaged
    assert seen == [verbosity]


def test_every_subcommand_lists_verbose() -> None:
    out = _help("service.cli", "serve")
    assert out.returncode == 0, out.stderr
    assert "-v, --verbose" in out.stdout
