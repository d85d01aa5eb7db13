"""Smoke test of the benchmark plumbing at tiny sizes (no timing assertions)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.common import make_synthetic_run, trajectory_errors
from bench.growth import run_growth
from bench.profiling import collapse_stacks
from bench.scale import analyze, metrics_delta, parse_prometheus, scale_targets
from bench.speed import run_speed

HAS_KISS = importlib.util.find_spec("kiss_icp") is not None
HAS_MPL = importlib.util.find_spec("matplotlib") is not None


@pytest.fixture(scope="module")
def tiny_results() -> dict[str, Any]:
    speed_run = make_synthetic_run(1, max_scans=6)
    growth_run = make_synthetic_run(1, size="small", laps=0.04)
    return {
        "speed": run_speed(speed_run, include_kiss=HAS_KISS, profile=True),
        "growth": run_growth(growth_run, profile=True),
    }


def test_speed_reports_every_method_on_the_same_scans(tiny_results: dict[str, Any]) -> None:
    speed = tiny_results["speed"]
    names = [m["name"] for m in speed["methods"]]
    assert names[0] == "ours"
    if HAS_KISS:
        assert "KISS-ICP" in names
    for m in speed["methods"]:
        assert len(m["times_ms"]) == speed["scans"] == 6
        assert m["timing"]["n"] == 5  # the first scan is left out
        assert math.isfinite(m["errors"]["ate_rmse_m"])
    assert {t["name"] for t in speed["targets"]} >= {"estimator median per 1,081-beam scan"}


def test_growth_reports_both_ends_of_the_run(tiny_results: dict[str, Any]) -> None:
    growth = tiny_results["growth"]
    assert growth["scans"] == len(growth["time_ms"]) == len(growth["distance_m"])
    assert growth["first_10pct"]["n"] >= 1
    assert growth["last_10pct"]["n"] >= 1
    assert len(growth["targets"]) == 1


def test_trajectory_errors_are_frame_independent() -> None:
    rng = np.random.default_rng(0)
    truth = np.cumsum(rng.normal(0, 0.3, (50, 3)), axis=0)
    # The same trajectory in another frame: rotated by 30° and shifted.
    c, s = math.cos(0.5), math.sin(0.5)
    est = np.column_stack(
        (
            c * truth[:, 0] - s * truth[:, 1] + 4.0,
            s * truth[:, 0] + c * truth[:, 1] - 2.0,
            truth[:, 2] + 0.5,
        )
    )
    errors = trajectory_errors(est, truth)
    for key in ("ate_rmse_m", "rpe_mean_m", "end_error_m", "heading_err_max_deg"):
        assert errors[key] == pytest.approx(0.0, abs=1e-9)


def test_analyze_counts_drops_and_latency() -> None:
    t0, t1 = 1_000_000_000, 2_000_000_000
    stamps = np.arange(t0, t1, 25_000_000)  # 40 scans per robot in the window
    scans = np.array([(r, st, st + 1_000_000) for r in (0, 1) for st in stamps], dtype=np.int64)
    # Robot 1 loses its last 4 scans; every answered scan arrives 10 ms after its stamp.
    poses = np.array(
        [(r, st, st + 10_000_000) for r in (0, 1) for st in stamps if r == 0 or st < stamps[-4]],
        dtype=np.int64,
    )
    out = analyze(["a", "b"], scans, poses, t0, t1)
    assert out["scans_published"] == 80
    assert out["dropped"] == 4
    assert out["latency_p50_ms"] == pytest.approx(10.0)
    assert out["publish_rate_per_robot_hz"] == pytest.approx(40.0)
    ok = {"robots": 10, "load": "loadgen", "mapper_processes": 2, **out}
    assert [t.passed for t in scale_targets([ok])] == [False]


def test_prometheus_deltas_sum_over_labels() -> None:
    before = parse_prometheus('# HELP x\nm_total{robot="a"} 1\nm_total{robot="b"} 2\nm_sum 0.5\n')
    after = parse_prometheus('m_total{robot="a"} 4\nm_total{robot="b"} 3\nm_sum 1.5\ng 7\n')
    assert metrics_delta(before, after) == {"m_total": 4.0, "m_sum": 1.0}


def test_collapse_stacks_shares() -> None:
    text = "main (a.py:1);work (b.py:2) 3\nmain (a.py:1);idle (c.py:9) 1\n"
    prof = collapse_stacks(text, "py-spy", "test")
    shares = {r.function: (r.self_share, r.inclusive_share) for r in prof.rows}
    assert shares["work (b.py)"] == (0.75, 0.75)
    assert shares["idle (c.py)"] == (0.25, 0.25)


@pytest.mark.skipif(not HAS_MPL, reason="matplotlib (the bench extra) is not installed")
def test_report_renders_with_plots(tiny_results: dict[str, Any], tmp_path: Path) -> None:
    from bench.common import machine_info
    from bench.report import PLOT_GROWTH, PLOT_SPEED, render

    res = {"machine": machine_info(), "quick": True, "wall_s": 1.0, **tiny_results}
    doc = tmp_path / "docs" / "benchmarks.md"
    text = render(res, doc, tmp_path / "docs" / "img")
    assert doc.read_text() == text
    for heading in ("## Machine", "## Targets", "## 1. Estimator speed", "## 3. Map growth"):
        assert heading in text
    assert "(img/" + PLOT_SPEED + ")" in text
    assert (tmp_path / "docs" / "img" / PLOT_SPEED).stat().st_size > 0
    assert (tmp_path / "docs" / "img" / PLOT_GROWTH).stat().st_size > 0


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_scale_point_runs_end_to_end(tmp_path: Path) -> None:
    """The real service, the measuring subscriber and the load generator, one robot, briefly."""
    from bench.scale import ScaleConfig, run_point

    cfg = ScaleConfig(
        robots=1,
        load="loadgen",
        mapper_processes=1,
        warmup_s=0.2,
        measure_s=1.0,
        drain_s=0.5,
        path_scans=40,
    )
    point = run_point(cfg, tmp_path)
    assert point["scans_published"] > 0
    assert point["poses_received"] > 0
    assert point["dropped"] == point["scans_published"] - point["poses_received"]
    assert point["service_rss_mib_max"] > 0
    assert point["loadgen"]["published"]["bench-r00"] > 0
