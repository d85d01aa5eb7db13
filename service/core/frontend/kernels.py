"""The matcher's inner loops, compiled (numba).

The search's and the submaps' kernels do the same floating-point operations, in the same order,
as the numpy code they replace, so the same bits: what numpy computes with its own vectorised
transcendental functions (log, exp), with BLAS, or in sums whose order numpy chooses (pairwise)
stays in numpy with the callers; but the small search's means (`dense_search`) are summed here,
in numpy's pairwise order addition for addition (`_pairwise_plan`). No fastmath: LLVM then
neither reorders nor fuses (a·b + c stays two roundings).

The refinement (`gauss_newton`) is the exception: the whole Gauss-Newton loop runs here, the
scan's sums in one pass over its points, because the evaluations a scan costs were
mostly numpy's per-call overhead. Its sums are sequential and its log is libm's, so its poses
differ from a numpy refinement's in the last bits (measured: 1e-14 m over 2,000 ACES scans).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from service.core.types import FloatArray

F32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]

_jit = numba.njit(cache=True, nogil=True)


@_jit
def _bicubic(  # noqa: PLR0917 - numba takes no keyword-only arguments
    values: F32Array,
    origin_x: float,
    origin_y: float,
    res: float,
    qx: float,
    qy: float,
    wu: FloatArray,
    dwu: FloatArray,
    wv: FloatArray,
    dwv: FloatArray,
) -> tuple[float, float, float]:
    """`LikelihoodGrid.interpolate` at the map point (qx, qy): the field's bicubic value
    (clipped to [0, 1]) and gradient (per metre); 0 and no gradient off the grid (or not a
    number). wu … dwv: scratch, 4 each."""
    h, w = values.shape
    u = (qx - origin_x) / res - 0.5
    v = (qy - origin_y) / res - 0.5
    fv = math.floor(v)
    fu = math.floor(u)
    if not (fv >= 1.0 and fu >= 1.0 and fv < h - 2 and fu < w - 2):
        return 0.0, 0.0, 0.0
    i0 = int(fv)
    j0 = int(fu)
    _catmull_rom(v - i0, wv, dwv)
    _catmull_rom(u - j0, wu, dwu)
    val = 0.0
    d_du = 0.0
    d_dv = 0.0
    for a in range(4):
        row = 0.0
        drow = 0.0
        for b in range(4):
            f = np.float64(values[i0 - 1 + a, j0 - 1 + b])
            row += wu[b] * f
            drow += dwu[b] * f
        val += wv[a] * row
        d_dv += dwv[a] * row
        d_du += wv[a] * drow
    return min(max(val, 0.0), 1.0), d_du / res, d_dv / res


@_jit
def _catmull_rom(t: float, weights: FloatArray, slopes: FloatArray) -> None:
    """`likelihood._catmull_rom` at one fraction, written into `weights` and `slopes`."""
    t2 = t * t
    t3 = t * t * t
    weights[0] = 0.5 * (-t3 + 2.0 * t2 - t)
    weights[1] = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0)
    weights[2] = 0.5 * (-3.0 * t3 + 4.0 * t2 + t)
    weights[3] = 0.5 * (t3 - t2)
    slopes[0] = 0.5 * (-3.0 * t2 + 4.0 * t - 1.0)
    slopes[1] = 0.5 * (9.0 * t2 - 10.0 * t)
    slopes[2] = 0.5 * (-9.0 * t2 + 8.0 * t + 1.0)
    slopes[3] = 0.5 * (3.0 * t2 - 2.0 * t)


@_jit
def _rows(  # noqa: PLR0917 - numba takes no keyword-only arguments
    value: float,
    grad_x: float,
    grad_y: float,
    r_sq: float,
    px: float,
    py: float,
    c: float,
    s: float,
    max_residual_sigmas: float,
) -> tuple[float, float, float, float, float, float]:
    """One point's ∂(r²/2)/∂(x, y, θ) and Gauss-Newton row ∂r/∂(x, y, θ): ∂(r²/2)/∂q = -∇M / M,
    exact; ∂r/∂q = -∇M / (M r) with r held off 0, where interpolation leaves ∇M and r not quite
    vanishing together. A point past the cap, or off the field, pulls nowhere."""
    r = math.sqrt(r_sq)
    inlier = r < max_residual_sigmas and value > 0.0
    inv_m = 1.0 / max(value, 1e-9) if inlier else 0.0
    hx = -grad_x * inv_m
    hy = -grad_y * inv_m
    r_held = max(r, 0.1)
    jx = hx / r_held
    jy = hy / r_held
    dqx_dt = -s * px - c * py
    dqy_dt = c * px - s * py
    return hx, hy, hx * dqx_dt + hy * dqy_dt, jx, jy, jx * dqx_dt + jy * dqy_dt


@_jit
def scan_terms(  # noqa: PLR0917 - numba takes no keyword-only arguments
    values: F32Array,
    origin_x: float,
    origin_y: float,
    res: float,
    pts: FloatArray,
    c: float,
    s: float,
    tx: float,
    ty: float,
    max_residual_sigmas: float,
) -> tuple[float, float, FloatArray, FloatArray]:
    """The scan's sums at the pose (rotation (c, s), translation (tx, ty)), in one pass over
    its points: Σ r² (r² = -2 ln M capped at max_residual_sigmas², as `residual_sq`), Σ M,
    Σ ∂(r²/2)/∂pose (3,) and Σ JᵀJ (3, 3) of the Gauss-Newton rows (`_rows`)."""
    floor = math.exp(-0.5 * max_residual_sigmas * max_residual_sigmas)
    wu = np.empty(4)
    dwu = np.empty(4)
    wv = np.empty(4)
    dwv = np.empty(4)
    sum_r_sq = 0.0
    sum_value = 0.0
    g = np.zeros(3)
    jtj = np.zeros((3, 3))
    for k in range(pts.shape[0]):
        px = pts[k, 0]
        py = pts[k, 1]
        value, gx, gy = _bicubic(
            values, origin_x, origin_y, res, (c * px - s * py) + tx, (s * px + c * py) + ty,
            wu, dwu, wv, dwv,
        )  # fmt: skip
        r_sq = -2.0 * math.log(min(max(value, floor), 1.0))
        hx, hy, ht, jx, jy, jt = _rows(value, gx, gy, r_sq, px, py, c, s, max_residual_sigmas)
        sum_r_sq += r_sq
        sum_value += value
        g[0] += hx
        g[1] += hy
        g[2] += ht
        jtj[0, 0] += jx * jx
        jtj[0, 1] += jx * jy
        jtj[0, 2] += jx * jt
        jtj[1, 1] += jy * jy
        jtj[1, 2] += jy * jt
        jtj[2, 2] += jt * jt
    jtj[1, 0] = jtj[0, 1]
    jtj[2, 0] = jtj[0, 2]
    jtj[2, 1] = jtj[1, 2]
    return sum_r_sq, sum_value, g, jtj


@_jit
def _wrap(theta_rad: float) -> float:
    """`types.wrap_angle`: to [-π, π)."""
    return (theta_rad + math.pi) % (2.0 * math.pi) - math.pi


@_jit
def _objective(  # noqa: PLR0917 - numba takes no keyword-only arguments
    values: F32Array,
    origin_x: float,
    origin_y: float,
    res: float,
    pts: FloatArray,
    pose: FloatArray,
    predicted: FloatArray,
    info_pred: FloatArray,
    wall_heading_rad: float,
    wall_sigma_rad: float,
    wall_huber: float,
    scan_weight: float,
    max_residual_sigmas: float,
) -> tuple[float, FloatArray, FloatArray, FloatArray, float]:
    """`matcher.refine`'s objective at `pose` (x, y, θ): (cost, gradient, Gauss-Newton Hessian,
    its scan part, mean field value). The scan's r² (halved, over `scan_weight` / N), the
    motion prior's Mahalanobis term and, where `wall_sigma_rad` is finite, the walls' Huber
    term on θ."""
    n = pts.shape[0]
    sum_r_sq, sum_value, g_scan, jtj = scan_terms(
        values, origin_x, origin_y, res, pts, math.cos(pose[2]), math.sin(pose[2]),
        pose[0], pose[1], max_residual_sigmas,
    )  # fmt: skip
    scale = scan_weight / max(n, 1)
    d = np.array([pose[0] - predicted[0], pose[1] - predicted[1], _wrap(pose[2] - predicted[2])])
    info_d = np.empty(3)
    for i in range(3):
        info_d[i] = info_pred[i, 0] * d[0] + info_pred[i, 1] * d[1] + info_pred[i, 2] * d[2]
    cost = scale * sum_r_sq + (d[0] * info_d[0] + d[1] * info_d[1] + d[2] * info_d[2])
    h_scan = scale * jtj
    g = scale * g_scan + info_d
    h = h_scan + info_pred
    if math.isfinite(wall_sigma_rad) and math.isfinite(wall_heading_rad):
        z = _wrap(pose[2] - wall_heading_rad) / wall_sigma_rad
        a = abs(z)
        cost += _huber_cost(z, wall_huber)
        wz = 1.0 if a <= wall_huber else wall_huber / a
        g[2] += wz * z / wall_sigma_rad
        h[2, 2] += wz / (wall_sigma_rad * wall_sigma_rad)
    return cost, g, h, h_scan, sum_value / n if n else 0.0


@_jit
def _solve3(a: FloatArray, b: FloatArray) -> FloatArray:
    """a⁻¹ b for a symmetric 3 × 3 `a`, by its adjugate."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    c11 = a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]
    c12 = a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]
    c22 = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    return np.array(
        [
            (c00 * b[0] + c01 * b[1] + c02 * b[2]) / det,
            (c01 * b[0] + c11 * b[1] + c12 * b[2]) / det,
            (c02 * b[0] + c12 * b[1] + c22 * b[2]) / det,
        ]
    )


