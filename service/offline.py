"""`mapping-service map INPUT --out DIR`: map a bag or a recording offline.

Reads the scans (`clients.logs`), runs them through one `service.core.slam.SlamSession` (the
core the live service runs too: front end, back end, map) and writes into DIR:

- `trajectory.tum`: one line per scan, `stamp x y z qx qy qz qw`, stamp = scan header stamp (s);
- `trajectory_covariance.csv`: one row per scan, the front end's own pose (before loop
  closure), quality, flags, keyframe, and its 3x3 (x, y, theta) covariance row-major
  (`PoseEstimate.covariance`: relative to the latest keyframe before the scan, map axes);
- `map.png` (with the trajectory drawn), `map.pgm` + `map.yaml` (ROS map_server);
- `report.json`: scan count, estimator time per scan, quality and flag statistics, input, map.

The library functions (`map_scans`, `write_outputs`, `build_report`) are what `bench.evaluate`
calls in-process; `run_map` is the command-line entry point.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from clients.logs import LogError, LogInfo, iter_log_scans, probe_log
from clients.wire import PoseFlag, Scan
from service import mapio
from service.bridge import scan_to_laser
from service.core.maps.grid import GridImage
from service.core.slam import (
    DEFAULT_DRAW_PERIOD_S,
    DEFAULT_FRONT_END,
    FrontEndName,
    LoopStats,
    SlamParams,
    SlamSession,
    make_frontend,
)
from service.core.types import Pose2D, PoseEstimate

log = logging.getLogger(__name__)

EXIT_OK: Final = 0
EXIT_OUTPUT: Final = 1  # the output directory cannot be written
EXIT_INPUT: Final = 2  # the input cannot be read or holds no scans
QUALITY_LOW: Final = 0.5


class OfflineError(Exception):
    """A mapping run that cannot produce its outputs (no scans, unwritable output, ...)."""


@dataclass(slots=True)
class MapRun:
    """Everything one offline mapping run produced, before it is written out."""

    stamps_ns: list[int] = field(default_factory=list)
    estimates: list[PoseEstimate] = field(default_factory=list)
    estimator_ns: list[int] = field(default_factory=list)  # time of `process` per scan
    integrate_ns: list[int] = field(default_factory=list)  # time of `integrate` per call
    image: GridImage | None = None  # the map, at the finished poses
    wall_s: float = 0.0
    beam_counts: set[int] = field(default_factory=set)
    with_odometry: int = 0  # scans that carried odometry into the estimator
    optimised: list[Pose2D] | None = None  # every scan's pose after loop closure (None: off)
    loops: LoopStats | None = None
    backend_s: float = 0.0  # the back end, all of it: nodes, submaps, loop search, optimisation
    front_end: str = DEFAULT_FRONT_END  # which front end (`--front-end`)
    wall_families_deg: list[float] = field(default_factory=lambda: [0.0])  # the estimator's

    @property
    def frontend_poses(self) -> list[Pose2D]:
        return [e.pose for e in self.estimates]

    @property
    def poses(self) -> list[Pose2D]:
        """The final trajectory: optimised when the back end ran, else the front end's."""
        return self.optimised if self.optimised is not None else self.frontend_poses

    @property
    def scans(self) -> int:
        return len(self.estimates)


