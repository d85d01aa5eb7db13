"""`mapping-service map`: outputs of a real subprocess run, and clean failures."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO_ROOT, dataset_path

from clients.recording import RecordingWriter
from clients.wire import OdometryPose, Scan, encode_scan

N_SCANS = 60


def _run_cli(*args: str | Path, timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    return subprocess.run(
        [sys.executable, "-m", "service.cli", "map", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
        cwd=REPO_ROOT,
        env=env,
    )


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[int]]:
    """A short synthetic sequence (UTM-30LX in a small building) as an .mrec with odometry."""
    from sensor_agent.sim import world as sim

    world = sim.generate_building(3, "small")
    trajectory = sim.generate_trajectory(world, 3, spacing_m=0.3)
    model = sim.LaserModel.utm30lx()
    rng = np.random.default_rng(3)
    path = tmp_path_factory.mktemp("offline") / "sim.mrec"
    stamps = []
    with RecordingWriter(path) as writer:
        for i in range(N_SCANS):
            x, y, th = (float(v) for v in trajectory.poses[i])
            stamp = int(trajectory.stamps_ns[i]) + 123  # sub-microsecond part must survive
            sample = sim.simulate_scan(world, (x, y, th), model, rng)
            scan = Scan(
                robot_id="sim-3",
                seq=i,
                sensor_stamp_ns=stamp,
                host_stamp_ns=stamp,
                angle_min_rad=model.angle_min_rad,
                angle_increment_rad=model.angle_increment_rad,
                range_min_m=model.range_min_m,
                range_max_m=model.range_max_m,
                ranges_m=sample.ranges_m,
                odom=OdometryPose(x, y, th, stamp),
                ranges_encoding="f32_m",
            )
            writer.append(encode_scan(scan))
            stamps.append(stamp)
    return path, stamps


def _pgm_header(data: bytes) -> tuple[int, int, int, int]:
    """Width, height, maxval and pixel offset of a binary PGM (P5), skipping # comments."""
    assert data.startswith(b"P5")
    values: list[int] = []
    pos = 2
    while len(values) < 3:
        while data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end : end + 1].isspace():
            end += 1
        values.append(int(data[pos:end]))
        pos = end
    return values[0], values[1], values[2], pos + 1  # one whitespace byte before the pixels


def _check_outputs(out: Path, stamps: list[int]) -> dict[str, object]:
    for name in ("trajectory.tum", "map.png", "map.pgm", "map.yaml", "report.json"):
        assert (out / name).is_file(), name
        assert (out / name).stat().st_size > 0, name

    lines = (out / "trajectory.tum").read_text().splitlines()
    assert len(lines) == len(stamps)
    for line, stamp_ns in zip(lines, stamps, strict=True):
        cols = line.split()
        assert len(cols) == 8, line
        assert len(cols[0].split(".")[1]) >= 6, "stamp needs at least 6 decimals"
        assert float(cols[0]) == pytest.approx(stamp_ns / 1e9, abs=2e-6)
        x, y, z, qx, qy, qz, qw = map(float, cols[1:])
        assert all(math.isfinite(v) for v in (x, y, z, qx, qy, qz, qw))
        assert z == qx == qy == 0.0
        assert qz * qz + qw * qw == pytest.approx(1.0, abs=1e-6)

    pgm = (out / "map.pgm").read_bytes()
    width, height, maxval, offset = _pgm_header(pgm)
    assert width > 0
    assert height > 0
    assert maxval == 255
    assert len(pgm) - offset == width * height

    assert (out / "map.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")

    yaml_text = (out / "map.yaml").read_text()
    keys = {line.split(":", 1)[0].strip() for line in yaml_text.splitlines() if ":" in line}
    for key in ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"):
        assert key in keys, key
    assert "map.pgm" in yaml_text

    report = json.loads((out / "report.json").read_text())
    assert report["scans"] == len(stamps)
    assert report["median_ms_per_scan"] > 0
    for key in ("p90_ms_per_scan", "p99_ms_per_scan", "quality", "flags", "input", "map"):
        assert key in report, key
    assert 0.0 <= report["quality"]["mean"] <= 1.0
    assert 0.0 <= report["quality"]["fraction_below_0_5"] <= 1.0
    assert report["map"]["resolution_m"] == pytest.approx(0.05)
    assert isinstance(report, dict)
    return report


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_map_recording_writes_every_output(
    recording: tuple[Path, list[int]], tmp_path: Path
) -> None:
    path, stamps = recording
    out = tmp_path / "out"
    result = _run_cli(path, "--out", out)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert f"{N_SCANS} scans" in result.stdout
    report = _check_outputs(out, stamps)
    assert report["input"]["kind"] == "mrec"  # type: ignore[index]
    assert report["scans_with_odometry"] == N_SCANS

    out2 = tmp_path / "no-odom"
    result = _run_cli(path, "--out", out2, "--no-odom", "--no-progress", "--resolution", "0.1")
    assert result.returncode == 0, result.stderr
    report = json.loads((out2 / "report.json").read_text())
    assert report["scans_with_odometry"] == 0
    assert report["input"]["use_odometry"] is False
    assert report["map"]["resolution_m"] == pytest.approx(0.1)
    # Loops are closed by default: the back end reports what it did and what it cost.
    loops = report["loop_closures"]
    assert set(loops) == {"accepted", "rejected", "search_s", "optimise_s", "solver_restarts"}
    assert loops["accepted"] >= 0
    assert loops["solver_restarts"] == 0
    assert report["backend_s"] > 0.0
    assert "loop closure:" in result.stdout

    out3 = tmp_path / "front-end"
    result = _run_cli(path, "--out", out3, "--no-odom", "--no-progress", "--no-loop-closure")
    assert result.returncode == 0, result.stderr
    report = json.loads((out3 / "report.json").read_text())
    assert report["loop_closures"] is None
    assert report["backend_s"] == 0.0
    assert "loop closure:" not in result.stdout