@_jit
def gauss_newton(  # noqa: PLR0917 - numba takes no keyword-only arguments
    values: F32Array,
    origin_x: float,
    origin_y: float,
    res: float,
    pts: FloatArray,
    start: FloatArray,
    predicted: FloatArray,
    info_pred: FloatArray,
    wall_heading_rad: float,
    wall_sigma_rad: float,
    wall_huber: float,
    scan_weight: float,
    max_residual_sigmas: float,
    iterations: int,
    halvings: int,
    tolerance_m: float,
) -> tuple[FloatArray, FloatArray, FloatArray, float, float]:
    """`matcher.refine`'s Gauss-Newton on `_objective` from `start`: (pose, Hessian, its scan
    part, mean field value, cost). A step that raises the cost is halved, at most `halvings`
    times; the refinement stops at `iterations`, at a step it cannot make pay, or when the next
    step would move no point by more than `tolerance_m` (converged: near the optimum the
    bicubic field's rounding decides whether a step that small pays, and trying it and its
    halvings cost more evaluations than the rest of the refinement)."""
    pose = start.copy()
    cost, g, h, h_scan, score = _objective(
        values, origin_x, origin_y, res, pts, pose, predicted, info_pred, wall_heading_rad,
        wall_sigma_rad, wall_huber, scan_weight, max_residual_sigmas,
    )  # fmt: skip
    reach_m = 0.0
    for k in range(pts.shape[0]):
        reach_m = max(reach_m, math.hypot(pts[k, 0], pts[k, 1]))
    damped = np.eye(3) * 1e-9
    for _ in range(iterations):
        step = -_solve3(h + damped, g)
        if abs(step[0]) + abs(step[1]) + reach_m * abs(step[2]) <= tolerance_m:
            break
        accepted = False
        for _half in range(halvings):
            cand = np.array([pose[0] + step[0], pose[1] + step[1], _wrap(pose[2] + step[2])])
            c2, g2, h2, hs2, s2 = _objective(
                values, origin_x, origin_y, res, pts, cand, predicted, info_pred,
                wall_heading_rad, wall_sigma_rad, wall_huber, scan_weight, max_residual_sigmas,
            )  # fmt: skip
            if c2 <= cost:
                pose, cost, g, h, h_scan, score = cand, c2, g2, h2, hs2, s2
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break
    return pose, h, h_scan, score, cost


