"""Section 3: how the per-scan cost grows with the map over a long synthetic run."""

from __future__ import annotations

import gc
import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import psutil

from bench.common import SyntheticRun, Target, TimingSummary, trajectory_errors
from bench.profiling import profile_calls
from service.core.types import LaserScan, Pose2D

log = logging.getLogger(__name__)

TARGET_FLAT = 0.20  # ±20 % between the first and the last 10 % of the run


def _grid_cells(grid: Any) -> int | None:
    try:
        image = grid.snapshot()
    except Exception:  # a grid without snapshot support: report no size
        return None
    data = getattr(image, "occupancy", image)  # GridImage.occupancy: (H, W) int8
    shape = getattr(data, "shape", None)
    return int(np.prod(shape)) if shape is not None else None


@dataclass(frozen=True, slots=True)
class StepTimes:
    estimator_ns: int
    grid_ns: int
    cpu_ns: int  # process CPU time of the whole step


class Pipeline:
    """One estimator and one occupancy grid, fed as a mapping session feeds them."""

    def __init__(self, keyframes_only: bool) -> None:
        from service.core.maps.grid import OccupancyGrid
        from service.core.slam import make_frontend

        self.estimator = make_frontend()
        self.grid = OccupancyGrid()
        self.keyframes_only = keyframes_only
        self.integrations = 0

    def step(self, scan: LaserScan) -> tuple[StepTimes, Pose2D]:
        c0, t0 = time.process_time_ns(), time.perf_counter_ns()
        e = self.estimator.process(scan)
        t1 = time.perf_counter_ns()
        if e.is_keyframe or not self.keyframes_only:
            self.grid.integrate(scan, e.pose)
            self.integrations += 1
        t2 = time.perf_counter_ns()
        return StepTimes(t1 - t0, t2 - t1, time.process_time_ns() - c0), e.pose

    def run(self, scan: LaserScan) -> None:
        self.step(scan)


