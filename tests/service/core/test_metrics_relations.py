"""The relation metric on hand-made trajectories."""

from __future__ import annotations

import math

import pytest

from service.core.metrics import MetricsError, parse_relations, relation_errors
from service.core.types import Pose2D


def test_parse_relations_skips_comments_and_rejects_garbage() -> None:
    rels = parse_relations(["# header", "", "1.0 2.0 0.5 0.0 0 0 0 0.1"])
    assert len(rels) == 1
    assert rels[0].truth == Pose2D(0.5, 0.0, 0.1)
    with pytest.raises(MetricsError):
        parse_relations(["1 2 3"])
    with pytest.raises(MetricsError):
        parse_relations(["1 2 3 4 5 6 7 x"])


def test_perfect_trajectory_has_zero_error_and_frame_invariance() -> None:
    truth = [Pose2D(0.0, 0.0, 0.0), Pose2D(1.0, 0.0, 0.5), Pose2D(1.5, 1.0, 1.5)]
    stamps = [1_000_000_000, 2_000_000_000, 3_000_000_000]
    lines = []
    for i in range(3):
        for j in range(i + 1, 3):
            d = truth[i].between(truth[j])
            lines.append(
                f"{stamps[i] / 1e9:.6f} {stamps[j] / 1e9:.6f} {d.x_m} {d.y_m} 0 0 0 {d.theta_rad}"
            )
    rels = parse_relations(lines)
    # The same trajectory in another map frame: relations do not care.
    frame = Pose2D(5.0, -2.0, 2.0)
    est = [frame.compose(p) for p in truth]
    r = relation_errors(stamps, est, rels)
    assert r.count == 3
    assert r.missing == 0
    assert r.trans_mean_m == pytest.approx(0.0, abs=1e-6)
    assert r.rot_max_deg == pytest.approx(0.0, abs=1e-6)


def test_known_error_and_missing_stamps() -> None:
    stamps = [1_000_000_000, 2_000_000_000]
    est = [Pose2D(0.0, 0.0, 0.0), Pose2D(1.1, 0.0, math.radians(2.0))]
    rels = parse_relations(["1.00005 2.0 1.0 0.0 0 0 0 0", "1.0 9.0 1 0 0 0 0 0"])
    r = relation_errors(stamps, est, rels)
    assert r.count == 1
    assert r.missing == 1
    assert r.trans_mean_m == pytest.approx(0.1)
    assert r.rot_mean_deg == pytest.approx(2.0)
    with pytest.raises(MetricsError):
        relation_errors(stamps, est, parse_relations(["7 8 1 0 0 0 0 0"]))