@_jit
def _clamp(i: int, lo: int, hi: int) -> int:
    return min(max(i, lo), hi)


@_jit
def prior_cost(info: FloatArray, dx: Any, dy: Any, dt: Any) -> Any:
    """The motion prior's Mahalanobis term at offsets (dx, dy, dt) from the prediction (scalars,
    or arrays elementwise): its six terms added left to right, the order every search's cost
    and the brute force share (so their bits agree)."""
    return (
        info[0, 0] * dx * dx
        + info[1, 1] * dy * dy
        + info[2, 2] * dt * dt
        + 2.0 * info[0, 1] * dx * dy
        + 2.0 * info[0, 2] * dx * dt
        + 2.0 * info[1, 2] * dy * dt
    )


@_jit
def _rotated_cells(  # noqa: PLR0917 - numba takes no keyword-only arguments
    px: FloatArray,
    py: FloatArray,
    c: float,
    s: float,
    tx: float,
    ty: float,
    origin_x: float,
    origin_y: float,
    res: float,
    rows: IntArray,
    cols: IntArray,
) -> None:
    """The cells (row, column) of the points rotated by (c, s) and moved to (tx, ty), into
    `rows` and `cols`: one rounding for the tree's lookups and the small lattice's alike."""
    for i in range(px.shape[0]):
        mx = c * px[i] - s * py[i] + tx
        my = s * px[i] + c * py[i] + ty
        rows[i] = int(np.rint((my - origin_y) / res - 0.5))
        cols[i] = int(np.rint((mx - origin_x) / res - 0.5))


@_jit
def lattice_gather(  # noqa: PLR0917 - numba takes no keyword-only arguments
    flat: F32Array,
    row0: int,
    col0: int,
    height: int,
    width: int,
    px: FloatArray,
    py: FloatArray,
    cos_t: FloatArray,
    sin_t: FloatArray,
    k: IntArray,
    di: IntArray,
    dj: IntArray,
    tx: float,
    ty: float,
    origin_x: float,
    origin_y: float,
    res: float,
    cells: IntArray,
    celled: npt.NDArray[np.bool_],
) -> F32Array:
    """`search._Problem.exact`'s lookups: for each pose m (rotation k[m] of the lattice's
    (cos_t, sin_t), cell offset (di, dj)[m] from (tx, ty)) the cost (a pyramid's level 0) under
    every point, (M, N). The mean is left to numpy (its summation order is the brute force's).

    A rotation's cells at (tx, ty) do not depend on the offset: they are computed once per
    search, into `cells` (R, 2, N) where `celled` (R,) is False, and kept there."""
    m_n = k.shape[0]
    n = px.shape[0]
    out = np.empty((m_n, n), dtype=np.float32)
    for m in range(m_n):
        kk = k[m]
        if not celled[kk]:
            _rotated_cells(
                px, py, cos_t[kk], sin_t[kk], tx, ty, origin_x, origin_y, res,
                cells[kk, 0], cells[kk, 1],
            )  # fmt: skip
            celled[kk] = True
        dr = di[m] - row0
        dc = dj[m] - col0
        for i in range(n):
            r = _clamp(cells[kk, 0, i] + dr, 0, height - 1)
            cc = _clamp(cells[kk, 1, i] + dc, 0, width - 1)
            out[m, i] = flat[r * width + cc]
    return out


@_jit
def _block_sum(values: FloatArray, lo: int, n: int) -> float:
    """numpy's `pairwise_sum` (numpy/_core/src/umath/loops_utils.h.src) of values[lo : lo + n]
    for n ≤ 128, where it does not split: under 8 values, in order from 0.0; else eight
    interleaved accumulators combined as a tree, then the rest in order."""
    if n < 8:
        res: float = 0.0
        for i in range(lo, lo + n):
            res += values[i]
        return res
    r0, r1, r2, r3 = values[lo], values[lo + 1], values[lo + 2], values[lo + 3]
    r4, r5, r6, r7 = values[lo + 4], values[lo + 5], values[lo + 6], values[lo + 7]
    whole = lo + n - n % 8
    for i in range(lo + 8, whole, 8):
        r0 += values[i]
        r1 += values[i + 1]
        r2 += values[i + 2]
        r3 += values[i + 3]
        r4 += values[i + 4]
        r5 += values[i + 5]
        r6 += values[i + 6]
        r7 += values[i + 7]
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for i in range(whole, lo + n):
        res += values[i]
    return res


# numpy's default buffer (`np.getbufsize()`): a reduction with a cast (float32 summed as float64)
# runs its inner loop, so its pairwise summation, over at most this many elements at a time.
_NUMPY_BUFSIZE = 8192


