"""`python -m bench [--quick] [--out bench/out]`: run the benchmarks, write docs/benchmarks.md.

Sections: estimator speed (ours, the paper baseline, KISS-ICP), end to end and scale (N robots
through Zenoh into one service), map growth over a long run, and accuracy (bench/evaluate.py).
Quick mode uses smaller sizes and finishes in about two minutes; the full mode takes longer.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from bench.common import REPO_ROOT, BenchError, machine_info, make_synthetic_run

log = logging.getLogger("bench")

SECTIONS = ("speed", "scale", "growth", "accuracy", "fleet")
# Set on some processors for old OpenBLAS builds; they slow a current numpy (see
# /work/.library/env/README.md), so the benchmark process runs without them and says so.
OPENBLAS_VARS = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE")


@dataclass(frozen=True, slots=True)
class Sizes:
    speed_scans: int | None  # None: the whole trajectory
    growth_building: str
    # Whole laps between the first and the last 10 % of the growth run: both windows then
    # cover the same corridors, so a change in cost comes from the map, not from the place.
    growth_laps_between: int
    scale_robots: tuple[int, ...]
    scale_loads: tuple[str, ...]
    scale_in_process: tuple[int, ...]  # N measured again with the estimators in the service
    scale_warmup_s: float
    scale_measure_s: float
    scale_drain_s: float
    fleet_robots: tuple[int, ...] = (10, 25, 40)
    fleet_warmup_s: float = 5.0
    fleet_measure_s: float = 20.0
    fleet_fanout_pairs: int = 2  # (without, with subscribers) pairs, alternated


FULL = Sizes(None, "paper", 3, (1, 5, 10, 25), ("agents", "loadgen"), (10,), 5.0, 20.0, 2.0)
QUICK = Sizes(
    300, "small", 2, (1, 5), ("agents", "loadgen"), (5,), 1.0, 4.0, 1.0, (10,), 2.0, 6.0, 1
)


def _drop_openblas_overrides() -> None:
    present = {k: os.environ[k] for k in OPENBLAS_VARS if k in os.environ}
    if not present or os.environ.get("BENCH_KEEP_OPENBLAS_ENV"):
        return
    env = {k: v for k, v in os.environ.items() if k not in OPENBLAS_VARS}
    env["BENCH_OPENBLAS_ENV_REMOVED"] = ", ".join(f"{k}={v}" for k, v in present.items()) + (
        " (unset for this run)"
    )
    os.execve(sys.executable, [sys.executable, "-m", "bench", *sys.argv[1:]], env)


def _timed(name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    t0 = time.monotonic()
    log.info("section %s: start", name)
    try:
        result = fn()
    except (BenchError, ImportError) as err:
        log.error("section %s failed: %s", name, err)
        result = {"error": str(err)}
    result["section_wall_s"] = time.monotonic() - t0
    log.info("section %s: %.1f s", name, result["section_wall_s"])
    return result


def run_accuracy(quick: bool, out_dir: Path) -> dict[str, Any]:
    """bench/evaluate.py in a process of its own; its markdown table goes into the report."""
    if not (REPO_ROOT / "bench" / "evaluate.py").exists():
        raise BenchError("bench/evaluate.py is not available")
    # A folder of our own: `python -m bench.evaluate` run by hand writes to bench/out too.
    acc_dir = out_dir / "accuracy"
    cmd = [sys.executable, "-m", "bench.evaluate", "--out", str(acc_dir)]
    if quick:
        cmd.append("--quick")
    shown = "python -m bench.evaluate" + (" --quick" if quick else "")
    proc = subprocess.run(
        cmd, cwd=REPO_ROOT, capture_output=True, text=True, timeout=3600, check=False
    )
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise BenchError(f"`{shown}` exited with {proc.returncode}: {tail[0]}")
    md = acc_dir / "accuracy.md"
    if not md.exists():
        raise BenchError(f"`{shown}` wrote no {md}")
    text = md.read_text()
    # Map pictures the evaluation names in its markdown (`name.png`), to copy next to the report.
    pictures = {
        name: str(acc_dir / name)
        for name in sorted(set(re.findall(r"`([\w.-]+\.png)`", text)))
        if (acc_dir / name).is_file()
    }
    return {"command": shown, "markdown": text, "pictures": pictures}


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "item"):
        return obj.item()
    if hasattr(obj, "tolist"):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _clean_nan(obj: Any) -> Any:
    if isinstance(obj, float) and math.isnan(obj):
        return None
    if isinstance(obj, dict):
        return {k: _clean_nan(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean_nan(v) for v in obj]
    return obj


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, about two minutes")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "out")
    parser.add_argument("--doc", type=Path, default=REPO_ROOT / "docs" / "benchmarks.md")
    parser.add_argument("--img-dir", type=Path, default=REPO_ROOT / "docs" / "img")
    parser.add_argument(
        "--sections",
        default=",".join(SECTIONS),
        help=f"comma-separated subset of {', '.join(SECTIONS)} (default: all)",
    )
    parser.add_argument(
        "--fleet-only",
        action="store_true",
        help="only the fleet section (N robots x 40 Hz, fan-out); writes bench/out/fleet.md "
        "and leaves docs/benchmarks.md alone",
    )
    parser.add_argument(
        "--mapper-processes",
        type=int,
        default=None,
        metavar="K",
        help="the service's --mapper-processes in the fleet section (default: the core count)",
    )
    parser.add_argument("--seed", type=int, default=1, help="synthetic building (default: 1)")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request otherwise
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    if args.fleet_only:
        sections = ["fleet"]
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        parser.error(f"unknown sections: {', '.join(sorted(unknown))}")
    _drop_openblas_overrides()
    sizes = QUICK if args.quick else FULL
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    res: dict[str, Any] = {
        "machine": machine_info(),
        "quick": args.quick,
        "sizes": {"full": asdict(FULL), "quick": asdict(QUICK)},
    }

    if "speed" in sections:
        from bench.speed import run_speed

        res["speed"] = _timed(
            "speed",
            lambda: run_speed(
                make_synthetic_run(args.seed, max_scans=sizes.speed_scans),
                live_scans=sizes.speed_scans or 800,
            ),
        )
    if "growth" in sections:
        from bench.growth import run_growth

        res["growth"] = _timed(
            "growth",
            lambda: run_growth(
                make_synthetic_run(
                    args.seed,
                    laps=sizes.growth_laps_between / 0.9,
                    size=sizes.growth_building,
                )
            ),
        )
    if "scale" in sections:
        from bench.scale import run_scale

        res["scale"] = _timed(
            "scale",
            lambda: run_scale(
                sizes.scale_robots,
                sizes.scale_loads,
                mapper_processes=os.cpu_count() or 1,
                in_process_counts=sizes.scale_in_process,
                warmup_s=sizes.scale_warmup_s,
                measure_s=sizes.scale_measure_s,
                drain_s=sizes.scale_drain_s,
                work_dir=args.out / "scale",
                profile_on_miss=not args.quick,
            ),
        )
    if "accuracy" in sections:
        res["accuracy"] = _timed("accuracy", lambda: run_accuracy(args.quick, args.out))
    if "fleet" in sections:
        from bench.fleet import run_fleet

        res["fleet"] = _timed(
            "fleet",
            lambda: run_fleet(
                sizes.fleet_robots,
                mapper_processes=args.mapper_processes or os.cpu_count() or 1,
                warmup_s=sizes.fleet_warmup_s,
                measure_s=sizes.fleet_measure_s,
                work_dir=args.out / "fleet",
                fanout_pairs_count=sizes.fleet_fanout_pairs,
            ),
        )
        res["fleet"]["loadavg_at_end"] = list(os.getloadavg())

    res["wall_s"] = time.monotonic() - t_start
    if args.fleet_only:
        from bench.report import render_fleet_only

        (args.out / "fleet.json").write_text(
            json.dumps(_clean_nan(res), indent=1, default=_json_default)
        )
        render_fleet_only(res, args.out / "fleet.md")
        log.info("wrote %s (%.1f s)", args.out / "fleet.md", res["wall_s"])
        return 1 if "error" in res["fleet"] else 0
    (args.out / "results.json").write_text(
        json.dumps(_clean_nan(res), indent=1, default=_json_default)
    )
    from bench.report import render

    render(res, args.doc, args.img_dir)
    log.info("wrote %s and %s (%.1f s)", args.doc, args.out / "results.json", res["wall_s"])
    failed = [name for name in sections if "error" in res.get(name, {})]
    if failed:
        log.error("sections that could not run: %s", ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
