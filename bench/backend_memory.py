"""`python -m bench.backend_memory [--km 1] [--out DIR]`: what the back end holds over a long run.

Front end and back end (loop closure on) on laps of the synthetic corridor loop, one scan
every 0.3 m (the paper's setting), as `mapping-service map` runs them. Every 100 m of travel:
the process's RSS growth, the size of the back end as a checkpoint stores it (pickled), and,
where the code reports it, what the submaps hold and the likelihood fields cached beside them.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import math
import pickle
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import psutil

from bench.common import git_commit, make_synthetic_run, path_length_m

log = logging.getLogger(__name__)

MIB = 2**20


def run(km: float, *, seed: int = 1, size: str = "paper", every_m: float = 100.0) -> dict[str, Any]:
    from service.core.slam import SlamParams, SlamSession

    probe = make_synthetic_run(seed, max_scans=2, size=size)
    laps = max(1.0, km * 1000.0 / probe.loop_length_m)
    synthetic = make_synthetic_run(seed, laps=laps, size=size)
    session = SlamSession(SlamParams(loop_closure=True))
    proc = psutil.Process()
    gc.collect()
    rss0 = proc.memory_info().rss
    samples: list[dict[str, float]] = []
    travelled_m, next_m = 0.0, every_m
    for i, scan in enumerate(synthetic.scans):
        session.process(scan)
        if i:
            travelled_m += path_length_m(synthetic.truth[i - 1 : i + 1])
        done = travelled_m >= km * 1000.0 or i == len(synthetic.scans) - 1
        if travelled_m >= next_m or done:
            next_m += every_m
            gc.collect()
            submaps = session.submaps
            sample = {
                "travelled_m": travelled_m,
                "rss_growth_mib": (proc.memory_info().rss - rss0) / MIB,
                "checkpoint_mib": len(pickle.dumps(session.backend, protocol=5)) / MIB,
                "submaps": float(len(submaps.submaps)),
            }
            held = getattr(submaps, "nbytes", None)  # older versions do not report it
            if held is not None:
                sample["submaps_and_cache_mib"] = held / MIB
            samples.append(sample)
            log.info("%.0f m: %s", travelled_m, {k: round(v, 1) for k, v in sample.items()})
            if done:
                break
    end = samples[-1]
    poses = session.finish()
    last = poses[-1]
    return {
        "commit": git_commit(),
        "seed": seed,
        "loop_m": synthetic.loop_length_m,
        "travelled_m": end["travelled_m"],
        "scans": i + 1,
        "accepted_closures": session.stats.accepted,
        "search_s": session.stats.search_s,
        "backend_s": session.stats.total_s,
        "last_pose": [last.x_m, last.y_m, last.theta_rad],
        "samples": samples,
        "rss_growth_mib_per_km": end["rss_growth_mib"] / (end["travelled_m"] / 1000.0),
        "checkpoint_mib_per_km": end["checkpoint_mib"] / (end["travelled_m"] / 1000.0),
    }


def table(result: dict[str, Any]) -> str:
    rows = [
        "| travelled (m) | submaps | RSS growth (MiB) | checkpoint (MiB) | held + cached (MiB) |"
    ]
    rows.append("|---|---|---|---|---|")
    for s in result["samples"]:
        held = s.get("submaps_and_cache_mib", math.nan)
        rows.append(
            f"| {s['travelled_m']:.0f} | {s['submaps']:.0f} | {s['rss_growth_mib']:.0f} | "
            f"{s['checkpoint_mib']:.1f} | {held:.1f} |"
        )
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.backend_memory", description=__doc__)
    parser.add_argument("--km", type=float, default=1.0, help="distance to drive (default 1)")
    parser.add_argument("--seed", type=int, default=1, help="synthetic building (default 1)")
    parser.add_argument(
        "--size", choices=("paper", "small"), default="paper", help="building preset (paper)"
    )
    parser.add_argument("--out", type=Path, default=Path("bench/out"), help="output folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    result = run(args.km, seed=args.seed, size=args.size)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "backend_memory.json").write_text(json.dumps(result, indent=2))
    text = table(result)
    (args.out / "backend_memory.md").write_text(text + "\n")
    log.info("%s", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