@_jit
def _pairwise_plan(n: int) -> tuple[IntArray, IntArray, IntArray]:
    """numpy's sum of n float32 values as float64 (`np.add.reduce(..., dtype=float64)` along a
    contiguous axis, so `mean`'s sum), as a program: from 0.0 (add's identity), each buffer of
    `_NUMPY_BUFSIZE` values in turn added to it, a buffer summed pairwise: above 128 values its
    two halves (the first a multiple of 8) summed apart and added, down to blocks of at most
    128 (`_block_sum`). Returns (ops, block starts, block lengths), ops in postfix order: op
    ≥ 0 sums block op, -1 adds the last two sums, -2 adds the last sum to the total. (A loop,
    not recursion: numba's cache does not load recursive functions safely.)"""
    ops = np.empty(3 * n + 3, dtype=np.int64)
    starts = np.empty(n + 1, dtype=np.int64)
    lengths = np.empty(n + 1, dtype=np.int64)
    stack = np.empty((64, 3), dtype=np.int64)  # (start, length, halves done): n halves per level
    n_ops, n_blocks = 0, 0
    for buf in range(0, max(n, 1), _NUMPY_BUFSIZE):
        stack[0, 0], stack[0, 1], stack[0, 2] = buf, min(_NUMPY_BUFSIZE, n - buf), 0
        top = 1
        while top:
            lo, m, done = stack[top - 1, 0], stack[top - 1, 1], stack[top - 1, 2]
            if m <= 128:
                starts[n_blocks], lengths[n_blocks] = lo, m
                ops[n_ops] = n_blocks
                n_blocks += 1
                n_ops += 1
                top -= 1
                continue
            if done == 2:
                ops[n_ops] = -1
                n_ops += 1
                top -= 1
                continue
            half = m // 2
            half -= half % 8
            stack[top - 1, 2] = done + 1
            stack[top, 0] = lo if done == 0 else lo + half
            stack[top, 1] = half if done == 0 else m - half
            stack[top, 2] = 0
            top += 1
        ops[n_ops] = -2
        n_ops += 1
    return ops[:n_ops], starts[:n_blocks], lengths[:n_blocks]


@_jit
def _pairwise_sum(
    values: FloatArray, ops: IntArray, starts: IntArray, lengths: IntArray, sums: FloatArray
) -> float:
    """numpy's float64 sum of `values` (float32 values, as float64), by `_pairwise_plan`'s
    program: the same additions in the same order, the same bits. `sums`: scratch, 64."""
    total = 0.0
    top = 0
    for o in range(ops.shape[0]):
        op = ops[o]
        if op >= 0:
            sums[top] = _block_sum(values, starts[op], lengths[op])
            top += 1
        elif op == -1:
            top -= 1
            sums[top - 1] = sums[top - 1] + sums[top]
        else:
            top -= 1
            total = total + sums[top]
    return total


@_jit
def dense_search(  # noqa: PLR0917 - numba takes no keyword-only arguments
    costs: F32Array,
    px: FloatArray,
    py: FloatArray,
    cos_t: FloatArray,
    sin_t: FloatArray,
    half_rows: int,
    half_cols: int,
    tx: float,
    ty: float,
    origin_x: float,
    origin_y: float,
    res: float,
    scan_weight: float,
    info: FloatArray,
    dt_k: FloatArray,
    wall_cost_k: FloatArray,
) -> tuple[int, int, int, int]:
    """`search.lattice_search` on a small lattice: every pose scored, the lowest cost's
    (rotation index k, row a, column b, poses scored), with the row offset a - half_rows and
    the column offset b - half_cols. Ties go to the lowest k, then a, then b (the brute force's
    order: its first minimum). Rotation k is (cos_t, sin_t)[k], at dt_k[k] from the prediction
    (tx, ty); `wall_cost_k` is the walls' cost per rotation, empty without their prior.

    A pose's cost is `search._Problem.exact`'s, operation for operation: the cost table's
    value under each point (its cell clamped onto the table, whose border costs the cap, as
    everything off it does), as float64; their pairwise sum (`_pairwise_sum`: numpy's `mean`
    along the points, bit for bit) over N; times the scan's weight; plus the motion prior's
    six terms added left to right; plus the walls' cost. No fastmath: the same bits.

    Per rotation the points' cells (`lattice_gather`'s) and their clamped columns at every
    column offset are computed once, per row offset their clamped rows; the table is read
    flat, at unsigned indices (no negative-index test in the inner loop)."""
    h, w = costs.shape
    n = px.shape[0]
    n_rot = cos_t.shape[0]
    n_rows, n_cols = 2 * half_rows + 1, 2 * half_cols + 1
    has_wall = wall_cost_k.shape[0] > 0
    rows0 = np.empty(n, dtype=np.int64)
    cols0 = np.empty(n, dtype=np.int64)
    flat = costs.ravel()
    rows = np.empty(n, dtype=np.uint64)  # clamped, at one row offset
    cols = np.empty((n_cols, n), dtype=np.uint64)  # clamped, at every column offset
    looked_up = np.empty(n)
    ops, starts, lengths = _pairwise_plan(n)
    sums = np.empty(64)
    best = math.inf
    best_k, best_a, best_b = n_rot, n_rows, n_cols
    for k in range(n_rot):
        _rotated_cells(px, py, cos_t[k], sin_t[k], tx, ty, origin_x, origin_y, res, rows0, cols0)
        for b in range(n_cols):
            for i in range(n):
                cols[b, i] = np.uint64(_clamp(cols0[i] + (b - half_cols), 0, w - 1))
        dt = dt_k[k]
        for a in range(n_rows):
            di = a - half_rows
            for i in range(n):
                rows[i] = np.uint64(_clamp(rows0[i] + di, 0, h - 1) * w)
            dy = di * res
            for b in range(n_cols):
                col = cols[b]
                for i in range(n):
                    looked_up[i] = flat[rows[i] + col[i]]
                total_cost = _pairwise_sum(looked_up, ops, starts, lengths, sums)
                scan = scan_weight * (total_cost / n)
                dx = (b - half_cols) * res
                total = scan + prior_cost(info, dx, dy, dt)
                if has_wall:
                    total = total + wall_cost_k[k]
                # The brute force's first minimum (and the first pose when every cost is +inf).
                if total < best or (total == best and best_k == n_rot):
                    best, best_k, best_a, best_b = total, k, a, b
    return best_k, best_a, best_b, n_rot * n_rows * n_cols


