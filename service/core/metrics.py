"""The relation metric of Kümmerle et al. 2009 ("On measuring the accuracy of SLAM algorithms").

A relation `t1 t2 x y z roll pitch yaw` is the true pose at t2 expressed in the pose at t1. For an
estimated trajectory, `d = inverse(x(t1)) ∘ x(t2)` and the error is `e = d ⊖ truth`. We report
mean ± std and max of |e_xy| (m) and |e_theta| (deg) over all relations whose stamps match an
estimated pose within a tolerance (0.1 ms: every relation stamp is a scan header stamp).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from service.core.types import Pose2D


class MetricsError(ValueError):
    """Malformed relations text or no usable relation."""


@dataclass(frozen=True, slots=True)
class Relation:
    t1_s: float
    t2_s: float
    truth: Pose2D


@dataclass(frozen=True, slots=True)
class RelationErrors:
    count: int  # relations evaluated
    missing: int  # relations whose stamps had no estimated pose
    trans_mean_m: float
    trans_std_m: float
    trans_max_m: float
    rot_mean_deg: float
    rot_std_deg: float
    rot_max_deg: float
    trans_errors_m: npt.NDArray[np.float64]
    rot_errors_deg: npt.NDArray[np.float64]


def parse_relations(lines: Iterable[str]) -> list[Relation]:
    """Parse `t1 t2 x y z roll pitch yaw` lines; blank lines and `#` comments are skipped."""
    out: list[Relation] = []
    for n, line in enumerate(lines, 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = text.split()
        if len(parts) < 8:
            raise MetricsError(f"relations line {n}: expected 8 numbers, got {len(parts)}")
        try:
            t1, t2, x, y, _z, _roll, _pitch, yaw = (float(v) for v in parts[:8])
        except ValueError as exc:
            raise MetricsError(f"relations line {n}: {exc}") from exc
        out.append(Relation(t1, t2, Pose2D(x, y, yaw)))
    return out


def relation_errors(
    stamps_ns: Sequence[int] | npt.NDArray[np.int64],
    poses: Sequence[Pose2D],
    relations: Sequence[Relation],
    tolerance_s: float = 1e-4,
) -> RelationErrors:
    """Evaluate the estimated trajectory (`poses[i]` at `stamps_ns[i]`) against `relations`."""
    if len(stamps_ns) != len(poses):
        raise MetricsError("stamps and poses differ in length")
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    sorted_s = stamps[order].astype(np.float64) * 1e-9

    def find(t_s: float) -> int | None:
        i = int(np.searchsorted(sorted_s, t_s))
        best: int | None = None
        for j in (i - 1, i):
            if (
                0 <= j < sorted_s.size
                and abs(sorted_s[j] - t_s) <= tolerance_s
                and (best is None or abs(sorted_s[j] - t_s) < abs(sorted_s[best] - t_s))
            ):
                best = j
        return None if best is None else int(order[best])

    te: list[float] = []
    re: list[float] = []
    missing = 0
    for rel in relations:
        i1, i2 = find(rel.t1_s), find(rel.t2_s)
        if i1 is None or i2 is None:
            missing += 1
            continue
        d = poses[i1].between(poses[i2])
        e = rel.truth.between(d)  # d ⊖ truth
        te.append(math.hypot(e.x_m, e.y_m))
        re.append(abs(math.degrees(e.theta_rad)))
    if not te:
        raise MetricsError("no relation matched an estimated pose")
    t = np.asarray(te)
    r = np.asarray(re)
    return RelationErrors(
        count=t.size,
        missing=missing,
        trans_mean_m=float(t.mean()),
        trans_std_m=float(t.std()),
        trans_max_m=float(t.max()),
        rot_mean_deg=float(r.mean()),
        rot_std_deg=float(r.std()),
        rot_max_deg=float(r.max()),
        trans_errors_m=t,
        rot_errors_deg=r,
    )
