"""Wall frames ("Atlanta world"): the building's wall families, each Manhattan on its own.

The paper's heading is absolute modulo 90° because every wall is parallel or perpendicular to
the first one. A wing built at 30° breaks that: its walls are Manhattan among themselves, at
30° to the main block's. Measured against the main block's family, the wing's walls make the
heading snap 30° (the wing "folded onto the main axes").

So the estimator keeps a list of wall families, each an angle in the map frame modulo 90°
(the first is 0: the first scan's walls define the map). The heading is measured against the
family the scan's surfaces follow (`WallFrames.select`), and the translation is correlated
along that family's axes. A family is added only when it is measured, not guessed: in scans
that see a known family and measure the heading on it, a strong set of walls far from every
known family, at the same angle from places along the path (`WallFrames.observe`). Walls seen
at an angle while no known family is in view are the heading's own error: not a family.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from service.core.frontend.heading import QUARTER, resolve_heading, wrap_quarter
from service.core.types import FloatArray

_BIN_RAD = math.radians(0.5)
_N_BINS = round(QUARTER / _BIN_RAD)


@dataclass(frozen=True, slots=True)
class FrameParams:
    tolerance_deg: float = 4.0  # a surface within this of a family's axes follows it
    switch_ratio: float = 2.0  # another family needs this many times the current one's support
    min_points: int = 20  # surfaces a family needs to be selected
    new_min_deg: float = 12.0  # a new family is at least this far from every known one
    new_min_share: float = 0.2  # ... and carries this share of the scan's surfaces ...
    new_min_points: int = 60  # ... and this many (~3 m of wall: its angle is measured on it)
    new_observations: int = 3  # ... in this many trusted scans ...
    new_span_m: float = 1.5  # ... taken this far apart (a curved wall turns as one drives by) ...
    new_agree_deg: float = 0.25  # ... measured within this of their median ...
    new_agree_share: float = 0.67  # ... as most of its observations are (a curved wall's scatter)
    pending_m: float = 8.0  # observations farther back along the path are forgotten
    # A scan is trusted to measure one when its heading stands on walls this strong (twice
    # the estimator's minimum peak fraction): a heading walked off a curved wall is not.
    new_anchor_peak_fraction: float = 0.16
    max_frames: int = 8  # a building has few wall families; beyond that, stop adding


def _quarter_dist(a: FloatArray, b: float) -> FloatArray:
    return np.abs(np.asarray(wrap_quarter(a - b), dtype=np.float64))


def family_support(
    map_directions_rad: FloatArray, frames_rad: list[float], tolerance_rad: float
) -> list[int]:
    """How many surfaces (map-frame directions, modulo π) follow each family's axes."""
    return [int((_quarter_dist(map_directions_rad, f) <= tolerance_rad).sum()) for f in frames_rad]


def strongest_other_family(
    map_directions_rad: FloatArray,
    frames_rad: list[float],
    min_separation_rad: float,
    tolerance_rad: float,
) -> tuple[float, int] | None:
    """The best-supported direction (modulo 90°) at least `min_separation_rad` from every frame.

    Returns (angle in [-45°, 45°), surfaces within `tolerance_rad` of it), or None.
    """
    if map_directions_rad.shape[0] == 0:
        return None
    folded = np.asarray(wrap_quarter(map_directions_rad)) + QUARTER / 2.0
    idx = np.floor(folded / _BIN_RAD).astype(np.int64) % _N_BINS
    counts = np.bincount(idx, minlength=_N_BINS).astype(np.float64)
    # Support within ± tolerance of every bin centre (a circular box sum).
    half = max(1, round(tolerance_rad / _BIN_RAD))
    padded = np.concatenate((counts[-half:], counts, counts[:half]))
    csum = np.concatenate(([0.0], np.cumsum(padded)))
    support = csum[2 * half + 1 :] - csum[: -(2 * half + 1)]
    centres: FloatArray = (np.arange(_N_BINS, dtype=np.float64) + 0.5) * _BIN_RAD - QUARTER / 2.0
    far = np.ones(_N_BINS, dtype=bool)
    for f in frames_rad:
        far &= _quarter_dist(centres, f) >= min_separation_rad
    if not far.any():
        return None
    best = int(np.flatnonzero(far)[np.argmax(support[far])])
    return float(centres[best]), int(support[best])


