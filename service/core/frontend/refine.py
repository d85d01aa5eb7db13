"""Joint 2-D check of the 1-D translation candidates against the local map.

The paper's two 1-D correlations are independent, so periodic doors along a corridor or an open
end can pull one axis to a wrong peak while the other is right. Scoring the few (x, y)
combinations of the best 1-D peaks by how many current points land on occupied local-map cells
picks the consistent one. The map is a boolean bitmap of occupied cells (dilated by one cell)
over the local map's bounding box: built in O(points) when a keyframe is added (no sort), and
each check is one gather. A local map spread so wide that the bitmap would be large falls back to
a sorted array of cell keys and `searchsorted` (memory proportional to the points).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from service.core.types import FloatArray, column_bounds

_OFFSET = 1 << 20  # keeps cell indices positive within ±52 km at 0.1 m
_STRIDE = 1 << 21
_MAX_BITMAP_CELLS = 1 << 22  # 4 Mi cells = 4 MiB of bool; wider local maps use sorted keys


class OccupiedCells:
    """Set of cells (default 0.1 m) within one cell of a local-map point."""

    def __init__(self, points_map_m: FloatArray, cell_m: float = 0.1) -> None:
        self.cell_m = cell_m
        self._bitmap: npt.NDArray[np.bool_] | None = None
        self._keys: npt.NDArray[np.int64] | None = None
        self._origin = np.zeros(2, dtype=np.int64)
        c = np.floor(points_map_m / cell_m).astype(np.int64)
        if c.shape[0] == 0:
            self._keys = np.empty(0, dtype=np.int64)
            return
        # Two cells of margin: the dilation reaches one, so the border rows and columns stay
        # free and a query clipped onto the border reads "free".
        x0, y0, x1, y1 = column_bounds(c)
        lo = np.array([x0 - 2, y0 - 2], dtype=np.int64)
        hi = np.array([x1 + 2, y1 + 2], dtype=np.int64)
        h, w = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
        if h * w <= _MAX_BITMAP_CELLS:
            self._origin = lo
            occ = np.zeros(h * w, dtype=np.bool_)
            occ[(c[:, 0] - lo[0]) * w + (c[:, 1] - lo[1])] = True
            occ2 = occ.reshape(h, w)
            # 3x3 dilation, separable: rows then columns (the margin keeps it off the edges).
            rows = occ2.copy()
            rows[1:] |= occ2[:-1]
            rows[:-1] |= occ2[1:]
            bitmap = rows.copy()
            bitmap[:, 1:] |= rows[:, :-1]
            bitmap[:, :-1] |= rows[:, 1:]
            self._bitmap = bitmap
        else:
            c += _OFFSET
            di, dj = (a.ravel() for a in np.mgrid[-1:2, -1:2])
            keys = (c[:, 0:1] + di[None, :]) * _STRIDE + (c[:, 1:2] + dj[None, :])
            self._keys = np.unique(keys.ravel())

    def hit_fraction(self, points_rot_m: FloatArray, cands: FloatArray) -> FloatArray:
        """Share of the (already rotated) points on occupied cells, per candidate translation."""
        k = cands.shape[0]
        world = points_rot_m[None, :, :] + cands[:, None, :]
        c = np.floor(world / self.cell_m).astype(np.int64)
        if self._bitmap is not None:
            h, w = self._bitmap.shape
            i = c[..., 0]
            j = c[..., 1]
            i -= self._origin[0]
            j -= self._origin[1]
            # Outside the box: onto the (free) border.
            np.minimum(np.maximum(i, 0, out=i), h - 1, out=i)
            np.minimum(np.maximum(j, 0, out=j), w - 1, out=j)
            i *= w
            i += j
            hit = self._bitmap.ravel()[i]
        else:
            assert self._keys is not None
            if self._keys.size == 0:
                return np.zeros(k, dtype=np.float64)
            c += _OFFSET
            q = (c[..., 0] * _STRIDE + c[..., 1]).ravel()
            pos = np.searchsorted(self._keys, q)
            pos = np.minimum(pos, self._keys.size - 1)
            hit = (self._keys[pos] == q).reshape(k, -1)
        # Count / n: bit for bit the mean of the booleans, without the generic mean's overhead.
        m = max(1, points_rot_m.shape[0])
        return np.asarray(np.count_nonzero(hit, axis=1) / m, dtype=np.float64)
