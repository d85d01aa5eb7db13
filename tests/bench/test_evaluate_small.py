"""bench.evaluate at a tiny size: the metric plumbing, the tables and the files it writes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench.evaluate import (
    PUBLISHED_FALLBACK,
    RunResult,
    SyntheticSequence,
    evaluate_synthetic,
    make_sequence,
    published_table,
    real_table,
    render_markdown,
    truth_relations,
)
from service.core.metrics import relation_errors
from service.core.types import Pose2D


@pytest.fixture(scope="module")
def sequence() -> SyntheticSequence:
    return make_sequence(2, size="small", max_scans=40)


def test_truth_relations_give_zero_error_on_the_truth(sequence: SyntheticSequence) -> None:
    local, far = truth_relations(sequence, seed=2)
    assert local
    poses = [Pose2D(*map(float, p)) for p in sequence.truth]
    errors = relation_errors(sequence.stamps_ns, poses, local + far)
    assert errors.trans_max_m < 1e-9
    assert errors.rot_max_deg < 1e-9
    # The same trajectory in another frame (rotated and shifted) has the same relations.
    frame = Pose2D(3.0, -2.0, 0.7)
    moved = [frame.compose(p) for p in poses]
    assert relation_errors(sequence.stamps_ns, moved, local).trans_max_m < 1e-9


def test_synthetic_run_writes_map_and_metrics(sequence: SyntheticSequence, tmp_path: Path) -> None:
    result = evaluate_synthetic(sequence, use_odometry=True, out_dir=tmp_path)
    assert result.scans == 40
    assert (tmp_path / result.map_png).read_bytes().startswith(b"\x89PNG")
    run_dir = tmp_path / "synthetic-2-odom"
    for name in ("map.png", "map.pgm", "map.yaml", "trajectory.tum", "report.json"):
        assert (run_dir / name).is_file()
    assert json.loads((run_dir / "report.json").read_text())["scans"] == 40
    for key in ("loop_gap_x_m", "loop_gap_y_m", "heading_err_max_deg"):
        assert np.isfinite(result.extra[key])
    markdown = render_markdown([], [result], quick=True, skipped=["ACES: absent"], published={})
    assert "synthetic 2" in markdown
    assert "_Skipped: ACES: absent_" in markdown


def test_published_figures_and_real_table(tmp_path: Path) -> None:
    table = published_table(tmp_path / "absent.md")
    assert table == PUBLISHED_FALLBACK
    md = tmp_path / "PUBLISHED_ERRORS.md"
    md.write_text("| dataset | a | b | c | d |\n|---|---|---|---|---|\n| ACES | 1 | 2 | 3 | 4 |\n")
    assert published_table(md)["ACES"] == ("1", "2", "3", "4")
    row = RunResult(
        dataset="ACES",
        mode="no odometry",
        scans=10,
        relations=5,
        relations_missing=0,
        trans_mean_m=0.1,
        trans_std_m=0.05,
        trans_max_m=0.3,
        rot_mean_deg=1.0,
        rot_std_deg=0.5,
        rot_max_deg=2.0,
        median_ms_per_scan=2.0,
        p99_ms_per_scan=5.0,
        quality_mean=0.9,
        quality_below_0_5=0.01,
        wall_s=1.0,
        map_png="aces-no-odom.png",
    )
    text = real_table([row], PUBLISHED_FALLBACK)
    assert "**0.100 ± 0.050 m**" in text
    assert "0.173 ± 0.614 m" in text