@_jit
def axis_lookup(  # noqa: PLR0917 - numba takes no keyword-only arguments
    costs: F32Array,
    origin_x: float,
    origin_y: float,
    res: float,
    pts: FloatArray,
    c: float,
    s: float,
    tx: float,
    ty: float,
    ux: float,
    uy: float,
    offsets_m: FloatArray,
    off_surface: float,
) -> F32Array:
    """`matcher.weakest_axis_from_response`'s lookups: the cost under every point of the scan
    at rotation (c, s), translation (tx, ty) + offset · (ux, uy), for each offset, (S, N);
    `off_surface` off the table. The mean is left to numpy."""
    rows_n, cols_n = costs.shape
    n = pts.shape[0]
    out = np.empty((offsets_m.shape[0], n), dtype=np.float32)
    for i in range(n):
        qx = c * pts[i, 0] - s * pts[i, 1] + tx
        qy = s * pts[i, 0] + c * pts[i, 1] + ty
        for m in range(offsets_m.shape[0]):
            col = math.floor((qx + offsets_m[m] * ux - origin_x) / res)
            row = math.floor((qy + offsets_m[m] * uy - origin_y) / res)
            if row >= 0 and row < rows_n and col >= 0 and col < cols_n:
                out[m, i] = costs[int(row), int(col)]
            else:
                out[m, i] = off_surface
    return out


@_jit
def _square_bound(lo: float, hi: float) -> float:
    """min of t² over [lo, hi]."""
    if lo <= 0.0 <= hi:
        return 0.0
    return min(lo * lo, hi * hi)


@_jit
def _product_bound(coef: float, p_lo: float, p_hi: float, q_lo: float, q_hi: float) -> float:
    """min of coef·p·q over the box: at a corner."""
    return min(coef * p_lo * q_lo, coef * p_lo * q_hi, coef * p_hi * q_lo, coef * p_hi * q_hi)


@_jit
def _huber_cost(z: float, huber: float) -> float:
    a = abs(z)
    return z * z if a <= huber else 2.0 * huber * a - huber * huber


@_jit
def block_bounds(  # noqa: PLR0917 - numba takes no keyword-only arguments
    flat: F32Array,
    pyramid_shape: IntArray,
    pts: FloatArray,
    range_m: FloatArray,
    thetas: FloatArray,
    dt_k: FloatArray,
    wall_z_k: FloatArray,
    k0: IntArray,
    k1: IntArray,
    row_off: IntArray,
    col_off: IntArray,
    rows_n: IntArray,
    cols_n: IntArray,
    frame: FloatArray,
    info: FloatArray,
) -> FloatArray:
    """`search._Problem.bound`: per block (rotations k0..k1, cell offsets from (row_off,
    col_off), rows_n × cols_n of them) a lower bound of every pose's cost in it:
    - scan: per point, where it can be over the block's rotations (within |p|·δ of the middle
      rotation's place, plus slack for the brute force's own rounding) widened by the block's
      translations; the pyramid's minimum over a square that holds that; their mean, weighed;
    - motion prior: the quadratic's terms bounded one by one over the block's (dx, dy, dθ) box;
    - walls: Huber at the block's angle nearest the walls' heading (`wall_z_k`: per rotation,
      its offset from that heading in σ; empty without the prior).
    `pyramid_shape` = (row0, col0, height, width, max_level); `frame` = (predicted x, y, grid
    origin x, y, resolution, scan weight, Huber). Bounds, so the order of their sums is free
    (the search's slack covers it)."""
    row0, col0, height, width, max_level = (
        pyramid_shape[0],
        pyramid_shape[1],
        pyramid_shape[2],
        pyramid_shape[3],
        pyramid_shape[4],
    )
    tx, ty, origin_x, origin_y, res, weight, huber = (
        frame[0],
        frame[1],
        frame[2],
        frame[3],
        frame[4],
        frame[5],
        frame[6],
    )
    m_n = k0.shape[0]
    n = pts.shape[0]
    out = np.empty(m_n)
    global_min = flat[flat.shape[0] - 1]
    for m in range(m_n):
        t0, t1 = thetas[k0[m]], thetas[k1[m]]
        mid = 0.5 * (t0 + t1)
        c = math.cos(mid)
        s = math.sin(mid)
        h = 0.5 * (t1 - t0) / res
        total = 0.0
        for i in range(n):
            px, py = pts[i, 0], pts[i, 1]
            u = (c * px - s * py + tx - origin_x) / res - 0.5
            v = (s * px + c * py + ty - origin_y) / res - 0.5
            reach = range_m[i] * h + 1e-6
            lo_c = int(np.rint(u - reach))
            lo_r = int(np.rint(v - reach))
            span_c = int(np.rint(u + reach)) - lo_c + cols_n[m]
            span_r = int(np.rint(v + reach)) - lo_r + rows_n[m]
            side = max(span_r, span_c)
            level = 0
            while (1 << level) < side:  # the smallest square that holds it
                level += 1
            if level > max_level:
                total += global_min
                continue
            r = min(max(lo_r + row_off[m] - row0, 0), height - 1)
            cc = min(max(lo_c + col_off[m] - col0, 0), width - 1)
            total += flat[(level * height + r) * width + cc]
        scan = weight * (total / max(n, 1))
        x_lo, x_hi = col_off[m] * res, (col_off[m] + cols_n[m] - 1) * res
        y_lo, y_hi = row_off[m] * res, (row_off[m] + rows_n[m] - 1) * res
        d_lo, d_hi = dt_k[k0[m]], dt_k[k1[m]]
        prior = (
            info[0, 0] * _square_bound(x_lo, x_hi)
            + info[1, 1] * _square_bound(y_lo, y_hi)
            + info[2, 2] * _square_bound(d_lo, d_hi)
            + _product_bound(2.0 * info[0, 1], x_lo, x_hi, y_lo, y_hi)
            + _product_bound(2.0 * info[0, 2], x_lo, x_hi, d_lo, d_hi)
            + _product_bound(2.0 * info[1, 2], y_lo, y_hi, d_lo, d_hi)
        )
        wall = 0.0
        if wall_z_k.shape[0]:
            z0, z1 = wall_z_k[k0[m]], wall_z_k[k1[m]]
            nearest = 0.0 if z0 * z1 <= 0.0 else min(abs(z0), abs(z1))
            wall = _huber_cost(nearest, huber)
        out[m] = scan + max(prior, 0.0) + wall  # the prior's Λ is positive semi-definite
    return out


