"""Joint 2-D check of the 1-D translation candidates against the local map.

The paper's two 1-D correlations are independent, so periodic doors along a corridor or an open
end can pull one axis to a wrong peak while the other is right. Scoring the few (x, y)
combinations of the best 1-D peaks by how many current points land on occupied local-map cells
picks the consistent one. The map is a sorted array of occupied cell keys (dilated by one cell),
so the memory is proportional to the local map and each check is a `searchsorted`.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from service.core.types import FloatArray

_OFFSET = 1 << 20  # keeps cell indices positive within ±52 km at 0.1 m
_STRIDE = 1 << 21


class OccupiedCells:
    """Set of cells (default 0.1 m) within one cell of a local-map point."""

    def __init__(self, points_map_m: FloatArray, cell_m: float = 0.1) -> None:
        self.cell_m = cell_m
        c = np.floor(points_map_m / cell_m).astype(np.int64) + _OFFSET
        di, dj = (a.ravel() for a in np.mgrid[-1:2, -1:2])
        keys = (c[:, 0:1] + di[None, :]) * _STRIDE + (c[:, 1:2] + dj[None, :])
        self.keys: npt.NDArray[np.int64] = np.unique(keys.ravel())

    def hit_fraction(self, points_rot_m: FloatArray, cands: FloatArray) -> FloatArray:
        """Share of the (already rotated) points on occupied cells, per candidate translation."""
        k = cands.shape[0]
        world = points_rot_m[None, :, :] + cands[:, None, :]
        c = np.floor(world / self.cell_m).astype(np.int64) + _OFFSET
        q = (c[..., 0] * _STRIDE + c[..., 1]).ravel()
        pos = np.searchsorted(self.keys, q)
        pos = np.minimum(pos, self.keys.size - 1)
        hit = (self.keys[pos] == q).reshape(k, -1)
        return np.asarray(hit.mean(axis=1), dtype=np.float64)
