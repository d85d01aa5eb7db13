"""The estimator's fast paths against straightforward reference implementations."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from service.core.frontend import refine
from service.core.frontend.gated import SortedReference, correlate_axis_gated
from service.core.frontend.heading import _median, heading_scores
from service.core.frontend.refine import OccupiedCells
from service.core.frontend.translation import axis_density, correlate_axis
from service.core.types import FloatArray


def _naive_scores(pts: FloatArray, angles: FloatArray, bin_m: float, soft: bool) -> FloatArray:
    out = np.empty(angles.shape[0])
    for k, a in enumerate(angles):
        c, s = math.cos(a), math.sin(a)
        total = 0.0
        for coord in (c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]):
            u = coord / bin_m
            lo = math.floor(float(u.min())) - 1
            i0 = np.floor(u - lo).astype(np.int64)
            if soft:
                f = (u - lo) - i0
                h = np.bincount(i0, 1.0 - f, i0.max() + 2) + np.bincount(i0 + 1, f, i0.max() + 2)
            else:
                h = np.bincount(i0).astype(np.float64)
            total += float((h * h).sum())
        out[k] = total
    return out


@pytest.mark.parametrize("soft", [False, True])
def test_heading_scores_match_naive_histograms(soft: bool) -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        pts = rng.normal(0.0, rng.uniform(0.5, 10.0), (int(rng.integers(5, 300)), 2))
        angles = rng.uniform(-0.8, 0.8, int(rng.integers(1, 40)))
        got = heading_scores(pts, angles, 0.05, "energy", soft=soft)
        np.testing.assert_allclose(got, _naive_scores(pts, angles, 0.05, soft), rtol=1e-9)


def test_correlate_axis_matches_per_shift_gather() -> None:
    rng = np.random.default_rng(6)
    for _ in range(30):
        ref = rng.uniform(-20.0, 20.0, int(rng.integers(10, 2000)))
        ref_w = np.asarray(rng.random(ref.shape[0]), dtype=np.float64)
        cur = rng.uniform(-21.0, 21.0, int(rng.integers(10, 500)))
        cur_w = np.asarray(rng.random(cur.shape[0]), dtype=np.float64)
        cur_w[rng.random(cur.shape[0]) < 0.3] = 0.0  # points that do not vote on this axis
        centre = float(rng.uniform(-1.0, 1.0))
        density = axis_density(ref, ref_w, 0.005, 0.03, 0.8)
        shifts, energy = correlate_axis(density, cur, cur_w, centre, 0.4)
        # The definition: reference density at 0.005 m, smoothed by the 0.03 m triangle over
        # the whole axis, read at every shifted current point (zero outside the reference).
        lo = math.floor((min(ref.min(), cur.min() + shifts[0]) - 1.0) / 0.005) * 0.005
        hi = max(ref.max(), cur.max() + shifts[-1]) + 1.0
        n_bins = math.ceil((hi - lo) / 0.005) + 2
        raw = np.bincount(np.floor((ref - lo) / 0.005).astype(np.int64), ref_w, n_bins)
        tri = 1.0 - np.abs(np.arange(-6, 7)) / 7.0
        dens = np.convolve(raw, tri, mode="same")
        base = np.floor((cur + shifts[0] - lo) / 0.005).astype(np.int64)
        want = np.array([cur_w @ dens[base + j] for j in range(shifts.shape[0])])
        np.testing.assert_allclose(energy, want, rtol=1e-9, atol=1e-9)


def test_axis_density_of_no_points_reads_zero() -> None:
    density = axis_density(np.empty(0), np.empty(0), 0.005, 0.03, 0.8)
    shifts, energy = correlate_axis(density, np.array([0.1, 5.0]), np.ones(2), 0.0, 0.4)
    assert shifts.shape == energy.shape == (161,)
    assert not energy.any()


def test_occupied_cells_bitmap_matches_sorted_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(7)
    cases = []
    for _ in range(30):
        pts = rng.normal(0.0, rng.uniform(0.5, 15.0), (int(rng.integers(1, 2000)), 2))
        query = np.concatenate((pts[:50] + rng.normal(0, 0.1, (min(50, len(pts)), 2)),
                                rng.normal(0.0, 20.0, (50, 2))))  # fmt: skip
        cands = rng.normal(0.0, 0.5, (int(rng.integers(1, 20)), 2))
        cases.append((pts, query, cands, OccupiedCells(pts).hit_fraction(query, cands)))
    monkeypatch.setattr(refine, "_MAX_BITMAP_CELLS", 0)  # force the sorted-keys form
    for pts, query, cands, fast in cases:
        np.testing.assert_array_equal(OccupiedCells(pts).hit_fraction(query, cands), fast)


def test_median_is_numpy_median() -> None:
    rng = np.random.default_rng(8)
    for n in (1, 2, 3, 89, 90, 91):
        v = rng.normal(size=n)
        assert _median(v) == float(np.median(v))


def _naive_gated(  # noqa: PLR0917 - the definition, input by input
    ref_pts: FloatArray,
    ref_w: FloatArray,
    ref_sides: npt.NDArray[np.bool_],
    cur_along: FloatArray,
    cur_other: FloatArray,
    cur_w: FloatArray,
    cur_sides: npt.NDArray[np.bool_],
    shifts: FloatArray,
    gate: FloatArray,
) -> FloatArray:
    """Every (current, reference) pair within the band and on the same side, by definition."""
    axis, step, half, min_w = 0, 0.005, 6, 0.05
    rk = ref_w[:, axis] > min_w
    ra, ro, rw, rs = ref_pts[rk, axis], ref_pts[rk, 1], ref_w[rk, axis], ref_sides[rk, axis]
    n_ext = shifts.shape[0] + 2 * half
    hist = np.zeros(n_ext + 1)
    for i in np.flatnonzero(cur_w > min_w):
        pair = (np.abs(ro - cur_other[i]) <= gate[i]) & (rs == cur_sides[i])
        pos = (ra[pair] - cur_along[i] - shifts[0]) / step + half
        w = cur_w[i] * rw[pair]
        ok = (pos >= 0.0) & (pos < n_ext - 1)
        i0 = np.floor(pos[ok]).astype(np.int64)
        np.add.at(hist, i0, w[ok] * (1.0 - (pos[ok] - i0)))
        np.add.at(hist, i0 + 1, w[ok] * (pos[ok] - i0))
    tri = 1.0 - np.abs(np.arange(-half, half + 1)) / (half + 1)
    return np.convolve(hist[:n_ext], tri, mode="valid")


def test_gated_correlation_matches_all_pairs_in_the_band() -> None:
    rng = np.random.default_rng(9)
    for _ in range(20):
        n_ref, n_cur = int(rng.integers(10, 1500)), int(rng.integers(5, 300))
        ref_pts = rng.uniform(-15.0, 15.0, (n_ref, 2))
        ref_w = rng.random((n_ref, 2))
        ref_sides = rng.random((n_ref, 2)) < 0.5
        cur = rng.uniform(-15.0, 15.0, (n_cur, 2))
        cur_w = rng.random(n_cur)
        cur_sides = rng.random(n_cur) < 0.5
        gate = rng.uniform(0.15, 0.45, n_cur)
        centre = float(rng.uniform(-0.5, 0.5))
        sorted_ref = SortedReference(ref_pts, ref_w, ref_sides, 0, 0.05)
        shifts, energy = correlate_axis_gated(
            sorted_ref, cur[:, 0], cur[:, 1], cur_w, cur_sides, centre, 0.4, 0.005, 0.03, gate, 0.05
        )
        want = _naive_gated(
            ref_pts, ref_w, ref_sides, cur[:, 0], cur[:, 1], cur_w, cur_sides, shifts, gate
        )
        np.testing.assert_allclose(energy, want, rtol=1e-9, atol=1e-9)
