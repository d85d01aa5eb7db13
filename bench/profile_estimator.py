"""Estimator speed and regression check on fixed sequences (a developer tool, not the report).

    python -m bench.profile_estimator [--synthetic N] [--aces N] [--live N] [--repeat N] [--profile]
                                      [--baseline N] [--record FILE.npz] [--compare FILE.npz]
                                      [--against DIR]

Sequences (all scans are prepared before timing):
- synthetic: paper-size building seed 0, UTM-30LX (1,081 beams), 0.3 m spacing, no odometry;
- aces-noodom / aces-odom: the first N ACES scans (180 beams), without / with odometry;
- live-40hz: UTM-30LX scans at 40 Hz along the simulator's robot motion (the load generator's).

Prints median / p99 ms per scan for each, optionally a cProfile top-20 over all of them, and
records or compares the poses and flags (max position / heading difference, flag mismatches).
`--steps` adds the cost of each of the front end's named steps (docs/estimator.md, "The steps
of one scan"): mean and median ms per scan, and their share of the whole.

`--against DIR` times another version of the estimator side by side, scan by scan alternately in
this process (so machine load hits both alike), e.g. the last commit:
    mkdir -p /tmp/head && git archive HEAD service | tar -x -C /tmp/head
    python -m bench.profile_estimator --repeat 3 --against /tmp/head
"""

from __future__ import annotations

import argparse
import cProfile
import importlib
import io
import os
import pstats
import sys
import time
from collections.abc import Callable
from itertools import islice
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from service.core.frontend.estimator import ManhattanEstimator
from service.core.types import LaserScan

# Like bench/evaluate.py: ../shared/datasets next to the checkout (DATASETS_DIR overrides).
DATASETS = Path(
    os.environ.get("DATASETS_DIR", Path(__file__).resolve().parents[2] / "shared" / "datasets")
)
ACES_BAG = DATASETS / "aces" / "aces.sort.bag"


def synthetic_scans(n: int, seed: int = 0) -> list[LaserScan]:
    from sensor_agent.sim.world import (
        LaserModel,
        generate_building,
        generate_trajectory,
        simulate_scan,
    )

    world = generate_building(seed, size="paper")
    traj = generate_trajectory(world, seed, spacing_m=0.3)
    model = LaserModel.utm30lx()
    rng = np.random.default_rng(seed)
    out = []
    for i in range(min(n, len(traj))):
        sample = simulate_scan(world, traj.poses[i], model, rng)
        out.append(
            LaserScan(
                stamp_ns=int(traj.stamps_ns[i]),
                angle_min_rad=model.angle_min_rad,
                angle_increment_rad=model.angle_increment_rad,
                ranges_m=sample.ranges_m,
                range_min_m=model.range_min_m,
                range_max_m=model.range_max_m,
            )
        )
    return out


def live_scans(n: int, seed: int = 1) -> list[LaserScan]:
    """`n` scans at 40 Hz along the simulator's continuous motion: what the load generator sends."""
    from bench.loadgen import path_scans

    return path_scans(seed, n, 1.0 / 40.0)


def aces_scans(n: int, use_odometry: bool) -> list[LaserScan]:
    from clients.logs import iter_log_scans
    from service.bridge import scan_to_laser

    if not ACES_BAG.exists():
        return []
    scans = islice(iter_log_scans(ACES_BAG, use_odom=use_odometry), n)
    return [scan_to_laser(s, use_odometry=use_odometry) for s in scans]


