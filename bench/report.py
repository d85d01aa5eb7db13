"""Render the results of a run as `docs/benchmarks.md` plus plots in `docs/img/`."""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

PLOT_SPEED = "bench_speed_per_scan.png"
PLOT_LATENCY = "bench_latency_vs_robots.png"
PLOT_GROWTH = "bench_time_per_scan_over_run.png"


def _f(x: Any, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    if isinstance(x, int):
        return f"{x:,}"
    return f"{x:,.{digits}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _verdict(passed: bool | None) -> str:
    return "n/a" if passed is None else ("**PASS**" if passed else "**MISS**")


def _targets_table(targets: Sequence[dict[str, Any]]) -> list[str]:
    return _table(
        ["target", "goal", "measured", "verdict"],
        [[t["name"], t["target"], t["measured"], _verdict(t["passed"])] for t in targets],
    )


def _profile_block(profile: dict[str, Any] | None) -> list[str]:
    if not profile:
        return []
    rows = []
    for r in profile["rows"]:
        calls = "" if r.get("calls") is None else _f(int(r["calls"]), 0)
        rows.append(
            [
                f"`{r['function']}`",
                f"{100 * r['self_share']:.1f} %",
                f"{100 * r['inclusive_share']:.1f} %",
                calls,
            ]
        )
    header = ["function", "own time", "incl. callees", "calls"]
    if profile["tool"] != "cProfile":
        header, rows = header[:3], [r[:3] for r in rows]
    return [
        "",
        f"Profile ({profile['tool']}): {profile['what']}. Top functions by own time:",
        "",
        *_table(header, rows),
    ]


# ---------------------------------------------------------------------------------------------
# Plots


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_speed(speed: dict[str, Any], path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    for m in speed["methods"]:
        t = np.sort(np.asarray(m["times_ms"][1:], dtype=float))
        if t.size:
            ax.plot(t, np.linspace(0, 100, t.size), label=m["name"])
    ax.set_xscale("log")
    ax.set_xlabel("time per scan (ms, log scale)")
    ax.set_ylabel("scans (%)")
    ax.set_title(f"Time per 1,081-beam scan, same {speed['scans']} scans, same run")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _scale_configs(scale: dict[str, Any]) -> list[tuple[str, int]]:
    """(load, mapper processes) pairs in report order: agents first, most processes first."""
    configs = {(p["load"], int(p.get("mapper_processes", 0))) for p in scale["points"]}
    return sorted(configs, key=lambda c: (0 if c[0] == "agents" else 1, -c[1]))


def _config_points(scale: dict[str, Any], load: str, k: int) -> list[dict[str, Any]]:
    return [
        p for p in scale["points"] if p["load"] == load and int(p.get("mapper_processes", 0)) == k
    ]


def plot_latency(scale: dict[str, Any], path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    colors = iter(("tab:red", "tab:blue", "tab:green", "tab:purple"))
    for load, k in _scale_configs(scale):
        pts = sorted(
            (p for p in _config_points(scale, load, k) if "error" not in p),
            key=lambda p: p["robots"],
        )
        if not pts:
            continue
        color = next(colors, "tab:gray")
        label = ("agents" if load == "agents" else "load generator") + (
            f", {k} mapper proc." if k else ", in-process"
        )
        n = [p["robots"] for p in pts]
        ax.plot(n, [p["latency_p50_ms"] for p in pts], "o--", color=color, label=f"{label} p50")
        ax.plot(n, [p["latency_p99_ms"] for p in pts], "s-", color=color, label=f"{label} p99")
    ns = sorted({p["robots"] for p in scale["points"]})
    ax.set_xticks(ns)
    ax.axhline(50.0, color="gray", lw=1, ls=":", label="target p99 50 ms")
    ax.set_yscale("log")
    ax.set_xlabel("robots at 40 Hz")
    ax.set_ylabel("scan → pose latency (ms, log)")
    ax.set_title("Scan→pose latency against the number of robots")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_growth(growth: dict[str, Any], path: Path) -> None:
    plt = _plt()
    dist = np.asarray(growth["distance_m"], dtype=float)
    t = np.asarray(growth["time_ms"], dtype=float)
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    ax.plot(dist, t, ".", ms=1.5, alpha=0.35, color="tab:blue", label="per scan")
    win = max(5, t.size // 50)
    cpu = np.asarray(growth.get("cpu_ms", []), dtype=float)
    curves = ((t, "tab:blue", "rolling median, wall"), (cpu, "tab:green", "rolling median, CPU"))
    for series, color, label in curves:
        if series.size > win:
            roll = np.array([np.median(series[i : i + win]) for i in range(series.size - win + 1)])
            ax.plot(dist[win // 2 : win // 2 + roll.size], roll, color=color, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("distance driven (m)")
    ax.set_ylabel("estimator + grid per scan (ms, log)")
    ax2 = ax.twinx()
    idx, rss = zip(*growth["rss_trace"], strict=True)
    ax2.plot(dist[list(idx)], rss, color="tab:orange", label="RSS growth (MiB)")
    ax2.set_ylabel("RSS growth (MiB)", color="tab:orange")
    ax.set_title(f"Cost per scan over a {growth['length_m']:.0f} m run")
    ax.grid(True, which="both", alpha=0.3)
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# Sections


def _sizes_text(z: dict[str, Any]) -> str:
    speed = "all scans of the loop" if z["speed_scans"] is None else f"{z['speed_scans']} scans"
    robots = ", ".join(str(n) for n in z["scale_robots"])
    return (
        f"speed on {speed}; scale with N = {robots} robots, {z['scale_warmup_s']:g} s warm-up "
        f"and {z['scale_measure_s']:g} s measured per point; growth in the "
        f"{z['growth_building']} building over {z['growth_laps_between']} laps + 10 %"
    )


def _sizes_lines(sizes: dict[str, Any] | None) -> list[str]:
    if not sizes:
        return []
    return [
        (
            f"Sizes: full mode: {_sizes_text(sizes['full'])}. Quick mode: "
            f"{_sizes_text(sizes['quick'])}."
        ),
        "",
    ]


def _caveats() -> list[str]:
    return [
        "",
        "## How to read these numbers",
        "",
        (
            "- Everything ran on the one machine described above. Its two cores are shared with "
            "other work (load average in the header), which inflates wall-clock times; the "
            "compared methods ran interleaved under the same conditions, so their ratios are "
            "the robust figures."
        ),
        (
            "- In the scale runs the load (agents or generator) and the measuring subscriber run "
            "on the same two cores as the service and take CPU from it; their CPU is reported "
            "beside the service's."
        ),
        (
            "- Latency includes Zenoh transport both ways (agent → service → subscriber) on "
            "loopback and the service's queueing; it is measured on one clock."
        ),
        (
            "- The growth run repeats the building's corridor loop; the map stops growing after "
            "the first lap."
        ),
    ]


def _header(res: dict[str, Any]) -> list[str]:
    m = res["machine"]
    mode = "quick" if res["quick"] else "full"
    lines = [
        "# Benchmarks",
        "",
        f"<!-- Generated by `{m['command']}`; do not edit by hand. -->",
        "",
        (
            f"Generated by `{m['command']}` ({mode} mode) on {m['date_utc']}, in "
            f"{res['wall_s'] / 60:.1f} min. Re-run with `make bench` (full) or `make "
            "bench-quick`; raw numbers are in `bench/out/results.json`."
        ),
        "",
        *_sizes_lines(res.get("sizes")),
        "## Machine",
        "",
    ]
    rows = [
        ["CPU", f"{m['cpu_model']}, {m['cores']} cores (`/proc/cpuinfo`, `os.cpu_count()`)"],
        ["memory", m["memory"]],
        ["OS", m["os"]],
        ["Python", m["python"]],
        ["numpy", f"{m['numpy']} ({m['blas']})"],
        ["eclipse-zenoh", m["zenoh"]],
        ["kiss-icp", m["kiss_icp"]],
        ["git commit", f"`{m['git_commit']}`"],
        ["load average at start", m["load_average_at_start"]],
        ["OpenBLAS overrides", m["openblas_env"]],
    ]
    lines += _table(["", ""], rows)
    lines += [
        "",
        (
            "The machine is small and shared: its two cores also ran other work during the run "
            "(see the load average), so single numbers carry some noise; the methods compared in "
            "each section ran side by side under the same conditions."
        ),
    ]
    return lines


def _speed_section(speed: dict[str, Any] | None, img_rel: str) -> list[str]:
    lines = ["", "## 1. Estimator speed", ""]
    if not speed:
        return [*lines, "Not run."]
    if "error" in speed:
        return [*lines, f"Not measured: {speed['error']}"]
    lines += [
        (
            f"{speed['scans']:,} scans of {speed['beams']:,} beams (simulated UTM-30LX, 270°) "
            f"along {speed['length_m']:.0f} m of a synthetic building (seed {speed['seed']}), one "
            f"scan every {speed['spacing_m']} m as in the paper. All methods ran in one process "
            "on the same scans, interleaved scan by scan with the order rotating, so they shared "
            "the machine's conditions; the first scan (initialisation) is left out. Times are "
            "wall clock; the CPU column is the process's CPU time over the same call (all "
            "threads), which leaves out waiting for a core on this shared machine. Accuracy is "
            "against the simulator's ground truth: ATE after the best rigid 2D alignment, the "
            "mean error of the scan-to-scan motion (RPE), the worst heading error, and the error "
            "of the last pose seen from the first (the loop gap)."
        ),
        "",
    ]
    rows = []
    ratios = speed.get("ratios_vs_ours", {})
    for m in speed["methods"]:
        t, e = m["timing"], m["errors"]
        ratio = "1" if m["name"] == "ours" else f"{ratios.get(m['name'], math.nan):.3g}×"
        rows.append(
            [
                f"**{m['name']}**",
                _f(t["median_ms"], 3),
                _f(t["p99_ms"], 3),
                _f(m["cpu"]["median_ms"], 3),
                ratio,
                _f(e["ate_rmse_m"], 3),
                _f(e["rpe_mean_m"], 4),
                _f(e["heading_err_max_deg"], 2),
                _f(e["end_error_m"], 3),
            ]
        )
    lines += _table(
        [
            "method",
            "median ms/scan",
            "p99 ms/scan",
            "median CPU ms/scan",
            "median time vs ours",
            "ATE RMSE (m)",
            "RPE mean (m)",
            "max heading err (°)",
            "end-pose error (m)",
        ],
        rows,
    )
    quotes = []
    for name, r in ratios.items():
        if r >= 1.0:
            quotes.append(f"ours takes 1/{r:.3g} of the time of {name} ({r:.3g}× faster)")
        else:
            quotes.append(f"{name} takes {r:.3g}× the time of ours ({1 / r:.3g}× faster than ours)")
    if quotes:
        lines += ["", "Median time per scan: " + "; ".join(quotes) + "."]
    lines += ["", "Methods:", ""]
    lines += [f"- **{m['name']}**: {m['description']}." for m in speed["methods"]]
    lines += [f"- note: {n}" for n in speed.get("notes", [])]
    alone = speed.get("alone")
    if alone:
        t, c = alone["timing"], alone["cpu"]
        lines += [
            "",
            (
                f"Ours alone on the same {alone['scans']:,} scans (best median of "
                f"{alone['passes']} passes, a fresh estimator each): median {t['median_ms']:.3f} "
                f"ms, p99 {t['p99_ms']:.3f} ms, CPU median {c['median_ms']:.3f} ms per scan. "
                "Interleaved, each of our calls starts with caches the other methods' calls "
                "filled, which the side-by-side median above includes; alone is how a mapper "
                "process runs it. The ratios are quoted from the interleaved run."
            ),
        ]
    live = speed.get("live")
    if live:
        t, c = live["timing"], live["cpu"]
        lines += [
            "",
            (
                "The service's own path is different: a UTM-30LX at 40 Hz moves ~2 cm between "
                "scans, so few scans are keyframes and the prediction is close. Ours alone on "
                f"{live['scans']:,} such "
                f"scans (best median of {live.get('passes', 1)} passes; "
                f"the load generator's path, same building): median {t['median_ms']:.3f} "
                f"ms, p99 {t['p99_ms']:.3f} ms, CPU median {c['median_ms']:.3f} ms per scan."
            ),
        ]
    lines += ["", f"![time per scan, cumulative]({img_rel}/{PLOT_SPEED})", ""]
    lines += _targets_table(speed["targets"])
    lines += _profile_block(speed.get("profile"))
    return lines


def _scale_section(scale: dict[str, Any] | None, img_rel: str) -> list[str]:
    lines = ["", "## 2. End to end and scale", ""]
    if not scale:
        return [*lines, "Not run."]
    if "error" in scale:
        return [*lines, f"Not measured: {scale['error']}"]
    lines += [
        (
            f"N robots publish 1,081-beam scans at {scale['rate_hz']:g} Hz each over Zenoh (TCP "
            "on loopback) into one `mapping-service serve` with one mapping session per robot, "
            f"run with `--mapper-processes {scale.get('mapper_processes', 0)}` (one per core: "
            "each of that many worker processes takes its robots' scans from Zenoh and decodes, "
            "records, maps and publishes them; the service's own process serves HTTP; "
            "`docs/service.md`). The load generator also drives the "
            "service with the estimators in its own process (`--mapper-processes 0`, the "
            f"default), side by side. After start-up and a {scale['warmup_s']:g} s warm-up, a "
            f"{scale['measure_s']:g} s window is measured. A separate subscriber process receives "
            "every scan (the agents connect to it too) and every pose: *published* counts the "
            "scans stamped in the window, *dropped* those whose pose never came, *latency* is "
            "the pose's arrival minus the scan's `host_stamp_ns` (taken by the agent just before "
            "it publishes). CPU is user + system time over the window (100 % = one core); the "
            "service's CPU and RSS include its mapper processes."
        ),
        "",
        "Two loads:",
        "",
        (
            "- **emulated agents**: N `sensor-agent --emulate` processes, the real robot path "
            "(simulated building → emulated UTM-30LX speaking SCIP 2.0 on a pty → driver → "
            "Zenoh). Every agent is a Python process on the same two cores as the service, so at "
            "larger N the agents themselves take most of the CPU ('load CPU');"
        ),
        (
            "- **load generator**: one `bench.loadgen` process publishes pre-simulated scans for "
            "all N robots at 40 Hz each, which isolates the service's own capacity."
        ),
        "",
        (
            "Columns: *published Hz/robot* is the scan rate the load actually achieved; "
            "*poses/s* the poses delivered to the subscriber during the window; *dropped* "
            "the window's scans that never got a pose (after the window the load stops and the "
            "service works off its queues, up to a minute, so each scan is either answered, "
            "however late, or discarded); *service ms/scan* the "
            "service's own worker time per scan (decode, record, estimate, map, publish; from "
            "its `/metrics` histogram; wall time of one ingest thread, so with many robots it "
            "includes waiting for the GIL, a mapper process and a core); *service queue drops* "
            "the scans its per-robot queues discarded (from `/metrics`); *load CPU* is the "
            "agents' or the generator's CPU, *machine busy* all processes on the machine, other "
            "users' included."
        ),
        "",
    ]
    for load, k in _scale_configs(scale):
        pts = sorted(_config_points(scale, load, k), key=lambda p: p["robots"])
        title = ("Emulated agents" if load == "agents" else "Load generator") + (
            f", {k} mapper processes" if k else ", estimators in the service's process"
        )
        rows = []
        for p in pts:
            if "error" in p:
                rows.append([str(p["robots"]), f"failed: {p['error']}", *[""] * 11])
                continue
            md = p.get("metrics_delta", {})
            work_n = md.get("mapping_scan_processing_seconds_count", 0.0)
            work_ms = 1e3 * md.get("mapping_scan_processing_seconds_sum", 0.0) / work_n
            rows.append(
                [
                    str(p["robots"]),
                    f"{p['publish_rate_per_robot_hz']:.1f}",
                    _f(p["sustained_scans_per_s"], 1),
                    f"{p['dropped']:,} of {p['scans_published']:,}",
                    _f(p["latency_p50_ms"], 1),
                    _f(p["latency_p99_ms"], 1),
                    _f(work_ms if work_n else None, 2),
                    _f(int(md.get("mapping_scans_dropped_total", 0))),
                    _f(p["service_cpu_pct"], 0),
                    _f(p["service_rss_mib_max"], 0),
                    _f(p["load_cpu_pct"], 0),
                    _f(p["subscriber_cpu_pct"], 0),
                    _f(p["machine_busy_pct"], 0),
                ]
            )
        lines += [f"**{title}**", ""]
        lines += _table(
            [
                "robots",
                "published Hz/robot",
                "poses/s",
                "dropped",
                "p50 ms",
                "p99 ms",
                "service ms/scan",
                "service queue drops",
                "service CPU %",
                "service RSS MiB",
                "load CPU %",
                "subscriber CPU %",
                "machine busy %",
            ],
            rows,
        )
        lines.append("")
    lines += [f"![latency against robots]({img_rel}/{PLOT_LATENCY})", ""]
    lines += _targets_table(scale["targets"])
    prof = scale.get("profile")
    if prof:
        lines += _profile_block(prof)
    lines += _scale_misses(scale)
    return lines


def _scale_misses(scale: dict[str, Any]) -> list[str]:
    """Why each configuration that missed the target missed it, from the measured points."""
    lines: list[str] = []
    cores = scale.get("mapper_processes", 0) or 1
    for load, k in _scale_configs(scale):
        big = [
            p
            for p in _config_points(scale, load, k)
            if "error" not in p and p["robots"] >= 10 and (p["dropped"] or p["latency_p99_ms"] > 50)
        ]
        if not big:
            continue
        p = min(big, key=lambda q: q["robots"])
        where = (
            f"at N={p['robots']} ({'agents' if load == 'agents' else 'load generator'}, "
            f"{f'{k} mapper processes' if k else 'in-process'}) the service used "
            f"{p['service_cpu_pct']:.0f} % CPU, the load {p['load_cpu_pct']:.0f} %, the "
            f"subscriber {p['subscriber_cpu_pct']:.0f} %, and the machine was "
            f"{p['machine_busy_pct']:.0f} % busy (100 % = all {cores} cores)."
        )
        if k == 0:
            why = (
                "Why it is missed in-process: estimating, mapping, decoding, recording and "
                "publishing run in Python under one interpreter lock, so one process uses one "
                "core however many threads it has (a thread per robot measured 1.5-2× the CPU "
                "per scan of one thread: `docs/service.md`); ten robots at 40 Hz need 400 "
                "scans/s, 2.5 ms per scan for everything, and the estimator and grid alone take "
                "most of that. Mapper processes lift that limit: "
            )
        else:
            why = (
                "Why it is missed with mapper processes: the estimators no longer share one "
                "core, but on this small machine the service's process, its mapper processes, "
                "the load and the subscriber all share the same cores, and a scan's estimate "
                "in a mapper process that also serves other robots costs more than in a "
                "quiet one (cold caches between scans). "
            )
        lines += ["", why + where]
    return lines


def _growth_section(growth: dict[str, Any] | None, img_rel: str) -> list[str]:
    lines = ["", "## 3. Map growth", ""]
    if not growth:
        return [*lines, "Not run."]
    if "error" in growth:
        return [*lines, f"Not measured: {growth['error']}"]
    grid_note = (
        f"`OccupancyGrid.integrate` on {'keyframes' if growth['keyframes_only'] else 'every scan'}"
        f" ({growth['grid_integrations']:,} integrations)"
    )
    lines += [
        (
            "One estimator and one occupancy grid, as in a mapping session, over "
            f"{growth['length_m']:.0f} m ({growth['scans']:,} scans, one every "
            f"{growth['spacing_m']} m; {'; '.join(growth['notes'])}). Per scan: the default "
            f"front end's `process` (the matcher), then {grid_note}, as the service's session "
            "does. "
            f"The building's corridor loop is {growth['loop_length_m']:.0f} m, so a long run "
            "drives it again; the length is chosen so that the last 10 % of the run covers the "
            "same corridors as the first 10 % (whole laps later): the two windows differ by the "
            "state accumulated in between, not by the place. The grid stops growing once the "
            "loop is mapped; the trajectory keeps growing."
        ),
        "",
        (
            "The two windows are timed side by side: while the long run drives its last 10 % "
            f"({growth['window_scans']:,} scans), a second, fresh estimator and grid process the "
            "run's first 10 %, interleaved scan by scan, so both see the same machine. (Timed "
            "minutes apart in one pass, as the plot shows, they also measure how busy this "
            "shared machine was at either time: there the change was "
            f"{growth['sequential_change']:+.1%}.) Memory is the growth of this process's RSS "
            "since the start of the run, read before the fresh pipeline starts."
        ),
        "",
    ]
    f10, l10 = growth["first_10pct"], growth["last_10pct"]
    rows = [
        [
            "median per scan, estimator + grid (ms)",
            _f(f10["median_ms"], 3),
            _f(l10["median_ms"], 3),
        ],
        ["p99 per scan (ms)", _f(f10["p99_ms"], 3), _f(l10["p99_ms"], 3)],
        [
            "median CPU time per scan (ms)",
            _f(growth["first_10pct_cpu"]["median_ms"], 3),
            _f(growth["last_10pct_cpu"]["median_ms"], 3),
        ],
        ["mean per scan (ms)", _f(f10["mean_ms"], 3), _f(l10["mean_ms"], 3)],
        [
            "mean, estimator only (ms)",
            _f(growth["first_10pct_estimator_mean_ms"], 3),
            _f(growth["last_10pct_estimator_mean_ms"], 3),
        ],
        [
            "mean, grid only (ms)",
            _f(growth["first_10pct_grid_mean_ms"], 3),
            _f(growth["last_10pct_grid_mean_ms"], 3),
        ],
        [
            "map size (cells in the bounding box of known cells)",
            _f(growth.get("grid_cells_after_first_10pct")),
            _f(growth.get("grid_cells_end")),
        ],
        [
            "RSS growth (MiB; after the first 10 % / at 90 % of the run)",
            _f(growth["rss_growth_mib_after_first_10pct"], 1),
            _f(growth["rss_growth_mib_at_90pct"], 1),
        ],
    ]
    lines += _table(["", "first 10 % of the run", "last 10 % of the run"], rows)
    e = growth["errors"]
    lines += [
        "",
        (
            f"Trajectory over the whole run: ATE {e['ate_rmse_m']:.3f} m, end-pose error "
            f"{e['end_error_m']:.3f} m, worst heading error {e['heading_err_max_deg']:.2f}°."
        ),
        "",
        f"![time per scan over the run]({img_rel}/{PLOT_GROWTH})",
        "",
    ]
    lines += _targets_table(growth["targets"])
    lines += _profile_block(growth.get("profile"))
    return lines


def _accuracy_section(accuracy: dict[str, Any] | None, img_dir: Path, img_rel: str) -> list[str]:
    lines = ["", "## 4. Accuracy", ""]
    if not accuracy:
        return [*lines, "Not run."]
    if "error" in accuracy:
        return [*lines, f"Not measured: {accuracy['error']}"]
    text = accuracy["markdown"]
    # The evaluation's map pictures live in bench/out (not committed): copy them beside ours.
    for name, src in accuracy.get("pictures", {}).items():
        if Path(src).is_file():
            shutil.copyfile(src, img_dir / f"accuracy_{name}")
            text = text.replace(f"`{name}`", f"[{name}]({img_rel}/accuracy_{name})")
    # Demote the evaluation's headings below this section's.
    text = re.sub(
        r"^(#{1,5}) ", lambda mt: "#" * min(6, len(mt.group(1)) + 1) + " ", text, flags=re.M
    )
    lines += [
        (
            f"From `{accuracy['command']}` (the relation metric of Kümmerle et al. 2009 on the "
            "real recordings, beside the published figures)."
        ),
        "",
        text.strip(),
    ]
    return lines


def _fleet_row(p: dict[str, Any], label: str) -> list[str]:
    if "error" in p:
        return [label, str(p["robots"]), f"failed: {p['error']}", "", "", "", "", "", "", "", ""]
    load = p.get("loadavg_before") or [math.nan]
    return [
        label,
        str(p["robots"]),
        f"{p['dropped']:,} of {p['scans_published']:,}",
        _f(p["latency_p50_ms"], 1),
        _f(p["latency_p99_ms"], 1),
        _f(p.get("scan_processing_ms_mean"), 2),
        _cpu_per_scan(p),
        _f(p["service_cpu_pct"], 0),
        _f(p["machine_busy_pct"], 0),
        _f(load[0], 1),
        _f(p["publish_rate_min_robot_hz"], 1),
    ]


def _cpu_per_scan(p: dict[str, Any]) -> str:
    """CPU-ms per accepted scan: the service's main process + its mapper processes."""
    by_proc = p.get("cpu_ms_per_scan_by_process") or {}
    if not by_proc:
        return ""
    main = by_proc.get("main", math.nan)
    mappers = sum(v for k, v in by_proc.items() if k != "main")
    return f"{main + mappers:.2f} ({main:.2f} + {mappers:.2f})"


FLEET_HEADER = [
    "run",
    "robots × 40 Hz",
    "dropped",
    "p50 ms",
    "p99 ms",
    "per-scan ms",
    "service CPU-ms/scan (main + mappers)",
    "service CPU %",
    "machine busy %",
    "load avg 1 min",
    "slowest robot Hz",
]


def fleet_section(fleet: dict[str, Any] | None) -> list[str]:
    lines = ["", "## 5. A fleet on one box", ""]
    if not fleet:
        return [*lines, "Not run."]
    if "error" in fleet:
        return [*lines, f"Not measured: {fleet['error']}"]
    lines += [
        (
            "One `bench.loadgen` process publishes N robots' scans at 40 Hz each into one "
            f"`mapping-service serve --mapper-processes {fleet['mapper_processes']}` on this "
            f"{fleet['cores']}-core machine; a separate subscriber process times scan→pose. "
            f"Warm-up {fleet['warmup_s']:g} s, window {fleet['measure_s']:g} s. *Service CPU* is "
            "its process tree (mapper processes included; 100 % = one core), *machine busy* is "
            "every process on the machine (100 % = all cores). The machine is shared with other "
            "work: the load average beside each point says how much (above the core count, "
            "every process waits for a core, ours included). *Per-scan ms* is the service's "
            "`mapping_scan_processing_seconds` mean (decode, record, estimate, publish). "
            "*Service CPU-ms/scan* is the CPU time (user + system) of the service's main "
            "process and of its mapper processes per accepted scan: far less sensitive to "
            "a busy neighbour than any wall time."
        ),
        "",
        *_table(
            FLEET_HEADER,
            [_fleet_row(p, "capacity") for p in fleet["capacity"]]
            + [
                _fleet_row(
                    p,
                    f"fan-out: {p['sse_clients']} SSE + {p['zenoh_pose_subscribers']} Zenoh"
                    if p.get("sse_clients")
                    else "fan-out: none",
                )
                for p in fleet["fanout"]
            ],
        ),
        "",
    ]
    pairs = fleet.get("fanout_pairs") or []
    if pairs:
        lines += [
            "Fan-out side by side (each pair run back to back):",
            "",
            *_table(
                [
                    "per-scan ms without → with",
                    "ratio",
                    "p99 ms without → with",
                    "ratio",
                    "dropped without → with",
                ],
                [
                    [
                        f"{_f(r['scan_ms_without'])} → {_f(r['scan_ms_with'])}",
                        f"×{r['scan_ratio']:.2f}",
                        f"{_f(r['p99_without'], 1)} → {_f(r['p99_with'], 1)}",
                        f"×{r['p99_ratio']:.2f}",
                        f"{r['dropped_without']} → {r['dropped_with']}",
                    ]
                    for r in pairs
                ],
            ),
            "",
        ]
    for p in fleet["fanout"]:
        fan = p.get("fanout")
        if fan:
            lines.append(
                f"With subscribers: {fan['sse_connected']} of {fan['sse_requested']} SSE streams "
                f"connected, {fan['sse_events']:,} pose events received by them, "
                f"{fan['zenoh_subscribers']} Zenoh subscribers "
                + ("(behind one router, as in a site) " if fan.get("zenoh_via_router") else "")
                + "each saw new poses at "
                f"≥ {fan['zenoh_polls_with_pose_min']} polls (every 0.5 s); the service counted "
                f"{_f(p.get('stream_poses_dropped'), 0)} stream poses dropped."
            )
    return lines


def render_fleet_only(res: dict[str, Any], doc_path: Path) -> str:
    """`python -m bench --fleet-only`: the fleet section alone, in a file of its own."""
    fleet = res.get("fleet")
    lines = [
        "# Fleet benchmark",
        "",
        (
            f"Machine: {res['machine'].get('cpu_model', '?')}, "
            f"{res['machine'].get('cores', '?')} cores, load average at the start "
            f"{res['machine'].get('load_average_at_start', '?')}. "
            "Written by `python -m bench --fleet-only`."
        ),
        "",
        "## Targets",
        "",
        *_targets_table(fleet.get("targets", []) if fleet else []),
        *fleet_section(fleet),
    ]
    text = "\n".join(lines).rstrip() + "\n"
    doc_path.parent.mkdir(parents=True, exist_ok=True)
    doc_path.write_text(text)
    return text


def render(res: dict[str, Any], doc_path: Path, img_dir: Path) -> str:
    """Write the plots and the markdown; returns the markdown."""
    img_dir.mkdir(parents=True, exist_ok=True)
    img_rel = os.path.relpath(img_dir, doc_path.parent)
    speed, scale, growth = res.get("speed"), res.get("scale"), res.get("growth")
    if speed and "error" not in speed:
        plot_speed(speed, img_dir / PLOT_SPEED)
    if scale and any("error" not in p for p in scale["points"]):
        plot_latency(scale, img_dir / PLOT_LATENCY)
    if growth and "error" not in growth:
        plot_growth(growth, img_dir / PLOT_GROWTH)
    fleet = res.get("fleet")
    all_targets = [
        t
        for sec in (speed, scale, growth, fleet)
        if sec and "targets" in sec
        for t in sec["targets"]
    ]
    lines = _header(res)
    lines += ["", "## Targets", ""]
    lines += _targets_table(all_targets) if all_targets else ["No target was measured."]
    lines += _speed_section(speed, img_rel)
    lines += _scale_section(scale, img_rel)
    lines += _growth_section(growth, img_rel)
    lines += _accuracy_section(res.get("accuracy"), img_dir, img_rel)
    if fleet is not None:
        lines += fleet_section(fleet)
    lines += _caveats()
    text = "\n".join(lines).rstrip() + "\n"
    # Sections measured by their own benchmarks (bench.foxglove_cost) outlive a regeneration.
    text += kept_sections(doc_path)
    doc_path.parent.mkdir(parents=True, exist_ok=True)
    doc_path.write_text(text)
    return text


def kept_sections(doc_path: Path) -> str:
    """The `<!-- keep:NAME -->` ... `<!-- /keep:NAME -->` blocks of the current document."""
    try:
        old = doc_path.read_text()
    except OSError:
        return ""
    blocks = re.findall(r"\n<!-- keep:([\w-]+) -->\n.*?\n<!-- /keep:\1 -->\n", old, flags=re.S)
    out = []
    for name in blocks:
        start = old.index(f"\n<!-- keep:{name} -->\n")
        end = old.index(f"\n<!-- /keep:{name} -->\n", start) + len(f"\n<!-- /keep:{name} -->\n")
        out.append(old[start:end])
    return "".join(out)