@pytest.mark.slow
@pytest.mark.timeout(180)
@pytest.mark.parametrize("front_end", ["matcher", "paper"])
def test_map_with_another_front_end(
    front_end: str, recording: tuple[Path, list[int]], tmp_path: Path
) -> None:
    """`--front-end matcher|paper` maps the same recording through the same outputs, and its
    trajectory follows the simulated truth. Poses are compared relative to the first one: the
    matcher's map frame is the first scan's, the paper's y axis is the first scan's major wall
    (the paper's standard direction)."""
    from sensor_agent.sim import world as sim

    path, stamps = recording
    out = tmp_path / front_end
    result = _run_cli(path, "--out", out, "--no-odom", "--no-progress", "--front-end", front_end)
    assert result.returncode == 0, result.stderr
    report = _check_outputs(out, stamps)
    assert report["front_end"] == front_end
    truth = sim.generate_trajectory(sim.generate_building(3, "small"), 3, spacing_m=0.3).poses
    rows = [line.split() for line in (out / "trajectory.tum").read_text().splitlines()]
    est = np.array(
        [[float(r[1]), float(r[2]), 2.0 * math.atan2(float(r[6]), float(r[7]))] for r in rows]
    )

    def relative(poses: np.ndarray) -> np.ndarray:
        c, s = math.cos(poses[0, 2]), math.sin(poses[0, 2])
        d = poses[:, :2] - poses[0, :2]
        return np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]))

    error_m = np.hypot(*(relative(est) - relative(truth[:N_SCANS])).T)
    # 60 scans, 18 m at the paper's spacing, no odometry: within 0.3 m everywhere.
    assert float(np.max(error_m)) < 0.3, error_m.max()


def test_the_front_end_choices_are_the_cores() -> None:
    """The CLI spells the front ends and the default out (it starts without importing the
    core): the same, the default first."""
    from service.app import store
    from service.cli import DEFAULT_FRONT_END, FRONT_END_CHOICES, SERVE_FRONT_END_CHOICES
    from service.core import slam

    assert FRONT_END_CHOICES == slam.FRONT_ENDS
    assert DEFAULT_FRONT_END == slam.DEFAULT_FRONT_END == slam.FRONT_ENDS[0] == "matcher"
    assert SERVE_FRONT_END_CHOICES == store.SESSION_FRONT_ENDS


def _assert_one_line_error(result: subprocess.CompletedProcess[str]) -> None:
    assert result.returncode == 2, result
    assert "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("mapping-service map: error: ")


def test_unreadable_inputs_fail_cleanly(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(os.urandom(4096))
    result = _run_cli(garbage, "--out", tmp_path / "o1")
    _assert_one_line_error(result)
    assert "not a ROS 1 bag" in result.stderr
    assert not (tmp_path / "o1").exists()

    result = _run_cli(tmp_path / "absent.bag", "--out", tmp_path / "o2")
    _assert_one_line_error(result)
    assert "no such file" in result.stderr


@pytest.mark.datasets
def test_wrong_topic_fails_cleanly(tmp_path: Path) -> None:
    bag = dataset_path("urg-04lx-demo", "laser_scan_matcher_demo.bag")
    result = _run_cli(bag, "--out", tmp_path / "o", "--scan-topic", "/laser")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "no scans on /laser" in result.stderr.splitlines()[-1]


@pytest.mark.datasets
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_map_damaged_urg_bag(tmp_path: Path) -> None:
    """The URG-04LX demo bag (malformed index records) maps through the tolerant reader."""
    bag = dataset_path("urg-04lx-demo", "laser_scan_matcher_demo.bag")
    out = tmp_path / "urg"
    result = _run_cli(bag, "--out", out, "--no-progress", timeout_s=220)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["scans"] == 360
    assert report["input"]["tolerant_reader"] is True
    assert report["beam_counts"] == [681]
    assert len((out / "trajectory.tum").read_text().splitlines()) == 360


def _tum_relation_error_m(trajectory: Path, relations: Path) -> float:
    """Mean translational relation error of a `trajectory.tum` (the relation metric)."""
    from bench.worlds import read_tum
    from service.core.metrics import parse_relations, relation_errors
    from service.core.types import Pose2D

    stamps, xyt = read_tum(trajectory)
    poses = [Pose2D(*map(float, row)) for row in xyt]
    errors = relation_errors(stamps, poses, parse_relations(relations.read_text().splitlines()))
    assert errors.missing == 0
    return errors.trans_mean_m


@pytest.mark.datasets
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_map_intel_with_its_defaults(tmp_path: Path) -> None:
    """Intel as a user maps it (odometry and loop closure on). Its odometry turns ~0.1° per scan
    away from the walls; trusted at a fixed σ it carried the heading 45° off in clutter (1.10 m);
    gtsam 4.3's iSAM2 (Cholesky) also failed on the graph and took the run down with it."""
    bag = dataset_path("intel", "intel.sort.bag")
    out = tmp_path / "intel"
    result = _run_cli(bag, "--out", out, "--no-progress", timeout_s=280)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    assert report["scans"] == 13631
    assert report["loop_closures"]["accepted"] > 100
    error_m = _tum_relation_error_m(out / "trajectory.tum", bag.parent / "intel.relations")
    assert error_m < 0.75, error_m  # 0.575 m measured
