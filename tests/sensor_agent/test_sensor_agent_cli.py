"""`sensor-agent` as a user runs it: argument errors, one-line failures, replay and emulation."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from clients.recording import RecordingWriter
from clients.wire import Scan, decode_scan, encode_scan
from clients.zenoh_config import build_zenoh_config
from sensor_agent.cli import main

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def run_agent(*args: str, timeout_s: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sensor_agent.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
        env=ENV,
        cwd=REPO,
    )


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["--robot-id", "r1"],
        ["--robot-id", "r1", "--emulate", "--device", "/dev/ttyACM0"],
        ["--robot-id", "a/b", "--emulate"],
        ["--robot-id", "r1", "--emulate", "--prefix", "robots/*"],
        ["--robot-id", "r1", "--replay", "x.bag", "--rate", "-1"],
        ["--robot-id", "r1", "--device", "/dev/ttyACM0", "--fault-garbage", "0.1"],
        ["--robot-id", "r1", "--emulate", "--fault-corrupt-lines", "2"],
    ],
)
def test_bad_arguments_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert "error:" in capsys.readouterr().err


def test_an_unopenable_device_is_one_line_and_exit_1() -> None:
    out = run_agent("--robot-id", "r1", "--device", "/dev/does-not-exist")
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert lines == [
        "sensor-agent: error: cannot open /dev/does-not-exist: No such file or directory"
    ]


def test_a_missing_log_is_one_line_and_exit_1(tmp_path: Path) -> None:
    out = run_agent("--robot-id", "r1", "--replay", str(tmp_path / "nope.bag"))
    assert out.returncode == 1
    assert len(out.stderr.strip().splitlines()) == 1
    assert "nope.bag" in out.stderr


@pytest.fixture
def short_dir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="sa-cli-") as d:  # unix socket paths are short
        yield Path(d)


def write_log(path: Path, n: int, period_ms: int) -> None:
    with RecordingWriter(path) as w:
        for i in range(n):
            t = 1_700_000_000_000_000_000 + i * period_ms * 1_000_000
            w.append(
                encode_scan(
                    Scan(
                        robot_id="old-name",
                        seq=i,
                        sensor_stamp_ns=t,
                        host_stamp_ns=t,
                        angle_min_rad=-1.0,
                        angle_increment_rad=0.01,
                        range_min_m=0.02,
                        range_max_m=30.0,
                        ranges_m=np.full(201, 1.0 + i / 1000),
                    )
                )
            )


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_replay_publishes_every_scan_then_exits_0(short_dir: Path) -> None:
    n = 30
    write_log(short_dir / "log.mrec", n, period_ms=40)
    endpoint = f"unixsock-stream/{short_dir / 'z.sock'}"
    received: list[Scan] = []
    alive: list[str] = []
    with zenoh.open(build_zenoh_config(listen=[endpoint])) as session:
        sub = session.declare_subscriber(
            "fleet/*/scan", lambda s: received.append(decode_scan(s.payload.to_bytes()))
        )
        tokens = session.liveliness().declare_subscriber(
            "fleet/*/alive",
            lambda s: alive.append("PUT" if s.kind == zenoh.SampleKind.PUT else "DELETE"),
        )
        out = run_agent(
            "--robot-id",
            "replayer",
            "--replay",
            str(short_dir / "log.mrec"),
            "--rate",
            "1",
            "--zenoh-connect",
            endpoint,
            "--prefix",
            "fleet",
        )
        deadline = time.monotonic() + 5
        while len(alive) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        sub.undeclare()
        tokens.undeclare()
    assert out.returncode == 0, out.stderr
    assert "replay finished: 30 scans" in out.stderr
    assert received, out.stderr
    seqs = [s.seq for s in received]
    # The first puts may precede the subscription's arrival; after that nothing is missing.
    assert seqs == list(range(n - len(seqs), n))
    assert {s.robot_id for s in received} == {"replayer"}
    assert received[-1].host_stamp_ns == 1_700_000_000_000_000_000 + (n - 1) * 40_000_000
    assert alive == ["PUT", "DELETE"]


@pytest.mark.slow
@pytest.mark.timeout(90)
def test_emulate_mode_streams_until_sigterm(short_dir: Path) -> None:
    """Also: while no subscriber matches, the agent says so once instead of counting
    `published=` up as if someone listened; it says again when one appears."""
    log_path = short_dir / "agent.log"
    endpoint = f"unixsock-stream/{short_dir / 'z.sock'}"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "sensor_agent.cli",
                "--robot-id",
                "emu-1",
                "--emulate",
                "--world-seed",
                "3",
                "--stats-interval",
                "0.3",
                "--zenoh-listen",
                endpoint,
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=ENV,
            cwd=REPO,
        )
    try:
        wait_log(proc, log_path, "no subscriber matches robots/emu-1/scan", 40)
        time.sleep(1.0)  # three more summary periods: still one line, no counters
        text = log_path.read_text()
        assert text.count("no subscriber matches") == 1, text
        assert "published=" not in text, text
        with zenoh.open(build_zenoh_config(connect=[endpoint])) as session:
            received: list[int] = []
            sub = session.declare_subscriber("robots/*/scan", lambda s: received.append(1))
            wait_log(proc, log_path, "a subscriber matches robots/emu-1/scan", 20)
            deadline = time.monotonic() + 40
            while "published=" not in log_path.read_text() or " 0.0 Hz" in last_summary(log_path):
                assert proc.poll() is None, log_path.read_text()
                assert time.monotonic() < deadline, log_path.read_text()
                time.sleep(0.1)
            assert received
            sub.undeclare()
            wait_log(proc, log_path, "no subscriber matches robots/emu-1/scan any more", 20)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log_path.read_text()
    assert "source: emulator (world seed 3)" in text
    assert "SOKUIKI Sensor TOP-URG UTM-30LX" in text
    assert "final:" in text


def wait_log(proc: subprocess.Popen[bytes], path: Path, fragment: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while fragment not in path.read_text():
        assert proc.poll() is None, path.read_text()
        assert time.monotonic() < deadline, f"no {fragment!r} in:\n{path.read_text()}"
        time.sleep(0.05)


def last_summary(path: Path) -> str:
    lines = [ln for ln in path.read_text().splitlines() if "published=" in ln]
    return lines[-1] if lines else " 0.0 Hz"