@_jit
def pyramid_update(  # noqa: PLR0917 - numba takes no keyword-only arguments
    levels: F32Array, cap: float, r0: int, r1: int, c0: int, c1: int
) -> None:
    """Levels 1.. of a min-pyramid (`search.build_pyramid`: level m + 1 at (r, c) = min of level
    m at (r, c), (r + s, c), (r, c + s), (r + s, c + s), s = 2^m, past the crop's end the cap)
    over the anchors whose window meets level 0's rows r0:r1, columns c0:c1, after those
    changed. A minimum is exact in any order: the same values as building it whole."""
    n_lv, h, w = levels.shape
    capf = np.float32(cap)
    for m in range(n_lv - 1):
        s = 1 << m
        a0 = max(0, r0 - (2 * s - 1))
        b0 = max(0, c0 - (2 * s - 1))
        cb = min(w, c1)
        c_in = max(b0, min(cb, w - s))  # columns b0:c_in have their right neighbour on the crop
        n_in = c_in - b0
        # The tests per row and per column hoisted out of the inner loop, and its rows sliced
        # to start at 0 (no negative-index wrapping to test): it compiles to vector minima.
        for r in range(a0, min(h, r1)):
            here, out = levels[m, r, b0:], levels[m + 1, r, b0:]
            right = levels[m, r, b0 + s :]
            if r + s < h:
                below, below_right = levels[m, r + s, b0:], levels[m, r + s, b0 + s :]
                for c in range(n_in):
                    out[c] = min(here[c], below[c], below_right[c], right[c])
                for c in range(n_in, cb - b0):
                    out[c] = min(here[c], below[c], capf)
            else:
                for c in range(n_in):
                    out[c] = min(here[c], capf, right[c])
                for c in range(n_in, cb - b0):
                    out[c] = min(here[c], capf)


@_jit
def stamp_arguments(  # noqa: PLR0917 - numba takes no keyword-only arguments
    v: FloatArray,
    u: FloatArray,
    ci: IntArray,
    cj: IntArray,
    di: IntArray,
    dj: IntArray,
    res_sq: float,
    sigma_sq: float,
) -> FloatArray:
    """`LikelihoodGrid.insert`'s exponents -d²/2σ² of every hit at every cell of its stamp,
    (N·K,), hit-major (the exp is left to numpy: its own vectorised exp)."""
    n, k_n = v.shape[0], di.shape[0]
    out = np.empty(n * k_n)
    for p in range(n):
        for k in range(k_n):
            dv = np.float64(ci[p] + di[k]) - v[p]
            du = np.float64(cj[p] + dj[k]) - u[p]
            out[p * k_n + k] = -0.5 * ((dv * dv + du * du) * res_sq) / sigma_sq
    return out


@_jit
def stamp_cells(  # noqa: PLR0917 - numba takes no keyword-only arguments
    ci: IntArray, cj: IntArray, di: IntArray, dj: IntArray, width: int, values: FloatArray
) -> tuple[FloatArray, IntArray, IntArray]:
    """The stamps' `values` (hit-major, as `stamp_arguments`) grouped by cell: (sorted, cells,
    starts) with `sorted` = values[order], `order` the stable argsort of the flat cell
    indices, `cells` the distinct ones ascending, `starts` where each begins in `sorted`. A
    counting sort over the stamps' box: the same permutation as numpy's stable sort, in
    linear time, and the gather done in it (numpy's `values[order]` cost as much again)."""
    n, k_n = ci.shape[0], di.shape[0]
    i_lo, i_hi = ci.min() + di.min(), ci.max() + di.max()
    j_lo, j_hi = cj.min() + dj.min(), cj.max() + dj.max()
    bw = j_hi - j_lo + 1
    # Unsigned keys and counts: an unsigned index is never wrapped as a negative one, so the
    # loops carry no such test (half the time); a box holds far fewer than 2^32 cells.
    counts = np.zeros((i_hi - i_lo + 1) * bw, dtype=np.uint32)
    keys = np.empty(n * k_n, dtype=np.uint32)
    offsets = np.empty(k_n, dtype=np.int64)  # of the stamp's cells from its centre, in the box
    for k in range(k_n):
        offsets[k] = di[k] * bw + dj[k]
    for p in range(n):
        base = (ci[p] - i_lo) * bw + (cj[p] - j_lo)
        for k in range(k_n):
            keys[p * k_n + k] = np.uint32(base + offsets[k])
    for idx in range(n * k_n):
        counts[keys[idx]] += np.uint32(1)
    # One pass: each cell's start (an exclusive prefix sum, left in `counts`) and the cells.
    cells = np.empty(n * k_n, dtype=np.int64)
    starts = np.empty(n * k_n, dtype=np.int64)
    d = 0
    total = np.uint32(0)
    for bi in range(i_hi - i_lo + 1):
        row = (bi + i_lo) * width + j_lo
        row_counts = counts[bi * bw : (bi + 1) * bw]
        for bj in range(bw):
            c = row_counts[bj]
            if c > 0:
                cells[d] = row + bj
                starts[d] = total
                d += 1
            row_counts[bj] = total
            total += c
    out = np.empty(n * k_n)
    for idx in range(n * k_n):
        key = keys[idx]
        out[counts[key]] = values[idx]
        counts[key] += np.uint32(1)
    return out, cells[:d], starts[:d]


