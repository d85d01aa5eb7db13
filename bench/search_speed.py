"""The matcher's correlative search: branch and bound against the brute force, same run.

    python -m bench.search_speed [--scans N] [--repeat R] [--frontend N]

Search alone: the matcher front end (no odometry) runs over the first N ACES scans; every 10th
scan from the 60th on, the submap, the scan's points and its priors are kept. Each kept search
is then run at two windows around the scan's own matched pose (offset by about one σ):
- 40 Hz: σ = 2 cm, 1° (a few cells, a few dozen rotations);
- paper: σ = 0.2 m, 15° (one scan per 0.3 m: the window clipped at ±0.6 m and ±25°).
Old (`matcher._brute_force_search`) and new (`matcher.search`) alternate call by call, so
machine load hits both alike; both must return the same pose. The new search's submap pyramid
is built once per submap change and cached: "warm" times reuse it, "build" is the build alone.

`--frontend N`: the whole front end over the first N ACES scans, old search and new side by
side (two front ends, scan by scan alternately): ms per scan, and the largest pose difference.
"""

from __future__ import annotations

import argparse
import copy
import math
import time
from collections.abc import Callable
from itertools import islice
from typing import Any

import numpy as np

from bench.matcher_speed import ACES_BAG
from service.core.frontend import matcher
from service.core.frontend.likelihood import LikelihoodGrid, off_surface_cost
from service.core.frontend.matcher import MatchOptions, Priors
from service.core.frontend.scan_matcher import MatcherParams, ScanMatcherFrontEnd
from service.core.frontend.search import build_pyramid
from service.core.types import LaserScan, Pose2D

Search = Callable[[LikelihoodGrid, np.ndarray, Priors, MatchOptions], tuple[Pose2D, int]]
WINDOWS = {"40 Hz (2 cm, 1°)": (0.02, 1.0), "paper (0.2 m, 15°)": (0.2, 15.0)}


def _aces(n: int) -> list[LaserScan]:
    from clients.logs import iter_log_scans
    from service.bridge import scan_to_laser

    if not ACES_BAG.exists():
        raise SystemExit(f"{ACES_BAG} not found (DATASETS_DIR)")
    scans = islice(iter_log_scans(ACES_BAG, use_odom=False), n)
    return [scan_to_laser(s, use_odometry=False) for s in scans]


def capture(scans: list[LaserScan]) -> list[tuple[LikelihoodGrid, np.ndarray, Priors, Pose2D]]:
    """(submap, points, priors, matched pose) of every 10th search from the 60th scan on."""
    kept: list[tuple[LikelihoodGrid, np.ndarray, Priors, Pose2D]] = []
    inner = matcher.match
    calls = [0]

    def spy(grid: LikelihoodGrid, pts: np.ndarray, priors: Priors, opts: MatchOptions) -> Any:
        result = inner(grid, pts, priors, opts)
        calls[0] += 1
        if calls[0] >= 60 and calls[0] % 10 == 0:
            kept.append((copy.deepcopy(grid), pts.copy(), priors, result.pose))
        return result

    import service.core.frontend.scan_matcher as sm

    sm.match = spy  # type: ignore[assignment]
    try:
        fe = ScanMatcherFrontEnd(MatcherParams(use_odometry=False))
        for scan in scans:
            fe.process(scan)
    finally:
        sm.match = inner
    return kept


