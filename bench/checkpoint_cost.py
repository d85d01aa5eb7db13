"""`python -m bench.checkpoint_cost [--km 1] [--every-m 250]`: a checkpoint's cost over a long run.

The live back end (loop closure on, the map kept as chunks, as `mapping-service serve` runs it)
on laps of the synthetic corridor loop, one scan every 0.3 m (the paper's setting). Every
`--every-m` of travel the same state is encoded twice, side by side: whole (every array in the
checkpoint, as before the array pack) and with the session's array pack (frozen arrays written
once, `service.app.statecodec.ArrayPack`). Reported per point: encode time, the checkpoint's
bytes, and what the pack grew by. A checkpoint is encoded while its session waits (and, with
mapper processes, the process's other sessions), every 2,400 scans: a minute at 40 Hz.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench.common import git_commit, make_synthetic_run, path_length_m

log = logging.getLogger(__name__)

MIB = 2**20
CORE = ("service.core",)


def run(km: float, *, every_m: float = 250.0, seed: int = 1) -> dict[str, Any]:
    from service.app import statecodec
    from service.core.slam import SlamParams, SlamSession

    probe = make_synthetic_run(seed, max_scans=2, size="paper")
    laps = max(1.0, km * 1000.0 / probe.loop_length_m)
    synthetic = make_synthetic_run(seed, laps=laps, size="paper")
    # As the service holds it: the map as chunks (`maps.composed`), in the checkpoint.
    session = SlamSession(SlamParams(loop_closure=True), map_resolution_m=0.05)
    samples: list[dict[str, float]] = []
    travelled_m, next_m = 0.0, every_m
    with tempfile.TemporaryDirectory() as tmp:
        pack = statecodec.ArrayPack(Path(tmp) / "frozen.mpack")
        for i, scan in enumerate(synthetic.scans):
            session.process(scan)
            if i:
                travelled_m += path_length_m(synthetic.truth[i - 1 : i + 1])
            done = travelled_m >= km * 1000.0 or i == len(synthetic.scans) - 1
            if not (travelled_m >= next_m or done):
                continue
            next_m += every_m
            state = {"core": session}
            t0 = time.perf_counter()
            whole = statecodec.encode(state, CORE)
            t1 = time.perf_counter()
            before = pack.path.stat().st_size if pack.path.exists() else 0
            packed = statecodec.encode(state, CORE, pack)
            t2 = time.perf_counter()
            sample = {
                "travelled_m": travelled_m,
                "whole_s": t1 - t0,
                "whole_mib": len(whole) / MIB,
                "packed_s": t2 - t1,
                "packed_mib": len(packed) / MIB,
                "pack_growth_mib": (pack.path.stat().st_size - before) / MIB,
                "pack_mib": pack.path.stat().st_size / MIB,
            }
            samples.append(sample)
            log.info("%.0f m: %s", travelled_m, {k: round(v, 3) for k, v in sample.items()})
            if done:
                break
    return {"commit": git_commit(), "seed": seed, "scans": i + 1, "samples": samples}


def table(result: dict[str, Any]) -> str:
    rows = [
        (
            "| travelled (m) | whole: encode (s) | whole: checkpoint (MiB) "
            "| with the pack: encode (s) | checkpoint (MiB) | pack grew (MiB) | pack (MiB) |"
        ),
        "|---|---|---|---|---|---|---|",
    ]
    for s in result["samples"]:
        rows.append(
            f"| {s['travelled_m']:.0f} | {s['whole_s']:.3f} | {s['whole_mib']:.2f} | "
            f"{s['packed_s']:.3f} | {s['packed_mib']:.2f} | {s['pack_growth_mib']:.2f} | "
            f"{s['pack_mib']:.2f} |"
        )
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.checkpoint_cost", description=__doc__)
    parser.add_argument("--km", type=float, default=1.0, help="distance to drive (default 1)")
    parser.add_argument(
        "--every-m", type=float, default=250.0, help="travel between checkpoints (default 250)"
    )
    parser.add_argument("--seed", type=int, default=1, help="synthetic building (default 1)")
    parser.add_argument("--out", type=Path, default=Path("bench/out"), help="output folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    result = run(args.km, every_m=args.every_m, seed=args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "checkpoint_cost.json").write_text(json.dumps(result, indent=2))
    text = table(result)
    (args.out / "checkpoint_cost.md").write_text(text + "\n")
    log.info("%s", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