@_jit
def stamp_add(  # noqa: PLR0917 - numba takes no keyword-only arguments
    density: F32Array,
    hits: F32Array,
    stamped: npt.NDArray[np.int32],
    cells: IntArray,
    added: FloatArray,
    this_insert: int,
    carved: bool,
) -> None:
    """`LikelihoodGrid.insert`'s scatter of the stamps' sums (`added`, per distinct cell of
    `cells`, flat) into the density, as float32 (numpy's `density.flat[cells] +=
    added.astype(float32)`); with free space carved, a hit and this insert's mark per cell."""
    dens, hit, mark = density.reshape(-1), hits.reshape(-1), stamped.reshape(-1)
    for d in range(cells.shape[0]):
        c = cells[d]
        dens[c] = dens[c] + np.float32(added[d])
        if carved:
            hit[c] = hit[c] + np.float32(1.0)
            mark[c] = this_insert


@_jit
def _normalised(density: F32Array, rad: int, i: int, j: int) -> np.float32:
    """The field at cell (i, j): its density over the maximum of the (2·rad + 1)² window
    (clipped to the grid), 0 where that maximum is at most 1e-3. Maxima are exact in any order;
    the division is float32's."""
    h, w = density.shape
    floor = np.float32(1e-3)
    d = density[i, j]
    peak = d
    for ii in range(max(0, i - rad), min(h, i + rad + 1)):
        for jj in range(max(0, j - rad), min(w, j + rad + 1)):
            peak = max(peak, density[ii, jj])
    return d / max(peak, floor) if peak > floor else np.float32(0.0)


@_jit
def normalise(  # noqa: PLR0917 - numba takes no keyword-only arguments
    density: F32Array,
    values: F32Array,
    hits: F32Array,
    misses: F32Array,
    carved: bool,
    rad: int,
    i0: int,
    i1: int,
    j0: int,
    j1: int,
) -> None:
    """`LikelihoodGrid._normalise` over rows i0:i1, columns j0:j1 (within the grid): the field
    = density / its maximum over the (2·rad + 1)² window (clipped to the grid), 0 where that
    maximum is at most 1e-3; with free space `carved`, times hits / max(hits + misses, 1)
    where hits + misses > 0, all in float32: the bits of numpy's `values *= np.where(seen > 0,
    h / np.maximum(seen, 1.0), 1.0)`, without its temporaries over the box.

    Where the density is 0 (most of a scan's box: open space) so is the field, whatever the
    maximum. Along a run of cells with density in a row, each column's maximum over the
    window's rows is taken once and the run's windows take the maximum of those (maxima are
    exact in any order: `_normalised`'s values)."""
    h, w = density.shape
    floor = np.float32(1e-3)
    col_peak = np.empty(w, dtype=np.float32)  # per column c_lo + c of a run
    # Rows sliced to start at 0 (no negative-index wrapping to test in the loops).
    for i in range(i0, i1):
        r_lo, r_hi = max(0, i - rad), min(h, i + rad + 1)
        dens, field = density[i, j0:j1], values[i, j0:j1]
        j = 0
        while j < j1 - j0:
            if not dens[j] > 0.0:
                field[j] = np.float32(0.0)
                j += 1
                continue
            k = j + 1
            while k < j1 - j0 and dens[k] > 0.0:
                k += 1
            c_lo, c_hi = max(0, j0 + j - rad), min(w, j0 + k + rad)
            n_c = c_hi - c_lo
            top = density[r_lo, c_lo:c_hi]
            for c in range(n_c):
                col_peak[c] = top[c]
            for r in range(r_lo + 1, r_hi):
                row = density[r, c_lo:c_hi]
                for c in range(n_c):
                    col_peak[c] = max(col_peak[c], row[c])
            for jj in range(j, k):
                d = dens[jj]
                peak = d
                for c in range(max(0, j0 + jj - rad) - c_lo, min(w, j0 + jj + rad + 1) - c_lo):
                    peak = max(peak, col_peak[c])
                f = d / max(peak, floor) if peak > floor else np.float32(0.0)
                if carved:
                    hit = hits[i, j0 + jj]
                    seen = hit + misses[i, j0 + jj]
                    if seen > np.float32(0.0):
                        f = f * (hit / max(seen, np.float32(1.0)))
                field[jj] = f
            j = k