def map_scans(
    scans: Iterable[Scan],
    *,
    resolution_m: float = 0.05,
    use_odometry: bool = True,
    draw_period_s: float = DEFAULT_DRAW_PERIOD_S,
    total: int | None = None,
    progress: bool = False,
    on_estimate: Callable[[Scan, PoseEstimate], None] | None = None,
    loop_closure: bool = True,
    slam_params: SlamParams | None = None,
    front_end: FrontEndName = DEFAULT_FRONT_END,
) -> MapRun:
    """Estimate a pose for every scan and build the occupancy map (`SlamSession`).

    The map draws keyframes and a scan every `draw_period_s` (0: keyframes only); degenerate
    poses are never drawn (their pose is only a prediction). Without loop closure it is one
    grid at the front-end poses. With `loop_closure`, the back end closes loops over the
    keyframes; each drawn scan goes, at its front-end pose, into the map chunk of its stretch
    of travel, and the map is the chunks composed at their anchor nodes' finished poses.
    """
    if slam_params is None:
        slam_params = SlamParams(loop_closure=loop_closure)
    elif slam_params.loop_closure != loop_closure:
        slam_params = replace(slam_params, loop_closure=loop_closure)
    frontend = make_frontend(front_end, use_odometry=use_odometry)
    slam = SlamSession(
        slam_params,
        frontend,
        map_resolution_m=resolution_m,
        draw_period_s=draw_period_s,
    )
    run = MapRun(front_end=front_end)
    start = time.perf_counter()
    bar = tqdm(
        total=total,
        disable=not progress,
        unit="scan",
        dynamic_ncols=True,
        file=sys.stderr,
        mininterval=0.25,
    )
    try:
        for scan in scans:
            laser = scan_to_laser(scan, use_odometry=use_odometry)
            t0 = time.perf_counter_ns()
            tracked = slam.track(laser)
            run.estimator_ns.append(time.perf_counter_ns() - t0)
            slam.integrate(tracked)
            estimate = tracked.estimate
            run.stamps_ns.append(scan.stamp_ns)
            run.estimates.append(estimate)
            run.beam_counts.add(scan.beam_count)
            run.with_odometry += laser.odom is not None
            if on_estimate is not None:
                on_estimate(scan, estimate)
            bar.update(1)
            if run.scans % 50 == 0:
                bar.set_postfix_str(f"q={estimate.quality:.2f}", refresh=False)
    finally:
        bar.close()
    if slam_params.loop_closure:
        run.optimised = slam.finish()
        run.loops = slam.stats
    run.image = slam.map_image()
    run.integrate_ns = slam.integrate_ns
    run.backend_s = slam.stats.total_s
    run.wall_families_deg = [round(math.degrees(a), 2) for a in frontend.wall_families_rad]
    run.wall_s = time.perf_counter() - start
    return run


# ---------------------------------------------------------------------------------------------
# Report and outputs


def _percentile_ms(times_ns: Sequence[int], q: float) -> float | None:
    if not times_ns:
        return None
    return round(float(np.percentile(np.asarray(times_ns, dtype=np.float64), q)) / 1e6, 4)


def _flag_counts(estimates: Sequence[PoseEstimate]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for flag in PoseFlag:
        if flag is PoseFlag.NONE or flag.name is None:
            continue
        n = sum(1 for e in estimates if e.flags & flag)
        counts[flag.name] = n
    return counts


def _loop_report(stats: LoopStats | None) -> dict[str, Any] | None:
    """`report.json`'s `loop_closures`: None when the back end was off."""
    if stats is None:
        return None
    return {
        "accepted": stats.accepted,
        "rejected": dict(sorted(stats.rejected.items())),
        "search_s": round(stats.search_s, 3),
        "optimise_s": round(stats.optimise_s, 3),
        "solver_restarts": stats.solver_restarts,
    }


def trajectory_length_m(poses: Sequence[Pose2D]) -> float:
    if len(poses) < 2:
        return 0.0
    xy = np.array([(p.x_m, p.y_m) for p in poses], dtype=np.float64)
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())


