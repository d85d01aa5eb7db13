"""1-D translation correlation gated by the other coordinate (projection aliasing).

The paper's 1-D histograms project every point onto one axis, so two different walls facing the
same way at different places along the other axis look alike: a wall segment at y = -70.0 m
beside one room and another at y = -69.8 m beside the next room (the synthetic building's rooms
are carved 0.1-0.2 m inside their outlines) correlate as strongly as the same wall seen twice.
Along a corridor the along-axis evidence is a few such faces (door jambs, pillars, cross walls),
so one aliased pair pulls the match 0.1-0.3 m and the local map then carries the error.

Here a current point votes only against reference points within `gate_m` of it in the other
coordinate (placed with the other axis' estimate): the correlation of the 2-D point sets along
one axis, within a thin band. With `sides`, a point pairs only with points seen from the same
side (the sensor on the same side of them along the axis): the two faces of a 0.1-0.2 m wall,
seen from either side through doors, are otherwise another 0.1-0.2 m alias. Same shifts, same
triangle kernel of half-width `bin_m` as `translation.correlate_axis`, so `pick_peak` treats both
alike.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from service.core.types import FloatArray, convolve_valid

_SIDE_OFFSET_M = 1.0e6  # far beyond any band: the two sides never pair
_BUCKET_M = 0.5  # bucket of the other coordinate (a band is 0.15-0.4 m each side)
_MARGIN_M = 1e-3  # the 2-D query reads a little more; the exact window filter follows


def _side_offset(sides: npt.NDArray[np.bool_]) -> FloatArray:
    return np.where(sides, _SIDE_OFFSET_M, 0.0)


def _clip(values: FloatArray, hi: float) -> FloatArray:
    """`np.clip(values, 0, hi)` in place, without its wrapper's overhead."""
    np.maximum(values, 0.0, out=values)
    return np.minimum(values, hi, out=values)


class SortedReference:
    """Reference points bucketed by the other coordinate, sorted along the axis within a bucket.

    A band query then reads, per bucket the band touches, only the points whose along-axis
    coordinate can fall inside the correlation window (a 2-D range query with two
    `searchsorted`), instead of every point in the band.
    """

    def __init__(
        self,
        points_map_m: FloatArray,
        weights: FloatArray,
        sides: npt.NDArray[np.bool_] | None,
        axis: int,
        min_weight: float,
    ) -> None:
        other = 1 - axis
        keep = np.flatnonzero(weights[:, axis] > min_weight)
        pts = points_map_m.take(keep, axis=0)
        key = pts[:, other]
        if sides is not None:
            key = key + _side_offset(sides.take(keep, axis=0)[:, axis])
        along = pts[:, axis]
        self.along_origin_m = float(along.min()) - 1.0 if along.size else 0.0
        # Bucket b's points sit in [b·span, (b + 1)·span) of the combined key.
        self.span_m = (float(along.max()) - self.along_origin_m + 1.0) * 2.0 if along.size else 1.0
        bucket = np.floor(key / _BUCKET_M)
        combined = bucket * self.span_m + (along - self.along_origin_m)
        # Distinct keys have one sorted order, so the fast (unstable, SIMD) sort gives the
        # stable sort's order unless two keys are equal (or NaN): then the stable sort (~3x
        # slower on these ever-changing keys) decides, as before.
        order = combined.argsort()
        sorted_keys = combined[order]
        if not (sorted_keys[1:] > sorted_keys[:-1]).all():
            order = combined.argsort(kind="stable")
            sorted_keys = combined[order]
        self.combined = np.ascontiguousarray(sorted_keys)
        self.other_m = np.ascontiguousarray(key[order])
        self.along_m = np.ascontiguousarray(along[order])
        self.weights = np.ascontiguousarray(weights.take(keep, axis=0)[order, axis])