def run(scans: list[LaserScan]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(wall ms, thread CPU ms, poses (N, 3), flags (N,)) of a fresh estimator over `scans`."""
    est = ManhattanEstimator()
    times = np.empty(len(scans))
    cpu = np.empty(len(scans))
    poses = np.empty((len(scans), 3))
    flags = np.empty(len(scans), dtype=np.int64)
    for i, scan in enumerate(scans):
        t0 = time.perf_counter_ns()
        c0 = time.thread_time_ns()
        e = est.process(scan)
        cpu[i] = (time.thread_time_ns() - c0) * 1e-6
        times[i] = (time.perf_counter_ns() - t0) * 1e-6
        poses[i] = e.pose
        flags[i] = int(e.flags)
    return times, cpu, poses, flags


STEPS = (
    "_predict",
    "_points",
    "_directions",
    "_heading",
    "_without_moved",
    "_translation",
    "_confidence",
    "_commit",
)


def step_costs(scans: list[LaserScan]) -> dict[str, np.ndarray]:
    """Per scan, the ms spent in each step (wrapped on one estimator), and in `process` whole."""
    est = ManhattanEstimator()
    spent = {name: np.zeros(len(scans)) for name in (*STEPS, "process")}
    index = 0

    inside = [False]  # a step called within another (`_commit` may find directions): its own

    def timed(name: str, method: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            if inside[0]:
                return method(*args, **kwargs)
            inside[0] = True
            t0 = time.perf_counter_ns()
            try:
                return method(*args, **kwargs)
            finally:
                spent[name][index] += (time.perf_counter_ns() - t0) * 1e-6
                inside[0] = False

        return call

    for name in STEPS:
        setattr(est, name, timed(name, getattr(est, name)))
    for index, scan in enumerate(scans):  # `timed` reads `index`
        t0 = time.perf_counter_ns()
        est.process(scan)
        spent["process"][index] = (time.perf_counter_ns() - t0) * 1e-6
    return spent


def print_step_costs(name: str, spent: dict[str, np.ndarray]) -> None:
    total = float(spent["process"].mean())
    print(f"{name:12s} steps (ms per scan, mean / median, share of process {total:.3f} ms):")
    accounted = np.zeros_like(spent["process"])
    for step in STEPS:
        accounted += spent[step]
        mean = float(spent[step].mean())
        print(
            f"  {step:16s} {mean:6.3f} / {np.median(spent[step]):6.3f}  {100 * mean / total:5.1f} %"
        )
    rest = spent["process"] - accounted
    print(f"  {'(rest)':16s} {rest.mean():6.3f} / {np.median(rest):6.3f}")


def module_of_tree(root: Path, name: str) -> ModuleType:
    """The module `name` (under `service`) of the source tree `root`, imported from its own
    `service` package beside ours, for old-against-new runs in one process."""
    ours = {k: sys.modules.pop(k) for k in list(sys.modules) if k.split(".")[0] == "service"}
    sys.path.insert(0, str(root))
    try:
        module = importlib.import_module(name)
        if not Path(module.__file__ or "").resolve().is_relative_to(root.resolve()):
            raise SystemExit(f"{root}: no {name.replace('.', '/')}.py there")
    finally:
        sys.path.remove(str(root))
        for k in [k for k in sys.modules if k.split(".")[0] == "service"]:
            del sys.modules[k]
        sys.modules.update(ours)
    return module


def load_estimator(root: Path) -> type[ManhattanEstimator]:
    """`ManhattanEstimator` of the source tree `root` (its own `service` package, not ours)."""
    cls: type[ManhattanEstimator] = module_of_tree(
        root, "service.core.frontend.estimator"
    ).ManhattanEstimator
    return cls


def run_pair(
    scans: list[LaserScan], other_cls: type[ManhattanEstimator]
) -> tuple[np.ndarray, np.ndarray]:
    """Wall ms per scan of ours and of `other_cls`, alternating which goes first."""
    pair = (ManhattanEstimator(), other_cls())
    times = np.empty((2, len(scans)))
    for i, scan in enumerate(scans):
        for j in (0, 1) if i % 2 == 0 else (1, 0):
            t0 = time.perf_counter_ns()
            pair[j].process(scan)
            times[j, i] = (time.perf_counter_ns() - t0) * 1e-6
    return times[0], times[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synthetic", type=int, default=400)
    ap.add_argument("--aces", type=int, default=1000)
    ap.add_argument("--live", type=int, default=0, help="N scans at 40 Hz (the live path)")
    ap.add_argument("--repeat", type=int, default=1, help="timed passes (best median kept)")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--steps", action="store_true", help="the cost of each front-end step")
    ap.add_argument(
        "--baseline", type=int, default=0, help="also time bench/paper_baseline.py on N scans"
    )
    ap.add_argument("--record", type=Path)
    ap.add_argument("--compare", type=Path)
    ap.add_argument("--against", type=Path, help="source tree of another version to time")
    a = ap.parse_args(argv)

    seqs = {"synthetic": synthetic_scans(a.synthetic)}
    if a.aces > 0:
        seqs["aces-noodom"] = aces_scans(a.aces, False)
        seqs["aces-odom"] = aces_scans(a.aces, True)
    if a.live > 0:
        seqs["live-40hz"] = live_scans(a.live)
    seqs = {k: v for k, v in seqs.items() if v}

    results: dict[str, np.ndarray] = {}
    medians: dict[str, float] = {}
    for name, scans in seqs.items():
        best: np.ndarray | None = None
        best_cpu: np.ndarray | None = None
        for _ in range(max(1, a.repeat)):
            times, cpu, poses, flags = run(scans)
            if best is None or np.median(times) < np.median(best):
                best = times
            if best_cpu is None or np.median(cpu) < np.median(best_cpu):
                best_cpu = cpu
        assert best is not None
        assert best_cpu is not None
        beams = scans[0].ranges_m.shape[0]
        print(
            f"{name:12s} {len(scans):5d} scans x {beams:4d} beams: "
            f"median {np.median(best):6.3f} ms  p99 {np.percentile(best, 99):6.3f} ms  "
            f"mean {best.mean():6.3f} ms | CPU median {np.median(best_cpu):6.3f} "
            f"p99 {np.percentile(best_cpu, 99):6.3f} ms"
        )
        medians[name] = float(np.median(best))
        results[f"{name}/poses"] = poses
        results[f"{name}/flags"] = flags

    if a.steps:
        for name, scans in seqs.items():
            print_step_costs(name, step_costs(scans))

    if a.against is not None:
        other_cls = load_estimator(a.against)
        for name, scans in seqs.items():
            best_pair: tuple[np.ndarray, np.ndarray] | None = None
            for _ in range(max(1, a.repeat)):
                t_ours, t_other = run_pair(scans, other_cls)
                if best_pair is None or np.median(t_ours) < np.median(best_pair[0]):
                    best_pair = (t_ours, t_other)
            assert best_pair is not None
            t_ours, t_other = best_pair
            print(
                f"{name:12s} side by side: ours median {np.median(t_ours):6.3f} p99 "
                f"{np.percentile(t_ours, 99):6.3f} ms | {a.against}: median "
                f"{np.median(t_other):6.3f} p99 {np.percentile(t_other, 99):6.3f} ms | "
                f"ratio {np.median(t_other) / np.median(t_ours):4.2f}x"
            )

    if a.baseline > 0 and "synthetic" in seqs:
        from bench.paper_baseline import PaperBaseline

        base = PaperBaseline()
        bt = []
        for scan in seqs["synthetic"][: a.baseline]:
            t0 = time.perf_counter_ns()
            base.process(scan)
            bt.append((time.perf_counter_ns() - t0) * 1e-6)
        med = float(np.median(bt))
        print(
            f"{'baseline':12s} {len(bt):5d} synthetic scans: median {med:6.3f} ms  p99 "
            f"{np.percentile(bt, 99):6.3f} ms  -> ours is {med / medians['synthetic']:.1f}x faster"
        )

    if a.record is not None:
        np.savez(a.record, **results)  # type: ignore[arg-type]
        print(f"recorded {a.record}")
    if a.compare is not None:
        ref = np.load(a.compare)
        for name in seqs:
            p0, f0 = ref[f"{name}/poses"], ref[f"{name}/flags"]
            p1, f1 = results[f"{name}/poses"], results[f"{name}/flags"]
            n = min(len(p0), len(p1))
            p0, f0, p1, f1 = p0[:n], f0[:n], p1[:n], f1[:n]
            dpos = np.hypot(p1[:, 0] - p0[:, 0], p1[:, 1] - p0[:, 1])
            dth = np.abs((p1[:, 2] - p0[:, 2] + np.pi) % (2 * np.pi) - np.pi)
            first = np.flatnonzero(dpos > 1e-3)
            print(
                f"{name:12s} max dpos {dpos.max() * 1e3:8.3f} mm  max dtheta "
                f"{np.degrees(dth.max()):7.4f} deg  flag mismatches {(f0 != f1).sum():4d}  "
                f"first >1mm at {first[0] if first.size else '-'}  final dpos "
                f"{dpos[-1] * 1e3:.3f} mm"
            )

    if a.profile:
        prof = cProfile.Profile()
        prof.enable()
        for scans in seqs.values():
            run(scans)
        prof.disable()
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats(
            os.environ.get("PROFILE_SORT", "tottime")
        ).print_stats(20)
        print(buf.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