@_jit
def carve(  # noqa: PLR0917 - numba takes no keyword-only arguments
    density: F32Array,
    values: F32Array,
    hits: F32Array,
    misses: F32Array,
    stamped: npt.NDArray[np.int32],
    this_insert: int,
    rad: int,
    origin_row: float,
    origin_col: float,
    end_rows: FloatArray,
    end_cols: FloatArray,
    margin_cells: float,
) -> tuple[int, int, int, int]:
    """Free space seen by a keyframe's rays (continuous cell coordinates, integers at centres):
    every cell a ray crosses up to `margin_cells` before its return counts one miss (once per
    ray), and a crossed cell on a surface gets its field again, the normalised density times
    hits / (hits + misses). A cell this keyframe's own hits stamped (`stamped` ==
    `this_insert`) is a surface seen now, not free: a ray grazing a wall does not erode it.
    Returns the box (rows i0:i1, columns j0:j1) of the field changed."""
    h, w = density.shape
    bi0, bi1, bj0, bj1 = h, 0, w, 0
    n = end_rows.shape[0]
    max_steps = 1
    for k in range(n):  # the most steps a ray takes (as below)
        dr = end_rows[k] - origin_row
        dc = end_cols[k] - origin_col
        free = math.sqrt(dr * dr + dc * dc) - margin_cells
        if free > 0.0:
            max_steps = max(max_steps, int(free * 2.0) + 1)
    rows = np.empty(max_steps, dtype=np.int64)  # a ray's cells, step by step ...
    cols = np.empty(max_steps, dtype=np.int64)
    crossed = np.empty(max_steps, dtype=np.int64)  # ... and the distinct ones, flat
    flat_stamped, flat_misses = stamped.reshape(-1), misses.reshape(-1)
    flat_density = density.reshape(-1)
    for k in range(n):
        dr = end_rows[k] - origin_row
        dc = end_cols[k] - origin_col
        length = math.sqrt(dr * dr + dc * dc)
        free = length - margin_cells
        if free <= 0.0:
            continue
        steps = int(free * 2.0) + 1  # half a cell apart: no cell crossed is skipped
        for s in range(steps):  # (no branch: compiles to vector arithmetic)
            t = 0.5 * s / length
            rows[s] = math.floor(origin_row + dr * t + 0.5)
            cols[s] = math.floor(origin_col + dc * t + 0.5)
        # A step's cell counts when it is on the grid and not the last counted one. Rows and
        # columns are monotonic along the ray (every rounding is), so with both ends on the
        # grid every step is, and the last cell counted is the previous step's: the test is
        # then a comparison with it, without a branch.
        last = steps - 1
        n_crossed = 0
        on_grid = min(rows[0], rows[last]) >= 0 and max(rows[0], rows[last]) < h
        if on_grid and min(cols[0], cols[last]) >= 0 and max(cols[0], cols[last]) < w:
            prev = -1
            for s in range(steps):
                cell = rows[s] * w + cols[s]
                crossed[n_crossed] = cell
                n_crossed += cell != prev
                prev = cell
        else:
            prev_i, prev_j = -1, -1
            for s in range(steps):
                i, j = rows[s], cols[s]
                if (i == prev_i and j == prev_j) or i < 0 or j < 0 or i >= h or j >= w:
                    continue
                prev_i, prev_j = i, j
                crossed[n_crossed] = i * w + j
                n_crossed += 1
        for q in range(n_crossed):
            cell = crossed[q]
            if flat_stamped[cell] == this_insert:
                continue
            flat_misses[cell] += np.float32(1.0)
            if not flat_density[cell] > 0.0:
                continue
            i, j = cell // w, cell % w
            surface = _normalised(density, rad, i, j)
            values[i, j] = surface * hits[i, j] / (hits[i, j] + misses[i, j])
            bi0, bi1 = min(bi0, i), max(bi1, i + 1)
            bj0, bj1 = min(bj0, j), max(bj1, j + 1)
    return bi0, bi1, bj0, bj1


@_jit
def hard_counts(
    points_xy_m: FloatArray, columns: FloatArray, offset_bins: float, width: int
) -> tuple[IntArray, IntArray]:
    """Of each column's hard projection histogram (2K columns: x then y coordinates of R(α)·p
    in bin units, `heading._rotation_columns`): Σ h² (`heading.heading_scores` with hard bins)
    and the largest bin (the walls' peak fraction). Each coordinate is x·c₀ + y·c₁ -
    offset_bins, rounded as numpy's elementwise ufuncs round it, truncated to its bin; Σ h²
    grows by 2h + 1 per point that joins a bin of h, so the counts are exact (the same as
    numpy's `bincount` of those bins) and no (M, 2K) index array is written."""
    n_cols = columns.shape[1]
    hist = np.zeros(width, dtype=np.int64)
    energy = np.zeros(n_cols, dtype=np.int64)
    peaks = np.zeros(n_cols, dtype=np.int64)
    for col in range(n_cols):
        c0, c1 = columns[0, col], columns[1, col]
        hist[:] = 0
        e = 0
        peak = 0
        for p in range(points_xy_m.shape[0]):
            a = points_xy_m[p, 0] * c0
            b = points_xy_m[p, 1] * c1
            b = a + b
            b = b - offset_bins
            i = int(b)
            e += 2 * hist[i] + 1
            hist[i] += 1
            peak = max(peak, hist[i])
        energy[col] = e
        peaks[col] = peak
    return energy, peaks


@_jit
def soft_histograms(points_xy_m: FloatArray, columns: FloatArray) -> tuple[FloatArray, int]:
    """`heading.heading_scores`' soft histograms, (2K, width), and the width: each coordinate
    x·c₀ + y·c₁ (a column of `heading._rotation_columns`, in bin units), shifted by the bins
    below the smallest, split between its bin and the next by its fraction. The sums run in
    numpy's `bincount` order (point by point, each point's columns in turn), the two halves
    apart and then added, as `heading._soft_counts` does: the same bits."""
    m_n = points_xy_m.shape[0]
    n_cols = columns.shape[1]
    lowest = math.inf
    highest = -math.inf
    for p in range(m_n):
        for col in range(n_cols):
            v = points_xy_m[p, 0] * columns[0, col] + points_xy_m[p, 1] * columns[1, col]
            lowest = min(lowest, v)
            highest = max(highest, v)
    lo = math.floor(lowest) - 1
    width = math.ceil(highest) - lo + 2
    below = np.zeros((n_cols, width))
    above = np.zeros((n_cols, width))
    for p in range(m_n):
        for col in range(n_cols):
            a = points_xy_m[p, 0] * columns[0, col]
            b = points_xy_m[p, 1] * columns[1, col]
            v = (a + b) - lo
            i = int(v)
            frac = v - math.floor(v)
            below[col, i] += 1.0 - frac
            above[col, i + 1] += frac
    return below + above, width
