"""The matcher front end's cost per scan, and whether another version gives the same poses.

    python -m bench.matcher_speed [--aces N] [--paper N] [--live N] [--against DIR] [--profile]

Sequences (all scans prepared before timing; the front end without odometry):
- aces: the first N ACES scans (180 beams, as recorded; keyframes every 0.3 m or 10°), 0: all;
- paper: a generated paper-size building, UTM-30LX (1,081 beams), scans 0.3 m apart;
- live: UTM-30LX scans at 40 Hz along the simulator's robot motion (the load generator's).

Prints the median / p90 ms per scan of `ScanMatcherFrontEnd.process`. `--against DIR` runs
another version's front end side by side, scan by scan, alternating which goes first (so machine
load hits both alike), and prints both medians, their ratio, and the largest pose difference
between the two over the whole sequence (the exactness check), e.g. against the last commit:

    mkdir -p /tmp/head && git archive HEAD service | tar -x -C /tmp/head
    python -m bench.matcher_speed --aces 0 --paper 300 --live 800 --against /tmp/head

`--accuracy H [H ...]`: instead, the front end alone over the whole of ACES and Intel for each
`MatchOptions.refine_halvings` H: relation errors (all, and under 5 s) and ms per scan.
"""

from __future__ import annotations

import argparse
import cProfile
import importlib
import io
import logging
import os
import pstats
import sys
import time
from itertools import islice
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from service.core.frontend.scan_matcher import MatcherParams, ScanMatcherFrontEnd
from service.core.types import LaserScan, Pose2D

log = logging.getLogger(__name__)

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


def load_front_end(root: Path) -> Any:
    """`ScanMatcherFrontEnd` of the source tree `root` (its own `service` package, not ours)."""
    other = module_of_tree(root, "service.core.frontend.scan_matcher")
    return lambda: other.ScanMatcherFrontEnd(other.MatcherParams(use_odometry=False))


def ours() -> ScanMatcherFrontEnd:
    return ScanMatcherFrontEnd(MatcherParams(use_odometry=False))


def run(fronts: list[Any], scans: list[LaserScan]) -> tuple[np.ndarray, np.ndarray]:
    """(ms per scan (F, N), poses (F, N, 3)) of the front ends `fronts`, scan by scan, the
    order alternating."""
    n, f = len(scans), len(fronts)
    times = np.empty((f, n))
    poses = np.empty((f, n, 3))
    for i, scan in enumerate(scans):
        for j in range(f) if i % 2 == 0 else reversed(range(f)):
            t0 = time.perf_counter_ns()
            p = fronts[j].process(scan).pose
            times[j, i] = (time.perf_counter_ns() - t0) * 1e-6
            poses[j, i] = (p.x_m, p.y_m, p.theta_rad)
    return times, poses


def sequences(a: argparse.Namespace) -> dict[str, list[LaserScan]]:
    seqs: dict[str, list[LaserScan]] = {}
    if a.aces >= 0:
        seqs["aces"] = aces_scans(a.aces if a.aces > 0 else 10**9, False)
    if a.paper > 0:
        seqs["paper"] = synthetic_scans(a.paper)
    if a.live > 0:
        seqs["live-40hz"] = live_scans(a.live)
    return {k: v for k, v in seqs.items() if v}


def accuracy(halvings: list[int]) -> None:
    """The front end alone (no odometry, no loop closure) over the whole of ACES and Intel, for
    each `MatchOptions.refine_halvings`: the relation error (Kümmerle et al.), all relations and
    those under 5 s (local), as `bench.evaluate` measures it, and the median ms per scan."""
    from bench.evaluate import LOCAL_RELATION_S, REAL_DATASETS, _match_relations
    from clients.logs import iter_log_scans
    from service.bridge import scan_to_laser
    from service.core.frontend.matcher import MatchOptions
    from service.core.metrics import parse_relations, relation_errors

    for dataset in REAL_DATASETS:
        if not dataset.bag.exists():
            continue
        scans = [
            scan_to_laser(s, use_odometry=False)
            for s in iter_log_scans(dataset.bag, use_odom=False)
        ]
        relations = parse_relations(dataset.relations.read_text().splitlines())
        for h in halvings:
            params = MatcherParams(use_odometry=False, match=MatchOptions(refine_halvings=h))
            times, poses = run([ScanMatcherFrontEnd(params)], scans)
            stamps = [s.stamp_ns for s in scans]
            kept, _ = _match_relations(stamps, relations)
            local = [r for r in kept if abs(r.t2_s - r.t1_s) < LOCAL_RELATION_S]
            est = [Pose2D(*p) for p in poses[0]]
            e_all, e_local = relation_errors(stamps, est, kept), relation_errors(stamps, est, local)
            print(
                f"{dataset.name:6s} refine_halvings {h}: relations {e_all.trans_mean_m:.4f} ± "
                f"{e_all.trans_std_m:.4f} m, {e_all.rot_mean_deg:.3f}° | local (< 5 s) "
                f"{e_local.trans_mean_m:.4f} m, {e_local.rot_mean_deg:.3f}° | median "
                f"{np.median(times[0]):.3f} ms/scan ({len(scans)} scans)",
                flush=True,
            )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--aces", type=int, default=0, help="ACES scans (0: all, -1: none)")
    ap.add_argument("--paper", type=int, default=300)
    ap.add_argument("--live", type=int, default=800)
    ap.add_argument("--against", type=Path, help="source tree of another version")
    ap.add_argument("--profile", action="store_true", help="cProfile top 25 of ours")
    ap.add_argument(
        "--accuracy",
        type=int,
        nargs="+",
        metavar="HALVINGS",
        help="instead: relation errors on ACES and Intel for these refine_halvings",
    )
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if a.accuracy:
        accuracy(a.accuracy)
        return 0
    other = load_front_end(a.against) if a.against is not None else None
    # Compile and warm whatever is compiled on first use, outside the timing.
    warm = synthetic_scans(3)
    for fe in [ours()] + ([other()] if other is not None else []):
        for scan in warm:
            fe.process(scan)
    for name, scans in sequences(a).items():
        fronts = [ours()] + ([other()] if other is not None else [])
        prof = cProfile.Profile() if a.profile else None
        if prof is not None:
            prof.enable()
        times, poses = run(fronts, scans)
        if prof is not None:
            prof.disable()
        beams = scans[0].ranges_m.shape[0]
        t = times[0]
        line = (
            f"{name:10s} {len(scans):5d} scans × {beams:4d} beams: ours median "
            f"{np.median(t):6.3f} ms, p90 {np.percentile(t, 90):6.3f}"
        )
        if other is not None:
            o = times[1]
            dxy = np.hypot(*(poses[0, :, :2] - poses[1, :, :2]).T)
            dth = np.abs(np.angle(np.exp(1j * (poses[0, :, 2] - poses[1, :, 2]))))
            line += (
                f" | {a.against}: median {np.median(o):6.3f}, p90 {np.percentile(o, 90):6.3f}"
                f" | ratio {np.median(o) / np.median(t):5.2f}× | poses: max |Δxy| "
                f"{dxy.max():.3g} m, max |Δθ| {dth.max():.3g} rad, "
                f"bit-identical {int(np.sum(np.all(poses[0] == poses[1], axis=1)))}/{len(scans)}"
            )
        print(line, flush=True)
        if prof is not None:
            buf = io.StringIO()
            pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(25)
            print(buf.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
