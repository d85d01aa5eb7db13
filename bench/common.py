"""Shared pieces of the benchmarks: statistics, machine facts, synthetic runs, trajectory errors."""

from __future__ import annotations

import datetime as dt
import logging
import math
import os
import platform
import subprocess
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.types import LaserScan, Pose2D

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parent.parent
FloatArray = npt.NDArray[np.float64]


class BenchError(Exception):
    """A benchmark could not run (missing piece, process that would not start, ...)."""


# ---------------------------------------------------------------------------------------------
# Statistics


@dataclass(frozen=True, slots=True)
class TimingSummary:
    """Per-call times in milliseconds."""

    n: int
    median_ms: float
    p99_ms: float
    mean_ms: float
    max_ms: float

    @classmethod
    def of_ns(cls, times_ns: Iterable[int] | npt.NDArray[Any]) -> TimingSummary:
        t = np.asarray(list(times_ns) if not isinstance(times_ns, np.ndarray) else times_ns)
        if t.size == 0:
            return cls(0, math.nan, math.nan, math.nan, math.nan)
        ms = t.astype(np.float64) / 1e6
        return cls(
            n=int(ms.size),
            median_ms=float(np.median(ms)),
            p99_ms=float(np.percentile(ms, 99)),
            mean_ms=float(ms.mean()),
            max_ms=float(ms.max()),
        )

    def as_dict(self) -> dict[str, float]:
        return {
            "n": self.n,
            "median_ms": self.median_ms,
            "p99_ms": self.p99_ms,
            "mean_ms": self.mean_ms,
            "max_ms": self.max_ms,
        }


@dataclass(frozen=True, slots=True)
class Target:
    """A target of the issue beside what this run measured."""

    name: str
    target: str
    measured: str
    passed: bool | None  # None: not measured in this run

    @property
    def verdict(self) -> str:
        return "n/a" if self.passed is None else ("PASS" if self.passed else "MISS")

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "target": self.target,
            "measured": self.measured,
            "passed": self.passed,
        }