@dataclass(slots=True)
class WallFrames:
    """The known wall families (map-frame angles modulo 90°) and the one the robot is in."""

    params: FrameParams = field(default_factory=FrameParams)
    angles_rad: list[float] = field(default_factory=lambda: [0.0])
    current: int = 0
    # The first family came from weak walls (the first scan saw a curved wall or clutter):
    # the first family measured on strong walls replaces it.
    provisional: bool = False
    # Recent trusted observations of a family not yet known: (x, y, angle) with the robot's
    # position in the map frame.
    _pending: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=64))

    @property
    def angle_rad(self) -> float:
        """The current family's angle."""
        return self.angles_rad[self.current]

    def select(self, map_directions_rad: FloatArray) -> int:
        """The family the scan's surfaces (at the predicted heading) follow; sticky by a margin."""
        if len(self.angles_rad) == 1:
            return self.current
        p = self.params
        support = family_support(map_directions_rad, self.angles_rad, math.radians(p.tolerance_deg))
        best = int(np.argmax(support))
        here = support[self.current]
        if (
            best != self.current
            and support[best] >= p.min_points
            and support[best] >= p.switch_ratio * here
        ):
            self.current = best
        return self.current

    def candidate(self, map_directions_rad: FloatArray) -> float | None:
        """A strong family far from the known ones in this scan (its rough angle), or None."""
        p = self.params
        if len(self.angles_rad) >= p.max_frames:
            return None
        total = map_directions_rad.shape[0]
        needed = max(p.new_min_points, p.new_min_share * total)
        # A new family's surfaces are not the current family's (12° apart, 4° bands): when
        # too few are left over, there is none (most scans; speed).
        if total - self.current_support(map_directions_rad) < needed:
            return None
        found = strongest_other_family(
            map_directions_rad,
            self.angles_rad,
            math.radians(p.new_min_deg),
            math.radians(p.tolerance_deg),
        )
        if found is None:
            return None
        angle, count = found
        if count < needed:
            return None
        return angle

    def observe(self, angle_rad: float, x_m: float, y_m: float) -> bool:
        """A trusted measurement of a new family from (x_m, y_m); True when it is added.

        Added when `new_observations` of them, spread over at least `new_span_m` of the path,
        agree within `new_agree_deg`, as most of its recent ones do: a straight wall keeps its
        direction as the robot drives past, a curved one turns and scatters.
        """
        p = self.params
        self._pending.append((x_m, y_m, float(wrap_quarter(angle_rad))))
        while math.hypot(self._pending[0][0] - x_m, self._pending[0][1] - y_m) > p.pending_m:
            self._pending.popleft()
        found = self._consistent(angle_rad)
        if found is None:
            return False
        angle, agree_xy = found
        span = float(np.sqrt(((agree_xy[:, None, :] - agree_xy[None, :, :]) ** 2).sum(-1).max()))
        far = all(
            abs(float(wrap_quarter(angle - f))) >= math.radians(p.new_min_deg)
            for f in self.angles_rad
        )
        if span < p.new_span_m or not far:
            return False
        if self.provisional:
            self.angles_rad[0], self.current, self.provisional = angle, 0, False
        else:
            self.angles_rad.append(angle)
        self._pending.clear()
        return True

    def is_pending(self, angle_rad: float) -> bool:
        """Whether trusted scans are learning a family near `angle_rad` (consistent so far)."""
        return self._consistent(angle_rad) is not None

    def _consistent(self, angle_rad: float) -> tuple[float, FloatArray] | None:
        """The pending measurements near `angle_rad`, if they agree: (their angle, positions)."""
        p = self.params
        a = float(wrap_quarter(angle_rad))
        near = [(x, y, float(wrap_quarter(b - a))) for x, y, b in self._pending]
        near = [o for o in near if abs(o[2]) <= math.radians(p.new_min_deg)]
        if len(near) < p.new_observations:
            return None
        # The median on the branch of `a` (the angles are modulo 90°).
        median = float(np.median([o[2] for o in near]))
        agree = [o for o in near if abs(o[2] - median) <= math.radians(p.new_agree_deg)]
        if len(agree) < max(p.new_observations, p.new_agree_share * len(near)):
            return None
        xy: FloatArray = np.array([(o[0], o[1]) for o in agree], dtype=np.float64)
        return float(wrap_quarter(a + median)), xy

    def current_support(self, map_directions_rad: FloatArray) -> int:
        """How many surfaces follow the current family."""
        tolerance = math.radians(self.params.tolerance_deg)
        return family_support(map_directions_rad, [self.angle_rad], tolerance)[0]

    def nearest_member(self, manhattan_rad: float, heading_rad: float) -> tuple[float, int]:
        """The heading ≡ `manhattan_rad` + a family's angle (mod 90°) nearest `heading_rad`."""
        best, best_k, best_d = heading_rad, self.current, math.inf
        for k, f in enumerate(self.angles_rad):
            c = resolve_heading(manhattan_rad + f, heading_rad)
            d = abs(c - heading_rad)
            if d < best_d:
                best, best_k, best_d = c, k, d
        return best, best_k