def search_table(n_scans: int, repeat: int) -> None:
    cases = capture(_aces(n_scans))
    opts = MatchOptions()
    rng = np.random.default_rng(0)
    print(f"{len(cases)} searches from the first {n_scans} ACES scans, {repeat} repeats each")
    print(f"{'window':20s} {'old ms':>9s} {'new ms':>9s} {'speed-up':>9s} "
          f"{'old poses':>10s} {'new scored':>10s} {'same pose':>10s}")  # fmt: skip
    for label, (sigma_m, sigma_deg) in WINDOWS.items():
        old_ms, new_ms, old_n, new_n, same = [], [], [], [], 0
        for grid, pts, priors, pose in cases:
            sig_t = math.radians(sigma_deg)
            cov = np.diag([sigma_m**2, sigma_m**2, sig_t**2])
            off = rng.normal(0.0, 1.0, 3) * np.array([sigma_m, sigma_m, sig_t])
            pred = Pose2D(pose.x_m + off[0], pose.y_m + off[1], pose.theta_rad + off[2])
            pr = Priors(pred, cov, priors.wall_heading_rad, priors.wall_sigma_rad)
            grid.residual_costs(opts.max_residual_sigmas)
            matcher.search(grid, pts, pr, opts)  # the pyramid, built once per submap
            for _ in range(repeat):
                t0 = time.perf_counter_ns()
                old = matcher._brute_force_search(grid, pts, pr, opts)
                t1 = time.perf_counter_ns()
                new = matcher.search(grid, pts, pr, opts)
                t2 = time.perf_counter_ns()
                old_ms.append((t1 - t0) * 1e-6)
                new_ms.append((t2 - t1) * 1e-6)
            old_n.append(old[1])
            new_n.append(new[1])
            same += int(old[0] == new[0])
        o, n = float(np.median(old_ms)), float(np.median(new_ms))
        print(f"{label:20s} {o:9.3f} {n:9.3f} {o / n:8.1f}× {np.median(old_n):10.0f} "
              f"{np.median(new_n):10.0f} {same:>5d}/{len(cases)}")  # fmt: skip
    builds = []
    off_surface = off_surface_cost(opts.max_residual_sigmas)
    for grid, *_ in cases:
        costs = grid.residual_costs(opts.max_residual_sigmas)
        t0 = time.perf_counter_ns()
        build_pyramid(costs, off_surface)
        builds.append((time.perf_counter_ns() - t0) * 1e-6)
    shape = cases[-1][0].values.shape
    print(f"pyramid build (once per submap change): median {np.median(builds):.3f} ms "
          f"(submap {shape[0]}×{shape[1]} cells)")  # fmt: skip


PARAMS = MatcherParams()


def frontend_table(n_scans: int) -> None:
    """Two front ends, old search and new, scan by scan alternately."""
    scans = _aces(n_scans)
    fronts = {"old": ScanMatcherFrontEnd(MatcherParams(use_odometry=False)),
              "new": ScanMatcherFrontEnd(MatcherParams(use_odometry=False))}  # fmt: skip
    searches: dict[str, Search] = {"old": matcher._brute_force_search, "new": matcher.search}
    times: dict[str, list[float]] = {"old": [], "new": []}
    poses: dict[str, list[tuple[float, float, float]]] = {"old": [], "new": []}
    new_search = matcher.search
    try:
        for scan in scans:
            for name, fe in fronts.items():
                matcher.search = searches[name]  # type: ignore[assignment]
                t0 = time.perf_counter_ns()
                p = fe.process(scan).pose
                times[name].append((time.perf_counter_ns() - t0) * 1e-6)
                poses[name].append((p.x_m, p.y_m, p.theta_rad))
    finally:
        matcher.search = new_search  # type: ignore[assignment]
    a, b = np.array(poses["old"]), np.array(poses["new"])
    dxy = float(np.max(np.hypot(*(a[:, :2] - b[:, :2]).T)))
    dth = float(np.max(np.abs(np.angle(np.exp(1j * (a[:, 2] - b[:, 2]))))))
    for name in ("old", "new"):
        t = np.array(times[name])
        print(f"front end, {name} search: median {np.median(t):.2f} ms/scan, mean "
              f"{t.mean():.2f}, p90 {np.percentile(t, 90):.2f} ({len(t)} ACES scans)")  # fmt: skip
    print(f"poses old vs new: max |Δxy| {dxy:.3g} m, max |Δθ| {dth:.3g} rad")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--frontend", type=int, default=0, help="also the whole front end, N scans")
    args = ap.parse_args()
    search_table(args.scans, args.repeat)
    if args.frontend:
        frontend_table(args.frontend)


if __name__ == "__main__":
    main()