# ---------------------------------------------------------------------------------------------
# Machine, versions, provenance


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def git_commit() -> str:
    """Short commit of the checkout, with `-dirty` when the work tree has changes."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def blas_info() -> str:
    try:
        deps = np.show_config(mode="dicts").get("Build Dependencies", {})
        blas = deps.get("blas", {})
        return f"{blas.get('name', '?')} {blas.get('version', '')}".strip()
    except Exception:  # show_config's shape changed across numpy versions
        return "unknown"


def machine_info() -> dict[str, Any]:
    """Facts for the report header, read off this machine now."""
    try:
        load1, load5, _ = os.getloadavg()
        load = f"{load1:.2f} (1 min), {load5:.2f} (5 min)"
    except OSError:
        load = "unknown"
    try:
        import psutil

        mem_gib = f"{psutil.virtual_memory().total / 2**30:.1f} GiB"
    except Exception:
        mem_gib = "unknown"
    return {
        "cpu_model": cpu_model(),
        "cores": os.cpu_count() or 0,
        "memory": mem_gib,
        "os": f"{platform.system()} {platform.release()} ({platform.machine()})",
        "python": platform.python_version(),
        "numpy": np.__version__,
        "blas": blas_info(),
        "zenoh": _version("eclipse-zenoh"),
        "kiss_icp": _version("kiss-icp"),
        "matplotlib": _version("matplotlib"),
        "date_utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "git_commit": git_commit(),
        "load_average_at_start": load,
        "openblas_env": os.environ.get("BENCH_OPENBLAS_ENV_REMOVED", "none set"),
        "command": " ".join(["python -m bench", *sys.argv[1:]]),
    }


# ---------------------------------------------------------------------------------------------
# Synthetic runs (the simulator of sensor_agent.sim.world)


@dataclass(slots=True)
class SyntheticRun:
    """Scans of a simulated UTM-30LX along a trajectory in a synthetic building, with truth."""

    seed: int
    spacing_m: float
    scans: list[LaserScan]
    truth: FloatArray  # (N, 3) x_m, y_m, theta_rad in the world frame
    loop_length_m: float
    notes: list[str] = field(default_factory=list)

    @property
    def length_m(self) -> float:
        return path_length_m(self.truth)

    @property
    def beam_count(self) -> int:
        return int(self.scans[0].ranges_m.shape[0]) if self.scans else 0


def path_length_m(poses: FloatArray) -> float:
    if poses.shape[0] < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1).sum())


def poses_to_array(poses: Any) -> FloatArray:
    """(N, 3) float64 from an (N, 3) array or a sequence of `Pose2D`-like triples."""
    if isinstance(poses, np.ndarray):
        arr = np.asarray(poses, dtype=np.float64)
    else:
        arr = np.array([(float(p[0]), float(p[1]), float(p[2])) for p in poses], dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise BenchError(f"expected (N, 3) poses, got shape {arr.shape}")
    return arr


def make_synthetic_run(
    seed: int = 1,
    *,
    spacing_m: float = 0.3,
    max_scans: int | None = None,
    laps: float = 1.0,
    size: str = "paper",
) -> SyntheticRun:
    """Simulate a UTM-30LX (270°, 1,081 beams) along the corridor loop of building `seed`.

    One scan every `spacing_m` of travel (or 10° of turn), as in the paper; `laps` > 1 drives
    the loop again; `max_scans` keeps the first scans only. `size` is the simulator's building
    preset ("paper": about 190 m x 50 m; "small": 48 m x 24 m).
    """
    try:
        from sensor_agent.sim import world as sim
    except ImportError as err:
        raise BenchError(f"the simulator sensor_agent.sim.world is not available: {err}") from err

    building = sim.generate_building(seed, size)  # type: ignore[arg-type]
    trajectory = sim.generate_trajectory(building, seed, spacing_m=spacing_m, laps=laps)
    truth = poses_to_array(trajectory.poses)
    stamps = np.asarray(trajectory.stamps_ns, dtype=np.int64)
    notes = [f"{size} building, seed {seed}, corridor loop {trajectory.loop_length_m:.0f} m"]
    if laps != 1.0:
        notes.append(f"{laps:.2f} laps of it")
    if max_scans is not None:
        truth, stamps = truth[:max_scans], stamps[:max_scans]
    return SyntheticRun(
        seed=seed,
        spacing_m=spacing_m,
        scans=simulate_scans(building, truth, stamps, seed),
        truth=truth,
        loop_length_m=float(trajectory.loop_length_m),
        notes=notes,
    )


def simulate_scans(
    building: Any, poses: FloatArray, stamps_ns: npt.NDArray[np.int64], seed: int
) -> list[LaserScan]:
    """UTM-30LX scans at `poses` (N, 3), as the estimator sees them (NaN for invalid beams)."""
    from sensor_agent.sim import world as sim

    model = sim.LaserModel.utm30lx()
    rng = np.random.default_rng(seed)
    scans: list[LaserScan] = []
    for (x, y, th), stamp_ns in zip(poses, stamps_ns, strict=True):
        sample = sim.simulate_scan(building, (float(x), float(y), float(th)), model, rng)
        scans.append(
            LaserScan(
                stamp_ns=int(stamp_ns),
                angle_min_rad=float(model.angle_min_rad),
                angle_increment_rad=float(model.angle_increment_rad),
                ranges_m=np.asarray(sample.ranges_m, dtype=np.float64),
                range_min_m=float(model.range_min_m),
                range_max_m=float(model.range_max_m),
            )
        )
    return scans


# ---------------------------------------------------------------------------------------------
# Trajectory errors against ground truth


def _wrap(a: FloatArray) -> FloatArray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def align_se2(est: FloatArray, truth: FloatArray) -> FloatArray:
    """`est` moved by the rigid 2D transform that best fits its positions onto `truth` (Horn)."""
    mu_e = est[:, :2].mean(axis=0)
    mu_t = truth[:, :2].mean(axis=0)
    a = est[:, :2] - mu_e
    b = truth[:, :2] - mu_t
    rot = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b)))
    c, s = math.cos(rot), math.sin(rot)
    xy = a @ np.array([[c, s], [-s, c]]) + mu_t
    return np.column_stack((xy, _wrap(est[:, 2] + rot)))


def relative_poses(poses: FloatArray, step: int = 1) -> FloatArray:
    """(N-step, 3) motion from pose i to pose i+step, in the frame of pose i."""
    a, b = poses[:-step], poses[step:]
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack((c * dx + s * dy, -s * dx + c * dy, _wrap(b[:, 2] - a[:, 2])))


def trajectory_errors(est: Sequence[Pose2D] | FloatArray, truth: FloatArray) -> dict[str, float]:
    """Frame-independent errors of an estimated trajectory against ground truth.

    - `ate_rmse_m`: RMS position error after the best rigid alignment;
    - `rpe_mean_m`, `rpe_rot_mean_deg`: mean error of the scan-to-scan motions;
    - `heading_err_max_deg`: largest heading error after the alignment;
    - `end_error_m`: error of the last pose seen from the first one (the loop gap on a loop).
    """
    e = poses_to_array(est)
    if e.shape[0] < 2:
        return {
            "ate_rmse_m": math.nan,
            "rpe_mean_m": math.nan,
            "rpe_rot_mean_deg": math.nan,
            "heading_err_max_deg": math.nan,
            "end_error_m": math.nan,
        }
    t = truth[: e.shape[0]]
    aligned = align_se2(e, t)
    ate = float(np.sqrt(np.mean(np.sum((aligned[:, :2] - t[:, :2]) ** 2, axis=1))))
    rel_e, rel_t = relative_poses(e), relative_poses(t)
    rpe = np.hypot(rel_e[:, 0] - rel_t[:, 0], rel_e[:, 1] - rel_t[:, 1])
    rpe_rot = np.abs(_wrap(rel_e[:, 2] - rel_t[:, 2]))
    end_e = relative_poses(e[[0, -1]])[0]
    end_t = relative_poses(t[[0, -1]])[0]
    return {
        "ate_rmse_m": ate,
        "rpe_mean_m": float(rpe.mean()),
        "rpe_rot_mean_deg": float(np.degrees(rpe_rot.mean())),
        "heading_err_max_deg": float(np.degrees(np.abs(_wrap(aligned[:, 2] - t[:, 2])).max())),
        "end_error_m": float(np.hypot(end_e[0] - end_t[0], end_e[1] - end_t[1])),
    }