def run_growth(
    run: SyntheticRun, *, keyframes_only: bool = True, profile: bool = True
) -> dict[str, Any]:
    """Per-scan cost and memory at the start and at the end of a long run.

    One pipeline (estimator, then the grid on keyframes, as a session does) drives the whole
    run; its time per scan over the run is kept for the plot, its RSS growth every 50 scans.
    The verdict compares costs measured side by side: during the last tenth of the run, a
    second, fresh pipeline processes the first tenth's scans, interleaved scan by scan with the
    grown one, so that both windows see the same machine (the run's first and last tenth cover
    the same corridors, see `make_synthetic_run(laps=...)`).
    """
    proc = psutil.Process()
    gc.collect()
    rss0 = proc.memory_info().rss
    n = len(run.scans)
    tenth = max(2, n // 10)
    grown = Pipeline(keyframes_only)
    fresh = Pipeline(keyframes_only)
    seq: list[StepTimes] = []
    side: list[StepTimes] = []  # the fresh pipeline on scans[0 : tenth]
    poses = np.zeros((n, 3))
    rss_trace: list[tuple[int, float]] = []
    cells_first: int | None = None
    rss_before_side = 0.0
    for i, scan in enumerate(run.scans):
        k = i - (n - tenth)
        if k == 0:
            rss_before_side = (proc.memory_info().rss - rss0) / 2**20
        if k >= 0 and k % 2 == 1:
            side.append(fresh.step(run.scans[k])[0])
        times, pose = grown.step(scan)
        seq.append(times)
        poses[i] = pose
        if k >= 0 and k % 2 == 0:
            side.append(fresh.step(run.scans[k])[0])
        if k < 0 and (i % 50 == 0 or i == n - tenth - 1):
            rss_trace.append((i, (proc.memory_info().rss - rss0) / 2**20))
        if i == tenth:
            cells_first = _grid_cells(grown.grid)  # outside the timed calls

    def wall(ts: list[StepTimes]) -> np.ndarray:
        return np.array([t.estimator_ns + t.grid_ns for t in ts], dtype=np.int64)

    def cpu(ts: list[StepTimes]) -> np.ndarray:
        return np.array([t.cpu_ns for t in ts], dtype=np.int64)

    def mean_ms(ts: list[StepTimes], attr: str) -> float:
        return float(np.mean([getattr(t, attr) for t in ts]) / 1e6)

    # Side by side: the fresh pipeline's first scan initialises it and is left out.
    fresh_t, grown_t = side[1:], seq[n - tenth :]
    first, last = TimingSummary.of_ns(wall(fresh_t)), TimingSummary.of_ns(wall(grown_t))
    first_cpu, last_cpu = TimingSummary.of_ns(cpu(fresh_t)), TimingSummary.of_ns(cpu(grown_t))
    change = last.median_ms / first.median_ms - 1.0
    # The same windows from the single sequential pass, measured minutes apart.
    seq_first = TimingSummary.of_ns(wall(seq[1:tenth]))
    seq_change = last.median_ms / seq_first.median_ms - 1.0
    trace_i = [float(i) for i, _ in rss_trace]
    trace_mib = [mib for _, mib in rss_trace]
    cum_m = np.concatenate(
        ([0.0], np.cumsum(np.linalg.norm(np.diff(run.truth[:, :2], axis=0), axis=1)))
    )
    result: dict[str, Any] = {
        "scans": n,
        "length_m": run.length_m,
        "spacing_m": run.spacing_m,
        "seed": run.seed,
        "notes": run.notes,
        "grid": True,
        "grid_integrations": grown.integrations,
        "keyframes_only": keyframes_only,
        "grid_cells_after_first_10pct": cells_first,
        "grid_cells_end": _grid_cells(grown.grid),
        "loop_length_m": run.loop_length_m,
        "window_scans": tenth,
        "first_10pct": first.as_dict(),
        "last_10pct": last.as_dict(),
        "first_10pct_cpu": first_cpu.as_dict(),
        "last_10pct_cpu": last_cpu.as_dict(),
        # Means for the split: the grid works on keyframes only, so its median is zero.
        "first_10pct_estimator_mean_ms": mean_ms(fresh_t, "estimator_ns"),
        "last_10pct_estimator_mean_ms": mean_ms(grown_t, "estimator_ns"),
        "first_10pct_grid_mean_ms": mean_ms(fresh_t, "grid_ns"),
        "last_10pct_grid_mean_ms": mean_ms(grown_t, "grid_ns"),
        "change": change,
        "sequential_first_10pct": seq_first.as_dict(),
        "sequential_change": seq_change,
        "rss_growth_mib_after_first_10pct": float(np.interp(float(tenth), trace_i, trace_mib)),
        "rss_growth_mib_at_90pct": rss_before_side,
        "rss_trace": rss_trace,
        "distance_m": cum_m.round(2).tolist(),
        "time_ms": (wall(seq) / 1e6).round(4).tolist(),
        "cpu_ms": (cpu(seq) / 1e6).round(4).tolist(),
        "errors": trajectory_errors(poses, run.truth),
    }
    target = Target(
        "per-scan cost, last 10 % vs first 10 % of the run",
        f"within ±{TARGET_FLAT:.0%}",
        f"{change:+.1%} ({first.median_ms:.2f} → {last.median_ms:.2f} ms median, side by side)",
        abs(change) <= TARGET_FLAT,
    )
    result["targets"] = [target.as_dict()]
    if profile and not target.passed:
        # A second, untimed pass brings fresh state to where the last tenth starts; only the
        # last tenth runs under the profiler.
        again = Pipeline(keyframes_only)
        for scan in run.scans[: n - tenth]:
            again.run(scan)
        result["profile"] = profile_calls(
            again.run, run.scans[-tenth:], "estimator + grid over the last 10 % of the run"
        ).as_dict()
    return result
