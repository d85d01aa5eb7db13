"""What the emulated UTM-30LX sees: a `Scene` gives the ranges of scan number k.

`make_scene(seed)` builds the synthetic building of `sensor_agent.sim.world` with a robot driving
its corridor loop; `RectangleRoom` is a tiny built-in fallback (and a cheap scene for tests).
Both are deterministic: scan k depends only on the seed and k.
"""

from __future__ import annotations

import logging
import math
from typing import Final, NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

log = logging.getLogger(__name__)

# UTM-30LX geometry (PROTOCOLS.md A.5): steps AMIN..AMAX, front AFRT, ARES steps per turn.
UTM_AMIN: Final = 0
UTM_AMAX: Final = 1080
UTM_AFRT: Final = 540
UTM_ARES: Final = 1440
UTM_DMIN_MM: Final = 23
UTM_DMAX_MM: Final = 60_000
UTM_SCAN_PERIOD_S: Final = 0.025  # 2400 rpm
UTM_STEPS: Final = UTM_AMAX - UTM_AMIN + 1


class SceneScan(NamedTuple):
    """(UTM_STEPS,) uint32 distances in mm (codes below DMIN for invalid beams) and intensities."""

    ranges_mm: npt.NDArray[np.uint32]
    intensities: npt.NDArray[np.uint32]


class Scene(Protocol):
    """The emulator's source of measurements."""

    def scan(self, index: int) -> SceneScan:
        """Scan number `index` (taken at `index * 25 ms` of scene time) for steps AMIN..AMAX."""
        ...


def _step_angles_rad() -> npt.NDArray[np.float64]:
    steps = np.arange(UTM_AMIN, UTM_AMAX + 1, dtype=np.float64)
    return (steps - UTM_AFRT) * 2.0 * math.pi / UTM_ARES


def _synthetic_intensities(
    ranges_mm: npt.NDArray[np.uint32], rng: np.random.Generator
) -> npt.NDArray[np.uint32]:
    """Plausible intensities: stronger when near, zero for invalid beams."""
    r_m = ranges_mm.astype(np.float64) / 1000.0
    base = 6000.0 / (1.0 + 0.15 * r_m * r_m) + rng.normal(0.0, 50.0, r_m.shape)
    base[ranges_mm < UTM_DMIN_MM] = 0.0
    return np.clip(np.rint(base), 0, 262_143).astype(np.uint32)


class RectangleRoom:
    """An empty W x H room; the laser circles its centre once every 20 s."""

    def __init__(self, seed: int = 0, width_m: float = 8.0, height_m: float = 5.0) -> None:
        self.seed = seed
        self.width_m = width_m
        self.height_m = height_m
        self._angles = _step_angles_rad()

    def pose_at(self, t_s: float) -> tuple[float, float, float]:
        phase = 2.0 * math.pi * t_s / 20.0
        x = self.width_m / 2 + 1.0 * math.cos(phase)
        y = self.height_m / 2 + 1.0 * math.sin(phase)
        return x, y, phase + math.pi / 2

    def scan(self, index: int) -> SceneScan:
        rng = np.random.default_rng((self.seed, index))
        x, y, theta = self.pose_at(index * UTM_SCAN_PERIOD_S)
        a = self._angles + theta
        c, s = np.cos(a), np.sin(a)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (self.width_m - x) / c, np.where(c < 0, -x / c, np.inf))
            ty = np.where(s > 0, (self.height_m - y) / s, np.where(s < 0, -y / s, np.inf))
        r_m = np.minimum(tx, ty) + rng.normal(0.0, 0.01, a.shape)
        mm = np.clip(np.rint(r_m * 1000.0), UTM_DMIN_MM, UTM_DMAX_MM).astype(np.uint32)
        # A few dropouts with the UTM-30LX "measurement error" code, as real scans have.
        mm[rng.random(a.shape) < 0.002] = 3
        return SceneScan(mm, _synthetic_intensities(mm, rng))


class WorldScene:
    """The synthetic building of `sensor_agent.sim.world`, seen by a UTM-30LX on a moving robot."""

    def __init__(self, seed: int = 1) -> None:
        from sensor_agent.sim import world as sim  # noqa: PLC0415  # heavy; only when used

        self.seed = seed
        self._sim = sim
        self._world = sim.generate_building(seed)
        self._motion = sim.RobotMotion(self._world, seed)
        self._model = sim.LaserModel.utm30lx()
        if self._model.beam_count != UTM_STEPS:
            raise ValueError(f"sim laser has {self._model.beam_count} beams, need {UTM_STEPS}")

    def pose_at(self, t_s: float) -> tuple[float, float, float]:
        return self._motion.pose_at(t_s)

    def scan(self, index: int) -> SceneScan:
        rng = np.random.default_rng((self.seed, index))
        pose = self._motion.pose_at(index * UTM_SCAN_PERIOD_S)
        sample = self._sim.simulate_scan(self._world, pose, self._model, rng)
        mm = np.minimum(np.asarray(sample.ranges_mm, dtype=np.uint32), UTM_DMAX_MM)
        return SceneScan(mm, _synthetic_intensities(mm, rng))


def make_scene(seed: int = 1, kind: str = "world") -> Scene:
    """`"world"` (the synthetic building; falls back to the room if unavailable) or `"room"`."""
    if kind == "room":
        return RectangleRoom(seed)
    try:
        return WorldScene(seed)
    except (ImportError, AttributeError, ValueError) as err:
        log.warning("synthetic building unavailable (%s); using a rectangular room", err)
        return RectangleRoom(seed)


__all__ = [
    "UTM_AFRT",
    "UTM_AMAX",
    "UTM_AMIN",
    "UTM_ARES",
    "UTM_DMAX_MM",
    "UTM_DMIN_MM",
    "UTM_SCAN_PERIOD_S",
    "UTM_STEPS",
    "RectangleRoom",
    "Scene",
    "SceneScan",
    "WorldScene",
    "make_scene",
]
