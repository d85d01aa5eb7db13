"""The occupancy grid's ray casting, compiled (numba): the cells one scan crosses and ends in.

`mark_cells` does what `OccupancyGrid.integrate` did in numpy, with the same floating-point
operations in the same order, so the same cells: the samples along each beam (`t = start +
step * k`), their cells (`floor(f + t * direction)`) and the scan-local window they are marked
in (1 free, 2 hit: a hit wins). The beam directions' cos and sin stay in numpy with the caller
(numpy's vectorised transcendental functions are not libm's). No fastmath: LLVM then neither
reorders nor fuses (a·b + c stays two roundings). `nogil`: a back end drawing a map does not
hold the front end's GIL.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

from service.core.types import FloatArray

I8Array = npt.NDArray[np.int8]

_jit = numba.njit(cache=True, nogil=True)


@_jit
def _mark(mark: I8Array, index: int, value: int) -> None:
    """mark[index] = value, with numpy's meaning of a negative index (and its IndexError)."""
    size = mark.shape[0]
    if index < 0:
        index += size
    if index < 0 or index >= size:
        raise IndexError("a ray-cast cell outside the scan's window")
    mark[index] = value


@_jit
def _mark_samples(  # noqa: PLR0917 - numba takes no keyword-only arguments
    mark: I8Array,
    origin: tuple[float, float, int, int, int],
    dir_x: float,
    dir_y: float,
    start_m: float,
    end_m: float,
    step_m: float,
) -> None:
    """Mark free the cells of the samples `start_m + step_m * k` below `end_m` of one beam.
    `origin`: the sensor in cells (fx, fy) and the window (i0, j0, width)."""
    fx, fy, i0, j0, width = origin
    count = math.ceil((end_m - start_m) / step_m)
    for k in range(max(count, 0)):
        t = start_m + step_m * float(k)
        i = math.floor(fy + t * dir_y)
        j = math.floor(fx + t * dir_x)
        _mark(mark, (i - i0) * width + (j - j0), 1)


@_jit
def mark_cells(  # noqa: PLR0917 - numba takes no keyword-only arguments
    fx: float,
    fy: float,
    dir_x: FloatArray,
    dir_y: FloatArray,
    ranges_m: FloatArray,
    starts_m: FloatArray,
    split_m: float,
    res: float,
    step_m: float,
) -> tuple[I8Array, int, int, int]:
    """The scan-local window of the cells crossed (1) and hit (2): (mark, i0, j0, width),
    cell (i, j) at `mark[(i - i0) * width + (j - j0)]`.

    (fx, fy): the sensor in cells; per valid beam, its direction over the resolution (dir_x,
    dir_y: cos and sin / res), its range and the distance its tracing starts at. Samples are
    `step_m` apart up to `split_m` (where neighbouring beams are a cell apart), `res` beyond,
    and stop half a cell before the hit.
    """
    n = ranges_m.shape[0]
    hit_i = np.empty(n, dtype=np.int64)
    hit_j = np.empty(n, dtype=np.int64)
    i0 = i1 = math.floor(fy)
    j0 = j1 = math.floor(fx)
    for b in range(n):
        hit_i[b] = math.floor(fy + ranges_m[b] * dir_y[b])
        hit_j[b] = math.floor(fx + ranges_m[b] * dir_x[b])
        i0 = min(i0, hit_i[b])
        i1 = max(i1, hit_i[b])
        j0 = min(j0, hit_j[b])
        j1 = max(j1, hit_j[b])
    width = j1 - j0 + 1
    mark = np.zeros((i1 - i0 + 1) * width, dtype=np.int8)
    origin = (fx, fy, i0, j0, width)
    for b in range(n):
        end = ranges_m[b] - 0.5 * res
        fine_end = min(end, split_m)
        _mark_samples(mark, origin, dir_x[b], dir_y[b], starts_m[b], fine_end, step_m)
        coarse_start = max(starts_m[b], fine_end)
        _mark_samples(mark, origin, dir_x[b], dir_y[b], coarse_start, end, res)
    for b in range(n):
        _mark(mark, (hit_i[b] - i0) * width + (hit_j[b] - j0), 2)
    return mark, i0, j0, width