def correlate_axis_gated(  # noqa: PLR0917 - mirrors correlate_axis plus the band
    ref: SortedReference,
    cur_along_m: FloatArray,
    cur_other_m: FloatArray,
    cur_weights: FloatArray,
    cur_sides: npt.NDArray[np.bool_] | None,
    centre_m: float,
    half_window_m: float,
    step_m: float,
    bin_m: float,
    gate_m: float | FloatArray,
    min_weight: float,
) -> tuple[FloatArray, FloatArray]:
    """E(shift) for shifts `centre + k·step` within ±half_window, pairs within the band only.

    `cur_along_m` are current points' coordinates on the matched axis before the shift,
    `cur_other_m` their other coordinate already in the map frame, `gate_m` the band's half
    width (one for all, or per point).
    """
    n_half = max(1, round(half_window_m / step_m))
    k = 2 * n_half + 1
    shifts = centre_m + step_m * np.arange(-n_half, n_half + 1, dtype=np.float64)
    energy = np.zeros(k, dtype=np.float64)
    # Array methods rather than np.* wrappers below: ~1 µs less per call on these few
    # thousand pairs (speed).
    sel = (cur_weights > min_weight).nonzero()[0]
    if sel.size == 0 or ref.other_m.size == 0:
        return shifts, energy
    co = cur_other_m.take(sel)
    gate = gate_m.take(sel) if isinstance(gate_m, np.ndarray) else np.full(sel.size, gate_m)
    if cur_sides is not None:
        co = co + _side_offset(cur_sides.take(sel))
    ca = cur_along_m.take(sel)
    cw = cur_weights.take(sel)
    half = max(1, round(bin_m / step_m))
    n_ext = k + 2 * half
    d_lo = float(shifts[0]) - half * step_m - _MARGIN_M
    d_hi = float(shifts[0]) + (n_ext - 1 - half) * step_m + _MARGIN_M
    b_lo = np.floor((co - gate) / _BUCKET_M)
    n_b = (np.floor((co + gate) / _BUCKET_M) - b_lo).astype(np.intp) + 1
    qi = np.arange(sel.size).repeat(n_b)
    qb = b_lo.repeat(n_b) + (np.arange(qi.size) - (n_b.cumsum() - n_b).repeat(n_b))
    base = qb * ref.span_m
    rel = ca.take(qi) - ref.along_origin_m
    lo = ref.combined.searchsorted(base + _clip(rel + d_lo, ref.span_m), side="left")
    hi = ref.combined.searchsorted(base + _clip(rel + d_hi, ref.span_m), side="right")
    cnt = hi - lo
    ends = cnt.cumsum()
    total = int(ends[-1])
    if total == 0:
        return shifts, energy
    ci = qi.repeat(cnt)
    rj = (lo - (ends - cnt)).repeat(cnt) + np.arange(total)
    pair = (np.abs(ref.other_m.take(rj) - co.take(ci)) <= gate.take(ci)).nonzero()[0]
    ci, rj = ci.take(pair), rj.take(pair)
    # The shift that puts current point i onto reference point j.
    pos = (ref.along_m.take(rj) - ca.take(ci) - float(shifts[0])) / step_m + half
    w = cw.take(ci) * ref.weights.take(rj)
    ok = (pos >= 0.0) & (pos < n_ext - 1)
    if not ok.all():  # the 2-D query's margin: rarely any
        pos, w = pos[ok], w[ok]
    if pos.size == 0:
        return shifts, energy
    # Linear split onto the step grid, then the triangle of the paper's bin.
    i0 = np.floor(pos).astype(np.intp)
    frac = pos - i0
    hist = np.bincount(i0, weights=w * (1.0 - frac), minlength=n_ext)[:n_ext]
    hist += np.bincount(i0 + 1, weights=w * frac, minlength=n_ext)[:n_ext]
    tri = 1.0 - np.abs(np.arange(-half, half + 1)) / (half + 1)
    energy = convolve_valid(hist.astype(np.float64, copy=False), tri)
    return shifts, energy