def build_report(
    run: MapRun,
    *,
    input_info: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The `report.json` content of a run."""
    quality: npt.NDArray[np.float64] = np.array([e.quality for e in run.estimates], dtype=float)
    report: dict[str, Any] = {
        "scans": run.scans,
        "median_ms_per_scan": _percentile_ms(run.estimator_ns, 50),
        "p90_ms_per_scan": _percentile_ms(run.estimator_ns, 90),
        "p99_ms_per_scan": _percentile_ms(run.estimator_ns, 99),
        "max_ms_per_scan": _percentile_ms(run.estimator_ns, 100),
        "mean_ms_per_scan": (
            round(float(np.mean(run.estimator_ns)) / 1e6, 4) if run.estimator_ns else None
        ),
        "median_ms_per_integrate": _percentile_ms(run.integrate_ns, 50),
        "integrated_scans": len(run.integrate_ns),
        "keyframes": sum(1 for e in run.estimates if e.is_keyframe),
        "beam_counts": sorted(run.beam_counts),
        "scans_with_odometry": run.with_odometry,
        "quality": {
            "mean": round(float(quality.mean()), 4) if quality.size else None,
            "median": round(float(np.median(quality)), 4) if quality.size else None,
            "min": round(float(quality.min()), 4) if quality.size else None,
            "fraction_below_0_5": (
                round(float(np.mean(quality < QUALITY_LOW)), 4) if quality.size else None
            ),
        },
        "flags": _flag_counts(run.estimates),
        "trajectory_length_m": round(trajectory_length_m(run.poses), 3),
        "duration_s": (
            round((run.stamps_ns[-1] - run.stamps_ns[0]) / 1e9, 3) if run.stamps_ns else 0.0
        ),
        "wall_time_s": round(run.wall_s, 3),
        "scans_per_second": round(run.scans / run.wall_s, 1) if run.wall_s > 0 else None,
        "backend_s": round(run.backend_s, 3),
        "loop_closures": _loop_report(run.loops),
        # Angles (degrees, modulo 90) of the wall families the heading was measured on.
        "wall_families_deg": run.wall_families_deg,
        "front_end": run.front_end,
    }
    if input_info is not None:
        report["input"] = input_info
    if run.image is not None:
        image = run.image
        res_m = float(image.resolution_m)
        report["map"] = {
            "resolution_m": res_m,
            "width_cells": image.width,
            "height_cells": image.height,
            "width_m": round(image.width * res_m, 3),
            "height_m": round(image.height * res_m, 3),
            "origin_m": [float(image.origin_x_m), float(image.origin_y_m)],
            "known_cells": int(np.count_nonzero(image.occupancy >= 0)),
        }
    return report


def write_outputs(
    run: MapRun,
    out_dir: str | Path,
    *,
    input_info: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write trajectory.tum, trajectory_covariance.csv, map.png, map.pgm, map.yaml and
    report.json; return the report."""
    out = Path(out_dir)
    if run.image is None:
        raise OfflineError("the run has no map")
    image = run.image
    report = build_report(run, input_info=input_info)
    try:
        out.mkdir(parents=True, exist_ok=True)
        _write_text(out / "trajectory.tum", mapio.format_tum(run.stamps_ns, run.poses))
        _write_text(out / "trajectory_covariance.csv", format_covariance_csv(run))
        _write_bytes(
            out / "map.png",
            mapio.to_png(
                image, trajectory=run.poses, robot_pose=run.poses[-1] if run.poses else None
            ),
        )
        _write_bytes(out / "map.pgm", mapio.to_pgm(image))
        _write_text(out / "map.yaml", mapio.to_yaml(image, image_file="map.pgm"))
        _write_text(out / "report.json", json.dumps(report, indent=2, sort_keys=False) + "\n")
    except OSError as err:
        raise OfflineError(f"cannot write to {out}: {err.strerror or err}") from None
    return report


COVARIANCE_CSV_HEADER: Final = (
    "stamp,x_m,y_m,theta_rad,quality,flags,keyframe,c_xx,c_xy,c_xt,c_yx,c_yy,c_yt,c_tx,c_ty,c_tt"
)


def format_covariance_csv(run: MapRun) -> str:
    """`trajectory_covariance.csv`: the front end's pose, quality, flags, keyframe and
    covariance per scan (stamp in seconds with 9 decimals, as in trajectory.tum)."""
    lines = [COVARIANCE_CSV_HEADER]
    for stamp, e in zip(run.stamps_ns, run.estimates, strict=True):
        cov = tuple(e.covariance) if len(e.covariance) == 9 else (math.nan,) * 9
        lines.append(
            f"{mapio.format_tum_stamp(stamp)},{e.pose.x_m:.6f},{e.pose.y_m:.6f},"
            f"{e.pose.theta_rad:.8f},{e.quality:.4f},{int(e.flags)},{int(e.is_keyframe)},"
            + ",".join(f"{v:.6g}" for v in cov)
        )
    return "\n".join(lines) + "\n"


def check_output_dir(out_dir: str | Path) -> None:
    """Raise `OfflineError` when `out_dir` cannot become the output directory: checked before
    the input is read, so a mistyped --out fails at once, not after a whole bag."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OfflineError(f"--out {out} exists and is not a directory")
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise OfflineError(f"--out {out}: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OfflineError(f"--out {out}: {existing} is not writable")
    if existing == out:  # a real write also catches read-only file systems, even as root
        probe = out / f".write-test-{os.getpid()}"
        try:
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as err:
            raise OfflineError(f"cannot write to {out}: {err.strerror or err}") from None


def _write_bytes(path: Path, data: bytes) -> None:
    # Write then rename, so a reader never sees half a file.
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _write_text(path: Path, text: str) -> None:
    _write_bytes(path, text.encode("utf-8"))


def input_summary(
    info: LogInfo, *, scan_topic: str, odom_topic: str, use_odometry: bool
) -> dict[str, Any]:
    return {
        "path": info.path,
        "kind": info.kind,
        "scan_topic": scan_topic if info.kind != "mrec" else None,
        "odom_topic": odom_topic if info.kind != "mrec" else None,
        "scan_count": info.scan_count,
        "has_odometry": info.has_odom,
        "use_odometry": use_odometry,
        "duration_s": round(info.duration_s, 3),
        "tolerant_reader": info.tolerant,
    }


# ---------------------------------------------------------------------------------------------
# Command line


def _fail(message: str) -> None:
    first_line = message.strip().splitlines()[0] if message.strip() else "unknown error"
    sys.stderr.write(f"mapping-service map: error: {first_line}\n")
    sys.stderr.flush()


def run_map(args: argparse.Namespace) -> int:
    """`mapping-service map`: returns 0, 1 (output not writable) or 2 (input unreadable)."""
    resolution_m = float(args.resolution)
    if not (math.isfinite(resolution_m) and 0.005 <= resolution_m <= 10.0):
        _fail(f"--resolution must be between 0.005 and 10 m, got {args.resolution}")
        return EXIT_INPUT
    use_odometry = not args.no_odom
    try:
        check_output_dir(args.out)
    except OfflineError as err:
        _fail(str(err))
        return EXIT_OUTPUT
    try:
        info = probe_log(args.input, scan_topic=args.scan_topic, odom_topic=args.odom_topic)
        if info.scan_count == 0:
            topics = ", ".join(sorted(info.topics)) or "none"
            _fail(f"{args.input}: no scans on {args.scan_topic} (topics: {topics})")
            return EXIT_INPUT
        scans = iter_log_scans(
            args.input,
            scan_topic=args.scan_topic,
            odom_topic=args.odom_topic,
            use_odom=use_odometry,
        )
        show_progress = not args.no_progress and sys.stderr.isatty()
        run = map_scans(
            scans,
            resolution_m=resolution_m,
            use_odometry=use_odometry,
            total=info.scan_count,
            progress=show_progress,
            loop_closure=not args.no_loop_closure,
            front_end=args.front_end,
        )
    except LogError as err:
        _fail(str(err))
        return EXIT_INPUT
    if run.scans == 0:
        _fail(f"{args.input}: no readable scans")
        return EXIT_INPUT
    summary = input_summary(
        info, scan_topic=args.scan_topic, odom_topic=args.odom_topic, use_odometry=use_odometry
    )
    try:
        report = write_outputs(run, args.out, input_info=summary)
    except OfflineError as err:
        _fail(str(err))
        return EXIT_OUTPUT
    log.info("wrote %s", args.out)
    quality = report["quality"]
    sys.stdout.write(
        f"{report['scans']} scans, median {report['median_ms_per_scan']:.2f} ms/scan, "
        f"mean quality {quality['mean']:.2f} ({100 * quality['fraction_below_0_5']:.1f}% "
        f"below 0.5), {report['trajectory_length_m']:.1f} m travelled, "
        f"map {report['map']['width_m']:.1f} x {report['map']['height_m']:.1f} m -> {args.out}\n"
    )
    families = report["wall_families_deg"]
    if len(families) > 1:
        sys.stdout.write(
            f"wall families at {', '.join(f'{a:g}' for a in families)} deg "
            "(walls not parallel or perpendicular to the first ones)\n"
        )
    loops = report["loop_closures"]
    if loops is not None:
        rejected = sum(loops["rejected"].values())
        sys.stdout.write(
            f"loop closure: {loops['accepted']} accepted, {rejected} rejected, "
            f"{report['backend_s']:.1f} s in the back end\n"
        )
    return EXIT_OK
