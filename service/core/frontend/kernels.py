"""The matcher's inner loops, compiled (numba): the same floating-point operations, in the same
order, as the numpy code they replace, so the same bits.

What numpy would compute with its own vectorised transcendental functions (log, exp) or with
BLAS, and the sums whose order numpy chooses (pairwise), stay in numpy with the callers: the
kernels do only the elementwise arithmetic and the gathers, where a scan's few hundred points
cost numpy dozens of calls of overhead each. No fastmath: LLVM then neither reorders nor fuses
(a·b + c stays two roundings).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from service.core.types import FloatArray

F32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]

_jit = numba.njit(cache=True, nogil=True)


@_jit
def interpolate(  # noqa: PLR0917 - numba takes no keyword-only arguments
    values: F32Array,
    origin_x: float,
    origin_y: float,
    res: float,
    pts: FloatArray,
    c: float,
    s: float,
    tx: float,
    ty: float,
) -> tuple[FloatArray, FloatArray]:
    """`LikelihoodGrid.interpolate` at the points `pts` rotated by (c, s) and moved by (tx, ty)
    (`rotate_points` then the translation): bicubic value (clipped to [0, 1]) and gradient."""
    n = pts.shape[0]
    h, w = values.shape
    value = np.zeros(n)
    grad = np.zeros((n, 2))
    if h < 4 or w < 4:
        return value, grad
    wu = np.empty(4)
    dwu = np.empty(4)
    wv = np.empty(4)
    dwv = np.empty(4)
    for k in range(n):
        qx = (c * pts[k, 0] - s * pts[k, 1]) + tx
        qy = (s * pts[k, 0] + c * pts[k, 1]) + ty
        u = (qx - origin_x) / res - 0.5
        v = (qy - origin_y) / res - 0.5
        fv = math.floor(v)
        fu = math.floor(u)
        if not (fv >= 1.0 and fu >= 1.0 and fv < h - 2 and fu < w - 2):
            continue  # off the grid (or not a number): 0, no gradient
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
        value[k] = min(max(val, 0.0), 1.0)
        grad[k, 0] = d_du / res
        grad[k, 1] = d_dv / res
    return value, grad


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
def scan_jacobians(  # noqa: PLR0917 - numba takes no keyword-only arguments
    value: FloatArray,
    grad: FloatArray,
    r_sq: FloatArray,
    pts: FloatArray,
    c: float,
    s: float,
    max_residual_sigmas: float,
) -> tuple[FloatArray, FloatArray]:
    """`matcher._scan_terms`' per-point rows in the pose (x, y, θ): ∂(r²/2)/∂pose and the
    Gauss-Newton Jacobian ∂r/∂pose, each (N, 3)."""
    n = pts.shape[0]
    half_grad = np.empty((n, 3))
    jac = np.empty((n, 3))
    for k in range(n):
        r = math.sqrt(r_sq[k])
        inlier = r < max_residual_sigmas and value[k] > 0.0
        inv_m = 1.0 / max(value[k], 1e-9) if inlier else 0.0
        hx = -grad[k, 0] * inv_m
        hy = -grad[k, 1] * inv_m
        r_held = max(r, 0.1)
        jx = hx / r_held
        jy = hy / r_held
        dqx_dt = -s * pts[k, 0] - c * pts[k, 1]
        dqy_dt = c * pts[k, 0] - s * pts[k, 1]
        half_grad[k, 0] = hx
        half_grad[k, 1] = hy
        half_grad[k, 2] = hx * dqx_dt + hy * dqy_dt
        jac[k, 0] = jx
        jac[k, 1] = jy
        jac[k, 2] = jx * dqx_dt + jy * dqy_dt
    return half_grad, jac


@_jit
def _clamp(i: int, lo: int, hi: int) -> int:
    return min(max(i, lo), hi)


@_jit
def lattice_gather(  # noqa: PLR0917 - numba takes no keyword-only arguments
    flat: F32Array,
    row0: int,
    col0: int,
    height: int,
    width: int,
    px: FloatArray,
    py: FloatArray,
    cos_k: FloatArray,
    sin_k: FloatArray,
    di: IntArray,
    dj: IntArray,
    tx: float,
    ty: float,
    origin_x: float,
    origin_y: float,
    res: float,
) -> F32Array:
    """`search._Problem.exact`'s lookups: for each pose m (rotation (cos_k, sin_k)[m], cell
    offset (di, dj)[m] from (tx, ty)) the cost (a pyramid's level 0) under every point, (M, N).
    The mean is left to numpy (its summation order is the brute force's)."""
    m_n = cos_k.shape[0]
    n = px.shape[0]
    out = np.empty((m_n, n), dtype=np.float32)
    for m in range(m_n):
        c = cos_k[m]
        s = sin_k[m]
        for i in range(n):
            mx = c * px[i] - s * py[i] + tx
            my = s * px[i] + c * py[i] + ty
            row = int(np.rint((my - origin_y) / res - 0.5)) + di[m]
            col = int(np.rint((mx - origin_x) / res - 0.5)) + dj[m]
            r = _clamp(row - row0, 0, height - 1)
            cc = _clamp(col - col0, 0, width - 1)
            out[m, i] = flat[r * width + cc]
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
        for r in range(a0, min(h, r1)):
            for c in range(b0, min(w, c1)):
                v = levels[m, r, c]
                if r + s < h:
                    v = min(v, levels[m, r + s, c])
                    if c + s < w:
                        v = min(v, levels[m, r + s, c + s])
                else:
                    v = min(v, capf)
                v = min(v, levels[m, r, c + s]) if c + s < w else min(v, capf)
                levels[m + 1, r, c] = v


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
def stamp_cells(
    ci: IntArray, cj: IntArray, di: IntArray, dj: IntArray, width: int
) -> tuple[IntArray, IntArray, IntArray]:
    """The stamps' cells grouped by cell: (order, cells, starts) with `order` the stable argsort
    of the flat cell indices (hit-major, as `stamp_arguments`), `cells` the distinct ones
    ascending, `starts` where each begins in the sorted order. A counting sort over the
    stamps' box: the same permutation as numpy's stable sort, in linear time."""
    n, k_n = ci.shape[0], di.shape[0]
    i_lo, i_hi = ci.min() + di.min(), ci.max() + di.max()
    j_lo, j_hi = cj.min() + dj.min(), cj.max() + dj.max()
    bw = j_hi - j_lo + 1
    counts = np.zeros((i_hi - i_lo + 1) * bw + 1, dtype=np.int64)
    keys = np.empty(n * k_n, dtype=np.int64)
    for p in range(n):
        for k in range(k_n):
            key = (ci[p] + di[k] - i_lo) * bw + (cj[p] + dj[k] - j_lo)
            keys[p * k_n + k] = key
            counts[key + 1] += 1
    distinct = 0
    for b in range(1, counts.shape[0]):
        if counts[b] > 0:
            distinct += 1
        counts[b] += counts[b - 1]
    cells = np.empty(distinct, dtype=np.int64)
    starts = np.empty(distinct, dtype=np.int64)
    d = 0
    for b in range(counts.shape[0] - 1):
        if counts[b + 1] > counts[b]:
            cells[d] = (b // bw + i_lo) * width + (b % bw + j_lo)
            starts[d] = counts[b]
            d += 1
    order = np.empty(n * k_n, dtype=np.int64)
    for idx in range(n * k_n):
        key = keys[idx]
        order[counts[key]] = idx
        counts[key] += 1
    return order, cells, starts


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
    density: F32Array, values: F32Array, rad: int, i0: int, i1: int, j0: int, j1: int
) -> None:
    """`LikelihoodGrid._normalise` over rows i0:i1, columns j0:j1 (within the grid): the field
    = density / its maximum over the (2·rad + 1)² window (clipped to the grid), 0 where that
    maximum is at most 1e-3. Where the density is 0 (most of a scan's box: open space) so is
    the field, whatever the maximum, so the window is read only where it is not
    (`_normalised`)."""
    for i in range(i0, i1):
        for j in range(j0, j1):
            if density[i, j] > 0.0:
                values[i, j] = _normalised(density, rad, i, j)
            else:
                values[i, j] = np.float32(0.0)


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
    for k in range(end_rows.shape[0]):
        dr = end_rows[k] - origin_row
        dc = end_cols[k] - origin_col
        length = math.sqrt(dr * dr + dc * dc)
        free = length - margin_cells
        if free <= 0.0:
            continue
        steps = int(free * 2.0) + 1  # half a cell apart: no cell crossed is skipped
        prev_i, prev_j = -1, -1
        for s in range(steps):
            t = 0.5 * s / length
            i = math.floor(origin_row + dr * t + 0.5)
            j = math.floor(origin_col + dc * t + 0.5)
            if (i == prev_i and j == prev_j) or i < 0 or j < 0 or i >= h or j >= w:
                continue
            prev_i, prev_j = i, j
            if stamped[i, j] == this_insert:
                continue
            misses[i, j] += np.float32(1.0)
            if not density[i, j] > 0.0:
                continue
            surface = _normalised(density, rad, i, j)
            values[i, j] = surface * hits[i, j] / (hits[i, j] + misses[i, j])
            bi0, bi1 = min(bi0, i), max(bi1, i + 1)
            bj0, bj1 = min(bj0, j), max(bj1, j + 1)
    return bi0, bi1, bj0, bj1


@_jit
def hard_energies(
    points_xy_m: FloatArray, columns: FloatArray, offset_bins: float, width: int
) -> IntArray:
    """`heading.heading_scores` with hard bins: Σ h² of each column's projection histogram (2K
    columns: x then y coordinates of R(α)·p in bin units, `heading._rotation_columns`), the
    x and y sums added per angle. Each coordinate is x·c₀ + y·c₁ - offset_bins, rounded as
    numpy's elementwise ufuncs round it, truncated to its bin; Σ h² grows by 2h + 1 per point
    that joins a bin of h, so the counts are exact and no (M, 2K) index array is written."""
    n_cols = columns.shape[1]
    k = n_cols // 2
    hist = np.zeros(width, dtype=np.int64)
    energy = np.zeros(n_cols, dtype=np.int64)
    for col in range(n_cols):
        c0, c1 = columns[0, col], columns[1, col]
        hist[:] = 0
        e = 0
        for p in range(points_xy_m.shape[0]):
            a = points_xy_m[p, 0] * c0
            b = points_xy_m[p, 1] * c1
            b = a + b
            b = b - offset_bins
            i = int(b)
            e += 2 * hist[i] + 1
            hist[i] += 1
        energy[col] = e
    return energy[:k] + energy[k:]
