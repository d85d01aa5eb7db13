"""Building families: many kinds of synthetic building, each randomised by seed (pure numpy).

The estimator was tuned on one generator (``world.generate_building``); these families are the
ground it is judged on (issue 14). Each ``generate(family, seed)`` gives a ``GeneratedWorld``:
a ``World`` (the same ray caster and ``LaserModel`` as ``world.py``), a ground-truth
``Trajectory`` of at least 300 m that returns to its start pose, and the switchable features
(walking people, glass, a person next to the robot). ``iter_scans`` simulates the scans.

Families (``FAMILIES``):

- ``manhattan``: ``world.generate_building(seed, "paper")`` with ``generate_trajectory``,
  unchanged: the building the estimator was tuned on.
- ``ring``: a ring of ~2.4 m corridors about 120 x 40 m, walls of zero thickness, plain walls
  along the corridors except one long side, whose inner wall has 0.9 m openings every ~6 m
  into large hollow areas (no door frames); random-angle boxes of 0.2-0.5 m as clutter; every
  corridor is longer than the UTM-30LX's 30 m. The path weaves (0.15 m lateral std, 2 deg
  heading wobble), a scan every 0.3 m (the issue's setting); half the seeds start at the end of
  a plain ~36 m short side.
- ``long_corridor``: a loop of corridors of different widths (1.8-3.0 m), the long ones
  125-150 m, doors and alcoves along parts of them and a plain stretch of >= 45 m.
- ``office``: 0.15 m thick walls, a ring corridor plus a middle corridor (the path is a figure
  of eight through it), rooms with door jambs, open and closed doors, furniture.
- ``hall``: two open halls (pillars, clutter boxes, a curved wall) joined by two corridors; the
  path runs lanes between the pillar rows.
- ``wing``: an aligned main block plus a wing rotated by an angle drawn from 15-60 deg, joined
  by a corridor; the path goes round the main block, into the wing, round it and back. Half
  the seeds give the main block a curved (rotunda) west wall.

Features per world (``Features``; each family has seeded defaults, every one can be switched):
``walkers`` people walking back and forth (two legs, or a body, that occlude and move between
scans), ``glass`` wall stretches invisible to the ray caster (``GeneratedWorld.glass_m``, for
pictures only), ``blocker_prob`` the share of scans in which a person stands 0.45-0.9 m from
the robot and blocks part of the scan.

Path styles (``PathStyle``): lateral weave and heading wobble, stops, 360 deg turns in place
(sharp corners > 100 deg are always turned in place), a start at the end of a featureless
corridor. Scan timing: ``scan_rate_hz=None`` is the paper's setting (a scan every 0.3 m or
10 deg, and every 1 s while standing still; stamps at the robot's speed), otherwise a fixed
rate (5-40 Hz) at the drawn speed.

Seeds: ``TUNING_SEEDS`` (0-99) are for looking at and tuning; ``TEST_SEEDS`` (1000-1999) are
held out and reported only as distributions. ``TUNING_SET`` and ``TEST_SET`` fix the worlds the
benchmark (``bench.worlds``) runs.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Final, Literal

import numpy as np

from sensor_agent.sim.world import (
    RASTER_RES_M,
    FloatArray,
    LaserModel,
    ScanSample,
    SimError,
    Trajectory,
    World,
    _Plan,
    _wrap,
    apply_beam_model,
    generate_building,
    generate_trajectory,
)

Family = Literal["manhattan", "ring", "long_corridor", "office", "hall", "wing"]
FAMILIES: Final[tuple[Family, ...]] = (
    "manhattan",
    "ring",
    "long_corridor",
    "office",
    "hall",
    "wing",
)
TUNING_SEEDS: Final = range(100)
TEST_SEEDS: Final = range(1000, 2000)
# The worlds the benchmark runs: 2 per family to look at, 24 held out (>= 300 m each).
TUNING_SET: Final[tuple[tuple[Family, int], ...]] = tuple((f, s) for f in FAMILIES for s in (0, 1))
_TEST_COUNTS: Final[dict[Family, int]] = {
    "manhattan": 3,
    "ring": 5,
    "long_corridor": 4,
    "office": 4,
    "hall": 4,
    "wing": 4,
}
TEST_SET: Final[tuple[tuple[Family, int], ...]] = tuple(
    (f, 1000 + k) for f in FAMILIES for k in range(_TEST_COUNTS[f])
)
MIN_PATH_M: Final = 300.0
PAPER_SPACING_M: Final = 0.3
PAPER_ROTATION_DEG: Final = 10.0
_STILL_PERIOD_S: Final = 1.0  # paper setting: a scan every second while standing still
_DENSE_STEP_M: Final = 0.01
_FAMILY_CODE: Final[dict[str, int]] = {f: i + 1 for i, f in enumerate(FAMILIES)}

Seg = tuple[float, float, float, float]


# --------------------------------------------------------------------------------------------
# Public types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Features:
    """Switchable per world: walking people, glass, a person next to the robot."""

    walkers: int = 0
    glass: bool = False
    blocker_prob: float = 0.0  # share of scans partly blocked by a person next to the robot


@dataclass(frozen=True)
class PathStyle:
    """How the robot drives the route (see the module doc)."""

    weave_std_m: float = 0.03  # lateral offset from the centre line, std
    weave_corr_m: float = 0.6  # its correlation length along the path
    wobble_deg: float = 0.3  # heading noise per scan, std (independent of the travel direction)
    stops: int = 0  # stands still 2-6 s this many times
    spins: int = 0  # turns 360 deg in place this many times
    start_featureless: bool = False  # start at the end of the family's plainest corridor
    # The heading turns with the weave (a robot facing where it drives); without it the weave
    # is a sideways offset and the heading only wobbles (the setting).
    heading_follows_weave: bool = False


@dataclass(frozen=True, eq=False)
class Walker:
    """A person walking back and forth between ``a_xy`` and ``b_xy`` at ``speed_mps``.

    Seen by the laser as two legs (radius 0.06 m, swinging) or, with ``body``, one 0.22 m disc.
    """

    a_xy: tuple[float, float]
    b_xy: tuple[float, float]
    speed_mps: float
    phase_m: float
    body: bool

    def discs(self, t_s: float) -> FloatArray:
        """(K, 3) ``x, y, radius`` of the person at ``t_s`` seconds."""
        ax, ay = self.a_xy
        dx, dy = self.b_xy[0] - ax, self.b_xy[1] - ay
        length = math.hypot(dx, dy)
        u = (self.phase_m + self.speed_mps * t_s) % (2.0 * length)
        forward = u < length
        d = u if forward else 2.0 * length - u
        ex, ey = dx / length, dy / length
        cx, cy = ax + d * ex, ay + d * ey
        if self.body:
            return np.array([[cx, cy, 0.22]])
        sign = 1.0 if forward else -1.0
        swing = 0.18 * math.sin(2.0 * math.pi * u / 1.4)  # a stride every 0.7 m
        nx, ny = -ey, ex
        return np.array(
            [
                [cx + 0.1 * nx + sign * swing * ex, cy + 0.1 * ny + sign * swing * ey, 0.06],
                [cx - 0.1 * nx - sign * swing * ex, cy - 0.1 * ny - sign * swing * ey, 0.06],
            ]
        )


@dataclass(frozen=True, eq=False)
class GeneratedWorld:
    """One generated building with its ground truth and features; ``iter_scans`` simulates it.

    ``info`` holds what the family claims about itself (corridor lengths, openings, wing
    angle ...), checked by the tests.
    """

    family: str
    seed: int
    world: World
    glass_m: FloatArray  # (G, 4) wall segments the ray caster does not see
    trajectory: Trajectory
    walkers: tuple[Walker, ...]
    features: Features
    style: PathStyle
    model: LaserModel
    scan_rate_hz: float | None  # None: the paper's setting (0.3 m / 10 deg)
    speed_mps: float
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.family}-{self.seed}"

    @property
    def path_length_m(self) -> float:
        return float(self.trajectory.path_length_m)

    def first(self, n: int) -> GeneratedWorld:
        """The same world with only the first ``n`` poses (a short file for tests and demos)."""
        t = self.trajectory
        short = Trajectory(
            stamps_ns=t.stamps_ns[:n],
            poses=t.poses[:n],
            loop_length_m=t.loop_length_m,
            path_length_m=float(np.hypot(*np.diff(t.poses[:n, :2], axis=0).T).sum()),
        )
        return replace(self, trajectory=short)

    def describe(self) -> dict[str, Any]:
        """JSON-friendly summary (no arrays)."""
        return {
            "family": self.family,
            "seed": self.seed,
            "scans": len(self.trajectory),
            "path_length_m": round(self.path_length_m, 1),
            "duration_s": round(
                float(self.trajectory.stamps_ns[-1] - self.trajectory.stamps_ns[0]) / 1e9, 1
            ),
            "scan_rate_hz": self.scan_rate_hz,
            "speed_mps": round(self.speed_mps, 2),
            "laser": self.model.name,
            "features": {
                "walkers": len(self.walkers),
                "glass_segments": int(self.glass_m.shape[0]),
                "blocker_prob": self.features.blocker_prob,
            },
            "style": {
                "weave_std_m": round(self.style.weave_std_m, 3),
                "wobble_deg": round(self.style.wobble_deg, 2),
                "stops": self.style.stops,
                "spins": self.style.spins,
                "start_featureless": self.style.start_featureless,
            },
            "info": {k: v for k, v in self.info.items() if not isinstance(v, np.ndarray)},
        }


@dataclass(frozen=True, eq=False)
class SimScan:
    """One simulated scan of a ``GeneratedWorld`` at ground-truth pose ``pose``."""

    index: int
    stamp_ns: int
    pose: tuple[float, float, float]
    sample: ScanSample
    blocked: bool  # a person next to the robot blocks part of it


def world_set(name: Literal["tuning", "test"]) -> tuple[tuple[Family, int], ...]:
    """The fixed (family, seed) list of the tuning or the test set."""
    if name == "tuning":
        return TUNING_SET
    if name == "test":
        return TEST_SET
    raise SimError(f"unknown world set {name!r}; use 'tuning' or 'test'")


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------


def generate(
    family: str,
    seed: int,
    *,
    features: Features | None = None,
    style: PathStyle | None = None,
    scan_rate_hz: float | Literal["seeded"] | None = "seeded",
    speed_mps: float | None = None,
    model: LaserModel | None = None,
) -> GeneratedWorld:
    """The ``family`` building of ``seed`` (deterministic), with seeded features and path style.

    ``features``, ``style``, ``scan_rate_hz`` (None = paper setting) and ``speed_mps`` override
    the seeded choices; ``model`` defaults to the UTM-30LX.
    """
    if family not in _FAMILY_CODE:
        raise SimError(f"unknown family {family!r}; use one of {', '.join(FAMILIES)}")
    rng = np.random.default_rng([seed, _FAMILY_CODE[family], 0xFA31])
    model = model if model is not None else LaserModel.utm30lx()
    d_features, d_style, d_rate, d_speed = _seeded_choices(family, seed, rng)
    features = features if features is not None else d_features
    style = style if style is not None else d_style
    rate = d_rate if scan_rate_hz == "seeded" else scan_rate_hz
    if rate is not None and not 1.0 <= rate <= 100.0:
        raise SimError(f"scan_rate_hz must be within 1-100 Hz, got {rate}")
    speed = d_speed if speed_mps is None else speed_mps
    if speed <= 0:
        raise SimError("speed_mps must be positive")

    if family == "manhattan":
        return _manhattan(seed, features, style=style, model=model)
    builders = {
        "ring": _ring,
        "long_corridor": _long_corridor,
        "office": _office,
        "hall": _hall,
        "wing": _wing,
    }
    layout = builders[family](rng, features, style)
    segments = np.asarray(layout.segments, dtype=np.float64).reshape(-1, 4)
    glass = np.asarray(layout.glass, dtype=np.float64).reshape(-1, 4)
    route = np.asarray(layout.route, dtype=np.float64)
    # Shift everything so the building lies in the positive quadrant with a margin.
    lo = np.minimum(segments[:, :2].min(axis=0), segments[:, 2:].min(axis=0)) - 2.0
    shift = -lo
    segments[:, [0, 2]] += shift[0]
    segments[:, [1, 3]] += shift[1]
    if glass.shape[0]:
        glass[:, [0, 2]] += shift[0]
        glass[:, [1, 3]] += shift[1]
    route = route + shift
    hi = np.maximum(segments[:, :2].max(axis=0), segments[:, 2:].max(axis=0)) + 2.0
    walk_rng = np.random.default_rng([seed, _FAMILY_CODE[family], 0x3A1C])
    lanes = [((a[0] + shift[0], a[1] + shift[1]), (b[0] + shift[0], b[1] + shift[1]))
             for a, b in layout.walk_lanes]  # fmt: skip
    walkers = _walkers(lanes, features.walkers, walk_rng)
    world = World(
        seed=seed,
        size=family,
        width_m=float(hi[0]),
        height_m=float(hi[1]),
        corridor_width_m=layout.corridor_width_m,
        segments_m=segments,
        loop_xy_m=route,
        free_raster=_free_raster(segments, float(hi[0]), float(hi[1])),
    )
    path_rng = np.random.default_rng([seed, _FAMILY_CODE[family], 0x7A7B])
    trajectory = _drive(
        route,
        layout.start_frac,
        style,
        rate_hz=rate,
        speed_mps=speed,
        rng=path_rng,
        spin_corners=layout.spin_corners,
    )
    info = dict(layout.info)
    info["shift_m"] = [round(float(shift[0]), 3), round(float(shift[1]), 3)]
    return GeneratedWorld(
        family=family,
        seed=seed,
        world=world,
        glass_m=glass,
        trajectory=trajectory,
        walkers=walkers,
        features=features,
        style=style,
        model=model,
        scan_rate_hz=rate,
        speed_mps=speed,
        info=info,
    )


_RATE_CYCLE_HZ: Final[tuple[float | None, ...]] = (None, None, None, None, 5.0, 10.0, 20.0, 40.0)


def _seeded_choices(
    family: str, seed: int, rng: np.random.Generator
) -> tuple[Features, PathStyle, float | None, float]:
    """Default features, path style, scan rate and speed of a family's seed."""
    u = rng.random(12)
    if family == "ring":
        # The setting: weave 0.15 m / 2 deg, a scan every 0.3 m; a person next to the
        # robot in 5 % of the scans on a third of the seeds.
        features = Features(walkers=0, glass=False, blocker_prob=0.05 if u[0] < 0.35 else 0.0)
        style = PathStyle(
            weave_std_m=0.15,
            weave_corr_m=0.25,
            wobble_deg=2.0,
            stops=1 if u[1] < 0.3 else 0,
            spins=0,
            start_featureless=bool(u[2] < 0.5),
        )
        return features, style, None, 0.7
    if family == "manhattan":
        # world.generate_trajectory's own path (a 0.2 m sinusoidal wiggle), no extra style.
        return Features(), PathStyle(weave_std_m=0.0, wobble_deg=0.0), None, 0.7
    # Half the worlds in the paper's setting, the others at a fixed rate (5-40 Hz), cycling
    # with the seed so that every four consecutive seeds of a family cover several rates.
    rate = _RATE_CYCLE_HZ[(seed + _FAMILY_CODE[family]) % len(_RATE_CYCLE_HZ)]
    speed = float(rng.uniform(0.6, 1.2)) if rate is not None else 0.7
    weave = u[3] < 0.6
    style = PathStyle(
        weave_std_m=float(0.05 + 0.10 * u[4]) if weave else 0.03,
        # At a fixed rate the weave is a smooth swerve the heading follows; in the paper
        # setting a sideways offset between scans, as in the ring.
        weave_corr_m=1.0 if rate is not None else 0.25,
        wobble_deg=float(0.5 + 1.5 * u[5]) if weave else 0.3,
        stops=int(u[6] * 3) if u[6] < 0.6 else 0,
        spins=1 if u[7] < 0.4 else 0,
        start_featureless=bool(u[8] < 0.5) if family == "long_corridor" else False,
        heading_follows_weave=rate is not None,
    )
    walkers = {"office": 6, "hall": 5, "wing": 3, "long_corridor": 2}.get(family, 0)
    features = Features(
        walkers=int(walkers * (0.5 + u[9])) if u[9] < 0.8 else 0,
        glass=bool(u[10] < 0.5),
        blocker_prob=0.05 if u[11] < 0.2 else 0.0,
    )
    return features, style, rate, speed


# --------------------------------------------------------------------------------------------
# Scans
# --------------------------------------------------------------------------------------------


def _raycast_discs(
    px: float, py: float, world_angles: FloatArray, discs: FloatArray, max_range_m: float
) -> FloatArray:
    """(B,) distance to the nearest of the (K, 3) discs along each beam; inf where none."""
    out = np.full(world_angles.shape[0], np.inf)
    if discs.shape[0] == 0:
        return out
    c = discs[:, :2] - (px, py)
    dist_c = np.hypot(c[:, 0], c[:, 1])
    near = dist_c <= max_range_m + discs[:, 2]
    if not near.any():
        return out
    c, r = c[near], discs[near, 2]
    ux, uy = np.cos(world_angles), np.sin(world_angles)
    proj = ux[:, None] * c[None, :, 0] + uy[:, None] * c[None, :, 1]  # (B, K)
    cc = np.einsum("ij,ij->i", c, c)
    disc = proj**2 - (cc - r**2)[None, :]
    with np.errstate(invalid="ignore"):
        root = np.sqrt(np.maximum(disc, 0.0))
    t = np.where(cc[None, :] <= r[None, :] ** 2, 0.0, proj - root)  # inside a disc: 0
    hit = (disc >= 0.0) & (proj + root > 0.0)
    t = np.where(hit, np.maximum(t, 0.0), np.inf)
    out = np.asarray(t.min(axis=1), dtype=np.float64)
    out[out > max_range_m] = np.inf
    return out


def iter_scans(gw: GeneratedWorld, *, noise_seed: int | None = None) -> Iterator[SimScan]:
    """Simulate every scan of the world's trajectory (deterministic by seed).

    Walls by ``World.raycast`` (glass is not in it), people as discs at the scan's time, the
    person next to the robot with probability ``blocker_prob`` per scan, then the laser
    model's noise, dropouts and codes (``world.apply_beam_model``).
    """
    seed = gw.seed if noise_seed is None else noise_seed
    rng = np.random.default_rng([seed, _FAMILY_CODE[gw.family], 0x5CA7])
    block_rng = np.random.default_rng([seed, _FAMILY_CODE[gw.family], 0xB10C])
    model = gw.model
    angles = model.angles_rad()
    traj = gw.trajectory
    t0 = int(traj.stamps_ns[0])
    fov_half = 0.5 * (model.angle_max_rad - model.angle_min_rad)
    for i in range(len(traj)):
        x, y, th = (float(v) for v in traj.poses[i])
        stamp = int(traj.stamps_ns[i])
        true_m = gw.world.raycast((x, y, th), angles, model.range_max_m)
        t_s = (stamp - t0) * 1e-9
        parts = [w.discs(t_s) for w in gw.walkers]
        u = block_rng.random(4)
        blocked = bool(u[0] < gw.features.blocker_prob)
        if blocked:
            bearing = th + (u[1] * 2.0 - 1.0) * min(math.radians(100.0), fov_half)
            dist = 0.45 + 0.45 * u[2]
            radius = 0.18 + 0.12 * u[3]
            parts.append(
                np.array([[x + dist * math.cos(bearing), y + dist * math.sin(bearing), radius]])
            )
        if parts:
            discs = np.vstack(parts)
            people_m = _raycast_discs(x, y, angles + th, discs, model.range_max_m)
            true_m = np.minimum(true_m, people_m)
        yield SimScan(
            index=i,
            stamp_ns=stamp,
            pose=(x, y, th),
            sample=apply_beam_model(true_m, model, rng),
            blocked=blocked,
        )


def drifting_odometry(
    poses: FloatArray,
    seed: int,
    *,
    scale_std: float = 0.02,
    heading_bias_deg_per_m: float = 0.5,
    trans_noise_m: float = 0.005,
    rot_noise_deg: float = 0.2,
) -> FloatArray:
    """(N, 3) wheel odometry for ground-truth ``poses``: scale error, heading bias, noise.

    The scale error and the heading bias per metre are drawn once per world (std
    ``scale_std`` / ``heading_bias_deg_per_m``); every increment gets independent noise. It
    starts at (0, 0, 0), as a robot's odometry frame does.
    """
    rng = np.random.default_rng([seed, 0x0D0E])
    p = np.asarray(poses, dtype=np.float64)
    scale = 1.0 + rng.normal(0.0, scale_std)
    bias = math.radians(rng.normal(0.0, heading_bias_deg_per_m))
    a, b = p[:-1], p[1:]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    dth = _wrap(b[:, 2] - a[:, 2])
    n = lx.shape[0]
    dist = np.hypot(lx, ly)
    moving = dist > 1e-6
    lx = lx * scale + np.where(moving, rng.normal(0.0, trans_noise_m, n), 0.0)
    ly = ly * scale + np.where(moving, rng.normal(0.0, trans_noise_m, n), 0.0)
    rot_noise = np.where(moving | (np.abs(dth) > 1e-6), rng.normal(0.0, 1.0, n), 0.0)
    dth = dth + bias * dist + rot_noise * math.radians(rot_noise_deg)
    out = np.zeros_like(p)
    for i in range(n):
        th = out[i, 2]
        ci, si = math.cos(th), math.sin(th)
        out[i + 1, 0] = out[i, 0] + ci * lx[i] - si * ly[i]
        out[i + 1, 1] = out[i, 1] + si * lx[i] + ci * ly[i]
        out[i + 1, 2] = (th + dth[i] + math.pi) % (2.0 * math.pi) - math.pi
    return out


# --------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------


@dataclass
class _Layout:
    segments: list[Seg]
    glass: list[Seg]
    route: list[tuple[float, float]]  # closed route corners; the path starts on leg 0
    start_frac: float  # where on leg 0 the path starts (share of the leg)
    corridor_width_m: float
    walk_lanes: list[tuple[tuple[float, float], tuple[float, float]]] = field(default_factory=list)
    spin_corners: frozenset[int] = frozenset()
    info: dict[str, Any] = field(default_factory=dict)


def _wall(  # noqa: PLR0917 - a wall is its two end points' coordinates
    out: list[Seg], x0: float, y0: float, x1: float, y1: float, gaps: Sequence[tuple[float, float]]
) -> None:
    """Wall p0-p1 with openings ``gaps`` (distances from p0 along the wall)."""
    length = math.hypot(x1 - x0, y1 - y0)
    ex, ey = (x1 - x0) / length, (y1 - y0) / length
    t = 0.0
    for lo, hi in sorted(gaps):
        g0, g1 = max(lo, 0.0), min(hi, length)
        if g0 > t + 1e-9:
            out.append((x0 + t * ex, y0 + t * ey, x0 + g0 * ex, y0 + g0 * ey))
        t = max(t, g1)
    if length > t + 1e-9:
        out.append((x0 + t * ex, y0 + t * ey, x1, y1))


def _box(  # noqa: PLR0917 - centre, size, angle
    out: list[Seg], cx: float, cy: float, sx: float, sy: float, angle: float
) -> None:
    c, s = math.cos(angle), math.sin(angle)
    pts = [
        (cx + c * dx - s * dy, cy + s * dx + c * dy)
        for dx, dy in ((-sx / 2, -sy / 2), (sx / 2, -sy / 2), (sx / 2, sy / 2), (-sx / 2, sy / 2))
    ]
    for a, b in zip(pts, pts[1:] + pts[:1], strict=True):
        out.append((a[0], a[1], b[0], b[1]))


def _circle(out: list[Seg], cx: float, cy: float, r: float, n: int = 12) -> None:
    a = np.linspace(0.0, 2.0 * math.pi, n + 1)
    xs, ys = cx + r * np.cos(a), cy + r * np.sin(a)
    for i in range(n):
        out.append((float(xs[i]), float(ys[i]), float(xs[i + 1]), float(ys[i + 1])))


def _arc(  # noqa: PLR0917 - centre, radius, angles, pieces
    out: list[Seg], cx: float, cy: float, r: float, a0: float, a1: float, n: int
) -> list[tuple[float, float]]:
    a = np.linspace(a0, a1, n + 1)
    pts = [(float(cx + r * math.cos(v)), float(cy + r * math.sin(v))) for v in a]
    for p, q in itertools.pairwise(pts):
        out.append((p[0], p[1], q[0], q[1]))
    return pts


def _clutter_box(
    rng: np.random.Generator,
    out: list[Seg],
    cx: float,
    cy: float,
    *,
    lo: float = 0.2,
    hi: float = 0.5,
) -> None:
    _box(out, cx, cy, rng.uniform(lo, hi), rng.uniform(lo, hi), rng.uniform(0.0, math.pi))


def _openings(
    rng: np.random.Generator, start: float, end: float, width: float, spacing: tuple[float, float]
) -> list[tuple[float, float]]:
    """Openings of ``width`` between ``start`` and ``end``, centres ``spacing`` apart."""
    gaps = []
    c = start + rng.uniform(*spacing) / 2.0
    while c + width / 2.0 < end:
        gaps.append((c - width / 2.0, c + width / 2.0))
        c += rng.uniform(*spacing)
    return gaps


def _transform(segs: Sequence[Seg], origin: tuple[float, float], angle: float) -> list[Seg]:
    c, s = math.cos(angle), math.sin(angle)
    ox, oy = origin
    return [
        (ox + c * x0 - s * y0, oy + s * x0 + c * y0, ox + c * x1 - s * y1, oy + s * x1 + c * y1)
        for x0, y0, x1, y1 in segs
    ]


def _free_raster(segments: FloatArray, width_m: float, height_m: float) -> np.ndarray:
    """Approximate floor plan at ``RASTER_RES_M``: every cell a wall passes through is solid."""
    nx = max(1, math.ceil(width_m / RASTER_RES_M))
    ny = max(1, math.ceil(height_m / RASTER_RES_M))
    free = np.ones((ny, nx), dtype=bool)
    if segments.shape[0] == 0:
        return free
    lengths = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    counts = np.maximum(2, np.ceil(lengths / (RASTER_RES_M / 2.0)).astype(np.int64) + 1)
    idx = np.repeat(np.arange(segments.shape[0]), counts)
    offs = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    t = offs / np.repeat(counts - 1, counts)
    s = segments[idx]
    x = s[:, 0] + t * (s[:, 2] - s[:, 0])
    y = s[:, 1] + t * (s[:, 3] - s[:, 1])
    j = np.clip((x / RASTER_RES_M).astype(np.int64), 0, nx - 1)
    i = np.clip((y / RASTER_RES_M).astype(np.int64), 0, ny - 1)
    free[i, j] = False
    return free


def _walkers(
    lanes: Sequence[tuple[tuple[float, float], tuple[float, float]]],
    count: int,
    rng: np.random.Generator,
) -> tuple[Walker, ...]:
    if not lanes or count <= 0:
        return ()
    picks = rng.choice(len(lanes), size=count, replace=count > len(lanes))
    out = []
    for k in picks:
        a, b = lanes[int(k)]
        length = math.hypot(b[0] - a[0], b[1] - a[1])
        out.append(
            Walker(
                a_xy=a,
                b_xy=b,
                speed_mps=float(rng.uniform(0.7, 1.4)),
                phase_m=float(rng.uniform(0.0, 2.0 * length)),
                body=bool(rng.random() < 0.3),
            )
        )
    return tuple(out)


# --------------------------------------------------------------------------------------------
# Families
# --------------------------------------------------------------------------------------------


def _manhattan(
    seed: int,
    features: Features,
    *,
    style: PathStyle,
    model: LaserModel,
) -> GeneratedWorld:
    """The original generator, unchanged (features can still be switched on)."""
    world = generate_building(seed, "paper")
    trajectory = generate_trajectory(world, seed, spacing_m=PAPER_SPACING_M)
    loop = world.loop_xy_m
    lanes = []
    w = world.corridor_width_m
    for a, b in zip(loop, np.roll(loop, -1, axis=0), strict=True):
        d = b - a
        length = float(np.hypot(*d))
        e = d / length
        n = np.array([-e[1], e[0]]) * (w / 2.0 - 0.35)
        p, q = a + 0.2 * length * e + n, b - 0.2 * length * e + n
        lanes.append(((float(p[0]), float(p[1])), (float(q[0]), float(q[1]))))
    walkers = _walkers(lanes, features.walkers, np.random.default_rng([seed, 1, 0x3A1C]))
    return GeneratedWorld(
        family="manhattan",
        seed=seed,
        world=world,
        glass_m=np.zeros((0, 4)),
        trajectory=trajectory,
        walkers=walkers,
        features=features,
        style=style,
        model=model,
        scan_rate_hz=None,
        speed_mps=0.7,
        info={"size": "paper", "loop_length_m": round(float(trajectory.loop_length_m), 1)},
    )


def _ring(rng: np.random.Generator, features: Features, style: PathStyle) -> _Layout:
    width = float(rng.uniform(120.0, 128.0))
    height = float(rng.uniform(38.0, 44.0))
    w = float(rng.uniform(2.35, 2.45))
    segs: list[Seg] = []
    glass: list[Seg] = []
    # Outer wall: plain all round.
    _wall(segs, 0.0, 0.0, width, 0.0, [])
    _wall(segs, width, 0.0, width, height, [])
    _wall(segs, width, height, 0.0, height, [])
    _wall(segs, 0.0, height, 0.0, 0.0, [])
    # Inner wall: the openings side (south or north) has 0.9 m openings every ~6 m.
    south = bool(rng.random() < 0.5)
    x0, x1 = w, width - w
    gaps = _openings(rng, 3.0, (x1 - x0) - 3.0, 0.9, (5.4, 6.6))
    opening_centres = [round(x0 + (g0 + g1) / 2.0, 3) for g0, g1 in gaps]
    y_open = w if south else height - w
    y_plain = height - w if south else w
    _wall(segs, x0, y_open, x1, y_open, gaps)
    plain_gaps: list[tuple[float, float]] = []
    if features.glass:
        # A stretch of the plain inner wall is glass: the hollow area behind shows through.
        g_len = float(rng.uniform(6.0, 15.0))
        g0 = float(rng.uniform(x0 + 40.0, x1 - 40.0 - g_len))
        plain_gaps.append((g0 - x0, g0 - x0 + g_len))
        glass.append((g0, y_plain, g0 + g_len, y_plain))
    _wall(segs, x0, y_plain, x1, y_plain, plain_gaps)
    _wall(segs, x0, w, x0, height - w, [])
    _wall(segs, x1, w, x1, height - w, [])
    # Large hollow areas behind the openings: cross walls every 15-30 m, clutter boxes inside.
    xs = [x0]
    while x1 - xs[-1] > 34.0:
        xs.append(xs[-1] + float(rng.uniform(15.0, 30.0)))
    xs.append(x1)
    for xc in xs[1:-1]:
        _wall(segs, xc, w, xc, height - w, [])
    for a, b in itertools.pairwise(xs):
        n_boxes = int(rng.integers(4, 12))
        for _ in range(n_boxes):
            cx = float(rng.uniform(a + 1.0, b - 1.0))
            cy = float(rng.uniform(w + 1.0, height - w - 1.0))
            _clutter_box(rng, segs, cx, cy)
    # A few boxes in the long corridors against the outer wall (clear of the path).
    for y_wall, sign in ((0.0, 1.0), (height, -1.0)):
        for _ in range(int(rng.integers(0, 4))):
            cx = float(rng.uniform(x0 + 5.0, x1 - 5.0))
            _clutter_box(rng, segs, cx, y_wall + sign * 0.3, lo=0.2, hi=0.3)
    c = [(w / 2, w / 2), (width - w / 2, w / 2), (width - w / 2, height - w / 2),
         (w / 2, height - w / 2)]  # fmt: skip
    if style.start_featureless:
        # Start at the end of the plain west corridor (~36 m), driving along it.
        route = [c[0], c[3], c[2], c[1]]
        start_frac = 1.0 / (height - w)
    else:
        k = int(rng.integers(4))
        order = c[k:] + c[:k]
        route = order if rng.random() < 0.5 else order[::-1]
        start_frac = float(rng.uniform(0.1, 0.6))
    lanes = []
    for y in (w / 2 - (w / 2 - 0.35), height - w / 2 + (w / 2 - 0.35)):
        lanes.append(((x0 + 10.0, y), (x1 - 10.0, y)))
    for a, b in itertools.pairwise(xs):
        lanes.append(((a + 2.0, height / 2), (b - 2.0, height / 2)))
    return _Layout(
        segments=segs,
        glass=glass,
        route=route,
        start_frac=start_frac,
        corridor_width_m=w,
        walk_lanes=lanes,
        info={
            "width_m": round(width, 3),
            "height_m": round(height, 3),
            "corridor_width_m": round(w, 3),
            "openings_side": "south" if south else "north",
            "opening_width_m": 0.9,
            "opening_centres_x_m": opening_centres,
            "opening_y_m": round(y_open, 3),
            "long_corridor_m": round(x1 - x0, 3),
            "short_corridor_m": round(height - 2 * w, 3),
            "hollow_area_walls_x_m": [round(v, 3) for v in xs],
        },
    )


def _long_corridor(rng: np.random.Generator, features: Features, style: PathStyle) -> _Layout:
    length = float(rng.uniform(125.0, 150.0))
    span = float(rng.uniform(28.0, 40.0))
    w1, w2 = float(rng.uniform(1.8, 3.0)), float(rng.uniform(1.8, 3.0))
    wc = float(rng.uniform(2.0, 2.6))
    segs: list[Seg] = []
    glass: list[Seg] = []
    ox0, ox1, oy0, oy1 = -wc / 2, length + wc / 2, -w1 / 2, span + w2 / 2
    ix0, ix1, iy0, iy1 = wc / 2, length - wc / 2, w1 / 2, span - w2 / 2
    # South corridor: rooms with doors along its inner side for a stretch, alcoves on the
    # outer side elsewhere. North corridor: one plain stretch of >= 45 m, doors elsewhere.
    s_a = float(rng.uniform(10.0, 40.0))
    s_b = s_a + float(rng.uniform(25.0, 45.0))
    door_gaps = [(g0 + s_a, g1 + s_a) for g0, g1 in _openings(rng, 0.0, s_b - s_a, 0.9,
                                                                (4.0, 8.0))]  # fmt: skip
    _wall(segs, ix0, iy0, ix1, iy0, [(g0 - ix0, g1 - ix0) for g0, g1 in door_gaps])
    depth = float(rng.uniform(4.0, 6.0))
    _wall(segs, s_a - 1.0, iy0 + depth, s_b + 1.0, iy0 + depth, [])
    between = [(a[1] + b[0]) / 2.0 for a, b in itertools.pairwise(door_gaps)]
    room_x = [s_a - 1.0, *between, s_b + 1.0]
    for xr in room_x:
        _wall(segs, xr, iy0, xr, iy0 + depth, [])
    for g0, g1 in door_gaps[:: max(1, len(door_gaps) // 3)]:
        _clutter_box(
            rng, segs, (g0 + g1) / 2 + rng.uniform(-1.0, 1.0), iy0 + depth / 2, lo=0.4, hi=0.8
        )
    # Outer south wall: door alcoves (0.9 m wide, 0.2 m deep) in a second stretch.
    a_a = float(rng.uniform(s_b + 10.0, max(s_b + 11.0, length - 45.0)))
    a_b = min(a_a + float(rng.uniform(20.0, 35.0)), length - 5.0)
    alcoves = [(g0 + a_a, g1 + a_a) for g0, g1 in _openings(rng, 0.0, a_b - a_a, 0.9, (5.0, 9.0))]
    _wall(segs, ox0, oy0, ox1, oy0, [(g0 - ox0, g1 - ox0) for g0, g1 in alcoves])
    for g0, g1 in alcoves:
        _wall(segs, g0, oy0, g0, oy0 - 0.2, [])
        _wall(segs, g0, oy0 - 0.2, g1, oy0 - 0.2, [])
        _wall(segs, g1, oy0 - 0.2, g1, oy0, [])
    # North corridor: a plain stretch of 45-70 m from its west end, doors after it.
    plain = float(rng.uniform(45.0, 70.0))
    n_gaps = _openings(rng, plain, length - 10.0, 0.9, (5.0, 10.0))
    _wall(segs, ix0, iy1, ix1, iy1, [(g0 - ix0, g1 - ix0) for g0, g1 in n_gaps])
    for g0, g1 in n_gaps:
        _wall(segs, g0 - 1.5, iy1, g0 - 1.5, iy1 - 4.0, [])
        _wall(segs, g0 - 1.5, iy1 - 4.0, g1 + 1.5, iy1 - 4.0, [])
        _wall(segs, g1 + 1.5, iy1 - 4.0, g1 + 1.5, iy1, [])
    north_gaps: list[tuple[float, float]] = []
    if features.glass:
        g0 = float(rng.uniform(plain + 5.0, max(plain + 6.0, length - 20.0)))
        north_gaps = [(g0 - ox0, g0 - ox0 + 8.0)]
        glass.append((g0, oy1, g0 + 8.0, oy1))
    _wall(segs, ox0, oy1, ox1, oy1, north_gaps)
    _wall(segs, ox0, oy0, ox0, oy1, [])
    _wall(segs, ox1, oy0, ox1, oy1, [])
    _wall(segs, ix0, iy0, ix0, iy1, [])
    _wall(segs, ix1, iy0, ix1, iy1, [])
    # Centre line: corridor centres.
    c = [(0.0, 0.0), (length, 0.0), (length, span), (0.0, span)]
    if style.start_featureless:
        # Start at the west end of the plain north stretch, driving east along it.
        route = [c[3], c[2], c[1], c[0]]
        start_frac = 1.2 / length
    else:
        route = c if rng.random() < 0.5 else c[::-1]
        start_frac = float(rng.uniform(0.1, 0.6))
    lanes = []
    if w1 >= 2.3:
        lanes.append(((20.0, -(w1 / 2 - 0.35)), (length - 20.0, -(w1 / 2 - 0.35))))
    if w2 >= 2.3:
        lanes.append(((20.0, span + (w2 / 2 - 0.35)), (length - 20.0, span + (w2 / 2 - 0.35))))
    return _Layout(
        segments=segs,
        glass=glass,
        route=route,
        start_frac=start_frac,
        corridor_width_m=min(w1, w2, wc),
        walk_lanes=lanes,
        info={
            "long_corridor_m": round(length, 3),
            "widths_m": [round(w1, 3), round(w2, 3), round(wc, 3)],
            "plain_stretch_m": round(plain, 3),
        },
    )


def _office(rng: np.random.Generator, features: Features, style: PathStyle) -> _Layout:
    """Raster-carved floor (0.15 m walls, every coordinate a multiple of 0.05 m)."""
    res = RASTER_RES_M

    def snap(v: float) -> float:
        return round(v / res) * res

    width = snap(float(rng.uniform(108.0, 122.0)))
    height = snap(float(rng.uniform(42.0, 50.0)))
    t = 0.15
    w = snap(float(rng.uniform(1.9, 2.3)))
    plan = _Plan(width, height)
    m = [snap(float(rng.uniform(5.0, 6.0))) for _ in range(4)]
    xl, xr, yb, yt = m[0], width - m[1], m[2], height - m[3]
    xm = snap(xl + (xr - xl) * float(rng.uniform(0.4, 0.6)))
    for rect in ((xl, yb, xr, yb + w), (xl, yt - w, xr, yt), (xl, yb, xl + w, yt),
                 (xr - w, yb, xr, yt), (xm, yb, xm + w, yt)):  # fmt: skip
        plan.rect(*rect, value=True)
    glass: list[Seg] = []
    furniture: list[Seg] = []
    lanes: list[tuple[tuple[float, float], tuple[float, float]]] = []
    doors_open = doors_closed = 0

    def rooms_along(  # noqa: PLR0917 - the row's rectangle, its door wall and side
        a: float, b: float, y0: float, y1: float, door_y: float, facing: int
    ) -> None:
        """A row of rooms between x=a..b, y0..y1, doors in the wall at ``door_y``."""
        nonlocal doors_open, doors_closed
        x = a
        while b - x > 3.0:
            x_end = min(b, snap(x + float(rng.uniform(3.5, 7.0))))
            if b - x_end < 3.0:
                x_end = b
            # One 0.15 m wall between neighbouring rooms, and between room and corridor.
            rx0, rx1 = snap(x + t) if x == a else x, snap(x_end - t)
            ry0, ry1 = snap(y0 + t), snap(y1 - t)
            plan.rect(rx0, ry0, rx1, ry1, value=True)
            dw = 0.9
            d0 = snap(float(rng.uniform(rx0 + 0.3, max(rx0 + 0.35, rx1 - 0.3 - dw))))
            closed = rng.random() < 0.4
            wall_lo, wall_hi = (ry1, ry1 + t) if facing > 0 else (ry0 - t, ry0)
            if features.glass and rng.random() < 0.15:
                plan.rect(rx0, wall_lo, rx1, wall_hi, value=True)  # glass front: invisible
                gy = door_y
                glass.append((rx0, gy, rx1, gy))
            elif closed:
                # The door panel sits at the room side; the corridor side shows a 0.10 m recess.
                if facing > 0:
                    plan.rect(d0, ry1 + 0.05, d0 + dw, ry1 + t + res, value=True)
                else:
                    plan.rect(d0, ry0 - t - res, d0 + dw, ry0 - 0.05, value=True)
                doors_closed += 1
            else:
                plan.rect(d0, wall_lo - res, d0 + dw, wall_hi + res, value=True)
                doors_open += 1
            # Door jambs: 0.05 m frames standing out into the corridor either side of the door.
            jy0, jy1 = (ry1 + t, ry1 + t + 0.05) if facing > 0 else (ry0 - t - 0.05, ry0 - t)
            plan.rect(d0 - 0.1, jy0, d0, jy1, value=False)
            plan.rect(d0 + dw, jy0, d0 + dw + 0.1, jy1, value=False)
            # Furniture: a desk, a chair, a shelf along the back wall.
            if rx1 - rx0 > 2.5 and ry1 - ry0 > 2.5:
                cx = float(rng.uniform(rx0 + 1.0, rx1 - 1.0))
                cy = float(rng.uniform(ry0 + 1.0, ry1 - 1.0))
                _box(furniture, cx, cy, rng.uniform(1.2, 1.6), rng.uniform(0.6, 0.8),
                     float(rng.choice([0.0, math.pi / 2])))  # fmt: skip
                _box(furniture, cx + rng.uniform(-0.6, 0.6), cy + 0.75, 0.45, 0.45,
                     rng.uniform(0.0, math.pi))  # fmt: skip
                back = ry0 + 0.25 if facing > 0 else ry1 - 0.25
                _box(furniture, (rx0 + rx1) / 2, back, min(1.8, rx1 - rx0 - 0.4), 0.4, 0.0)
            x = x_end

    # Rooms: outer strips facing the ring, inner blocks (two rows) facing the long corridors.
    rooms_along(xl, xr, 0.0, yb, yb, +1)
    rooms_along(xl, xr, yt, height, yt, -1)
    # Inner blocks: a row of rooms on each long corridor, a solid core between them.
    depth = snap(min(7.0, (yt - yb - 2 * w) / 2.0 - 1.0))
    for a, b in ((xl + w, xm), (xm + w, xr - w)):
        rooms_along(a, b, yb + w, yb + w + depth, yb + w, -1)
        rooms_along(a, b, yt - w - depth, yt - w, yt - w, +1)
    segs = [tuple(map(float, s)) for s in plan.segments()]
    segs_all: list[Seg] = [(s[0], s[1], s[2], s[3]) for s in segs] + furniture
    cx_l, cx_r, cx_m = xl + w / 2, xr - w / 2, xm + w / 2
    cy_b, cy_t = yb + w / 2, yt - w / 2
    # A figure of eight: the middle corridor is driven twice, northwards.
    route = [(cx_m, cy_b), (cx_m, cy_t), (cx_l, cy_t), (cx_l, cy_b), (cx_m, cy_b),
             (cx_m, cy_t), (cx_r, cy_t), (cx_r, cy_b)]  # fmt: skip
    if rng.random() < 0.5:
        route = route[::-1]  # the middle corridor southwards, twice
    k = int(rng.integers(len(route)))
    route = route[k:] + route[:k]
    # People walk along the corridor walls (0.3 m from them: clear of the weaving robot).
    off = w / 2 - 0.3
    lanes += [((xl + 5.0, cy_b - off), (xr - 5.0, cy_b - off)),
              ((xl + 5.0, cy_t + off), (xr - 5.0, cy_t + off)),
              ((cx_m + off, cy_b + 4.0), (cx_m + off, cy_t - 4.0))]  # fmt: skip
    return _Layout(
        segments=segs_all,
        glass=glass,
        route=route,
        start_frac=float(rng.uniform(0.2, 0.6)),
        corridor_width_m=w,
        walk_lanes=lanes,
        info={
            "wall_thickness_m": t,
            "corridor_width_m": round(w, 3),
            "doors_open": doors_open,
            "doors_closed": doors_closed,
            "size_m": [round(width, 2), round(height, 2)],
        },
    )


def _hall(rng: np.random.Generator, features: Features, style: PathStyle) -> _Layout:
    delta = float(rng.uniform(5.0, 6.5))  # lane spacing; pillar rows between lanes
    w = float(rng.uniform(2.2, 2.8))
    gap = float(rng.uniform(20.0, 32.0))
    widths = [float(rng.uniform(36.0, 46.0)), float(rng.uniform(36.0, 46.0))]
    margins = [(float(rng.uniform(4.0, 7.0)), float(rng.uniform(4.0, 7.0))) for _ in range(2)]
    lanes_y = [k * delta for k in range(4)]
    segs: list[Seg] = []
    glass: list[Seg] = []
    walk: list[tuple[tuple[float, float], tuple[float, float]]] = []
    xa0, xa1 = 0.0, widths[0]
    xb0, xb1 = widths[0] + gap, widths[0] + gap + widths[1]
    halls = [(xa0, xa1, -margins[0][0], lanes_y[3] + margins[0][1]),
             (xb0, xb1, -margins[1][0], lanes_y[3] + margins[1][1])]  # fmt: skip
    doors = [(lanes_y[0] - w / 2, lanes_y[0] + w / 2), (lanes_y[3] - w / 2, lanes_y[3] + w / 2)]
    curved_east = True
    for hi, (x0, x1, y0, y1) in enumerate(halls):
        _wall(segs, x0, y0, x1, y0, [])
        _wall(segs, x1, y1, x0, y1, [])
        side_gaps = [(d0 - y0, d1 - y0) for d0, d1 in doors]
        if hi == 0:
            _wall(segs, x0, y0, x0, y1, [])
            _wall(segs, x1, y0, x1, y1, side_gaps)
        else:
            _wall(segs, x0, y0, x0, y1, side_gaps)
            # The far wall of the second hall is curved (bulging outwards 3-6 m).
            bulge = float(rng.uniform(3.0, 6.0))
            half = (y1 - y0) / 2.0
            radius = (half**2 + bulge**2) / (2.0 * bulge)
            cx, cy = x1 + bulge - radius, (y0 + y1) / 2.0
            phi = math.asin(half / radius)
            _arc(segs, cx, cy, radius, -phi, phi, 24)
        # Pillars between the lanes, clutter around them.
        pillar_x = np.arange(x0 + 6.0 + rng.uniform(0.0, 2.0), x1 - 5.0, rng.uniform(5.0, 8.0))
        for k in range(3):
            py = lanes_y[k] + delta / 2.0
            for px in pillar_x:
                if rng.random() < 0.5:
                    s = float(rng.uniform(0.4, 0.7))
                    _box(segs, float(px), py, s, s, 0.0)
                else:
                    _circle(segs, float(px), py, float(rng.uniform(0.2, 0.35)))
                if rng.random() < 0.3:
                    bx = min(max(float(px) + rng.uniform(-1.5, 1.5), x0 + 5.0), x1 - 5.0)
                    _clutter_box(rng, segs, bx, py + rng.uniform(-0.8, 0.8))
            walk.append(
                ((x0 + 4.5, lanes_y[k] + delta / 4.0), (x1 - 4.5, lanes_y[k] + delta / 4.0))
            )
        for y_edge, sign in ((y0, 1.0), (y1, -1.0)):
            for _ in range(int(rng.integers(3, 8))):
                bx = float(rng.uniform(x0 + 2.0, x1 - 2.0))
                by = y_edge + sign * float(rng.uniform(0.4, 1.5))
                _clutter_box(rng, segs, bx, by, lo=0.3, hi=0.8)
    # Two corridors joining the halls (glass on one wall of one of them, when switched on).
    for k, (d0, d1) in enumerate(doors):
        _wall(segs, xa1, d0, xb0, d0, [])
        if features.glass and k == 1:
            g_len = min(10.0, gap - 6.0)
            g0 = xa1 + (gap - g_len) / 2
            _wall(segs, xa1, d1, xb0, d1, [(g0 - xa1, g0 - xa1 + g_len)])
            glass.append((g0, d1, g0 + g_len, d1))
        else:
            _wall(segs, xa1, d1, xb0, d1, [])
    # Lanes: hall B bottom to top, hall A top to bottom (4 lanes each).
    ea, wa = xa1 - 3.0, xa0 + 3.0
    eb, wb = xb1 - 3.0, xb0 + 3.0
    l0, l1, l2, l3 = lanes_y
    route = [
        (eb, l0), (eb, l1), (wb, l1), (wb, l2), (eb, l2), (eb, l3),
        (wa, l3), (wa, l2), (ea, l2), (ea, l1), (wa, l1), (wa, l0),
    ]  # fmt: skip
    if rng.random() < 0.5:
        route = route[::-1]
    k = int(rng.integers(len(route)))
    route = route[k:] + route[:k]
    return _Layout(
        segments=segs,
        glass=glass,
        route=route,
        start_frac=float(rng.uniform(0.2, 0.6)),
        corridor_width_m=w,
        walk_lanes=walk,
        info={
            "hall_widths_m": [round(v, 2) for v in widths],
            "lane_spacing_m": round(delta, 3),
            "corridor_gap_m": round(gap, 2),
            "curved_wall": curved_east,
        },
    )


def _block(  # noqa: PLR0917 - a rectangle and its corridor width
    rng: np.random.Generator,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    w: float,
    outer_gaps: dict[str, list[tuple[float, float]]],
    skip_outer: frozenset[str] = frozenset(),
) -> list[Seg]:
    """A rectangular corridor ring (thin walls) with rooms along its inner side."""
    segs: list[Seg] = []
    sides = {
        "S": (x0, y0, x1, y0),
        "E": (x1, y0, x1, y1),
        "N": (x1, y1, x0, y1),
        "W": (x0, y1, x0, y0),
    }
    for name, (a, b, c, d) in sides.items():
        if name not in skip_outer:
            _wall(segs, a, b, c, d, outer_gaps.get(name, []))
    ix0, iy0, ix1, iy1 = x0 + w, y0 + w, x1 - w, y1 - w
    depth = min(5.0, (iy1 - iy0) / 2.0 - 1.0, (ix1 - ix0) / 2.0 - 1.0)
    inner = {
        "S": (ix0, iy0, ix1, iy0),
        "E": (ix1, iy0, ix1, iy1),
        "N": (ix1, iy1, ix0, iy1),
        "W": (ix0, iy1, ix0, iy0),
    }
    for a, b, c, d in inner.values():
        length = math.hypot(c - a, d - b)
        gaps = [g for g in _openings(rng, depth + 0.5, length - depth - 0.5, 0.9, (5.0, 10.0))
                if rng.random() < 0.6]  # fmt: skip
        _wall(segs, a, b, c, d, gaps)
        # Room back wall and cross walls between the doors.
        ex, ey = (c - a) / length, (d - b) / length
        nx, ny = -ey, ex  # points inwards (the ring runs counter-clockwise)
        _wall(segs, a + depth * (ex + nx), b + depth * (ey + ny),
              c + depth * (-ex + nx), d + depth * (-ey + ny), [])  # fmt: skip
        cuts = [depth] + [(g0 + g1) / 2.0 + float(rng.choice([-1.5, 1.5])) for g0, g1 in gaps]
        for s in cuts:
            _wall(segs, a + s * ex, b + s * ey, a + s * ex + depth * nx, b + s * ey + depth * ny,
                  [])  # fmt: skip
    return segs


def _wing(rng: np.random.Generator, features: Features, style: PathStyle) -> _Layout:
    angle_deg = float(rng.uniform(15.0, 60.0))
    alpha = math.radians(angle_deg)
    w = float(rng.uniform(2.2, 2.6))
    wm, hm = float(rng.uniform(70.0, 85.0)), float(rng.uniform(30.0, 38.0))
    wu, hv = float(rng.uniform(35.0, 45.0)), float(rng.uniform(16.0, 22.0))
    yc = float(rng.uniform(w + 5.0, hm / 2.0))
    lc = max(float(rng.uniform(8.0, 14.0)), (hv / 2.0) * math.tan(alpha) + 4.0)
    half_gap = w / (2.0 * math.cos(alpha))
    curved = bool(rng.random() < 0.5)
    segs = _block(
        rng, 0.0, 0.0, wm, hm, w,
        {"E": [(yc - half_gap, yc + half_gap)]},
        skip_outer=frozenset({"W"}) if curved else frozenset(),
    )  # fmt: skip
    glass: list[Seg] = []
    if curved:
        # A rotunda: the west outer wall bulges out 3-5 m (a curved wall along the path).
        bulge = float(rng.uniform(3.0, 5.0))
        half = hm / 2.0
        radius = (half**2 + bulge**2) / (2.0 * bulge)
        phi = math.asin(half / radius)
        _arc(segs, radius - bulge, hm / 2.0, radius, math.pi - phi, math.pi + phi, 28)
    # The wing in its own frame (u along the connector, v across), then placed.
    wing_local = _block(
        rng, 0.0, -hv / 2.0, wu, hv / 2.0, w, {"W": [(hv / 2 - w / 2, hv / 2 + w / 2)]}
    )
    ex, ey = math.cos(alpha), math.sin(alpha)
    origin = (wm + lc * ex, yc + lc * ey)
    segs += _transform(wing_local, origin, alpha)
    nx, ny = -ey, ex
    # Connector walls (v = -w/2 and v = +w/2), from the main block's east wall to the wing.
    for v in (-w / 2.0, w / 2.0):
        t0 = v * math.tan(alpha)
        p = (wm + t0 * ex + v * nx, yc + t0 * ey + v * ny)
        q = (wm + lc * ex + v * nx, yc + lc * ey + v * ny)
        if features.glass and v > 0:
            length = math.hypot(q[0] - p[0], q[1] - p[1])
            g0, g1 = length * 0.3, length * 0.3 + min(4.0, length * 0.4)
            _wall(segs, p[0], p[1], q[0], q[1], [(g0, g1)])
            glass.append((p[0] + g0 * ex, p[1] + g0 * ey, p[0] + g1 * ex, p[1] + g1 * ey))
        else:
            _wall(segs, p[0], p[1], q[0], q[1], [])
    c0, c1 = (w / 2, w / 2), (wm - w / 2, w / 2)
    c2, c3 = (wm - w / 2, hm - w / 2), (w / 2, hm - w / 2)
    junction = (wm - w / 2, yc - (w / 2) * math.tan(alpha))

    def wing_pt(u: float, v: float) -> tuple[float, float]:
        return (origin[0] + u * ex + v * nx, origin[1] + u * ey + v * ny)

    w0 = wing_pt(w / 2, 0.0)
    wing_loop = [wing_pt(w / 2, -hv / 2 + w / 2), wing_pt(wu - w / 2, -hv / 2 + w / 2),
                 wing_pt(wu - w / 2, hv / 2 - w / 2), wing_pt(w / 2, hv / 2 - w / 2)]  # fmt: skip
    route = [c0, c1, junction, w0, *wing_loop, w0, junction, c2, c3]
    lanes = [((w + 6.0, w / 2 - (w / 2 - 0.35)), (wm - w - 6.0, w / 2 - (w / 2 - 0.35))),
             ((w + 6.0, hm - 0.35), (wm - w - 6.0, hm - 0.35))]  # fmt: skip
    return _Layout(
        segments=segs,
        glass=glass,
        route=route,
        start_frac=float(rng.uniform(0.2, 0.6)),
        corridor_width_m=w,
        walk_lanes=lanes,
        info={
            "wing_angle_deg": round(angle_deg, 3),
            "connector_m": round(lc, 2),
            "curved_wall": curved,
            "main_block_m": [round(wm, 2), round(hm, 2)],
            "wing_m": [round(wu, 2), round(hv, 2)],
            # Route corners 3..8 lie in the wing (the path between them is in its frame).
            "wing_route_corners": [3, 8],
        },
    )


# --------------------------------------------------------------------------------------------
# Driving a route
# --------------------------------------------------------------------------------------------


_SHARP_TURN_RAD: Final = math.radians(100.0)


def _drive(
    route: FloatArray,
    start_frac: float,
    style: PathStyle,
    *,
    rate_hz: float | None,
    speed_mps: float,
    rng: np.random.Generator,
    turn_radius_m: float = 1.0,
    spin_rate_deg_s: float = 45.0,
    start_ns: int = 1_700_000_000_000_000_000,
    spin_corners: frozenset[int] = frozenset(),
) -> Trajectory:
    """Drive the closed ``route`` from a point on its first leg back to that point.

    Corners turn on a circular arc of ``turn_radius_m`` (smaller where the legs are short),
    sharp ones (> 100 deg) in place. Weave, wobble, stops and spins follow ``style``.
    """
    pts = np.asarray(route, dtype=np.float64)
    k = pts.shape[0]
    start = pts[0] + start_frac * (pts[1 % k] - pts[0])
    seq = np.vstack((start, pts[1:], pts[:1], start))
    # Primitives: ("line", p, h, L) / ("arc", p, h0, kappa, L) / ("spin", p, h0, dth) /
    # ("stop", p, h, duration_s).
    prims: list[tuple[Any, ...]] = []
    legs = np.diff(seq, axis=0)
    lens = np.hypot(legs[:, 0], legs[:, 1])
    heads = np.arctan2(legs[:, 1], legs[:, 0])
    n_legs = legs.shape[0]
    taus = np.zeros(n_legs + 1)
    kinds = ["none"] * (n_legs + 1)
    turns = np.zeros(n_legs + 1)
    for i in range(1, n_legs):
        turn = float(_wrap(np.array([heads[i] - heads[i - 1]]))[0])
        turns[i] = turn
        if abs(turn) < 1e-9:
            continue
        if abs(turn) > _SHARP_TURN_RAD or i in spin_corners:
            kinds[i] = "spin"
        else:
            tau = turn_radius_m * math.tan(abs(turn) / 2.0)
            taus[i] = min(tau, 0.45 * lens[i - 1], 0.45 * lens[i])
            kinds[i] = "arc"
    for i in range(n_legs):
        p = seq[i] + taus[i] * np.array([math.cos(heads[i]), math.sin(heads[i])])
        length = lens[i] - taus[i] - taus[i + 1]
        prims.append(("line", p, float(heads[i]), float(length)))
        j = i + 1
        if j < n_legs and kinds[j] == "arc":
            r = taus[j] / math.tan(abs(turns[j]) / 2.0)
            a = seq[j] - taus[j] * np.array([math.cos(heads[i]), math.sin(heads[i])])
            prims.append(("arc", a, float(heads[i]), math.copysign(1.0 / r, turns[j]),
                          float(r * abs(turns[j]))))  # fmt: skip
        elif j < n_legs and kinds[j] == "spin":
            prims.append(("spin", seq[j], float(heads[i]), float(turns[j])))
    prims = _insert_events(prims, style, rng)

    # Dense samples.
    xs: list[FloatArray] = []
    ys: list[FloatArray] = []
    hp: list[FloatArray] = []  # path heading (travel direction)
    hr: list[FloatArray] = []  # robot heading before weave and wobble
    ss: list[FloatArray] = []  # travelled distance along the centre path
    ts: list[FloatArray] = []
    drive: list[FloatArray] = []
    s_now, t_now = 0.0, 0.0
    spin_s: list[float] = []
    omega = math.radians(spin_rate_deg_s)
    for prim in prims:
        kind = prim[0]
        if kind in ("line", "arc"):
            length = prim[4] if kind == "arc" else prim[3]
            n = max(1, math.ceil(length / _DENSE_STEP_M))
            ds = np.linspace(0.0, length, n + 1)[1:]
            p, h0 = prim[1], prim[2]
            if kind == "line":
                x = p[0] + ds * math.cos(h0)
                y = p[1] + ds * math.sin(h0)
                h = np.full(n, h0)
            else:
                kappa = prim[3]
                h = h0 + kappa * ds
                x = p[0] + (np.sin(h) - math.sin(h0)) / kappa
                y = p[1] - (np.cos(h) - math.cos(h0)) / kappa
            xs.append(x)
            ys.append(y)
            hp.append(h)
            hr.append(h)
            ss.append(s_now + ds)
            ts.append(t_now + ds / speed_mps)
            drive.append(np.ones(n, dtype=bool))
            s_now += length
            t_now += length / speed_mps
        elif kind == "spin":
            p, h0, dth = prim[1], prim[2], prim[3]
            n = max(1, math.ceil(abs(dth) / math.radians(0.5)))
            frac = np.linspace(0.0, 1.0, n + 1)[1:]
            xs.append(np.full(n, p[0]))
            ys.append(np.full(n, p[1]))
            hp.append(np.where(frac < 1.0, h0, h0 + dth))
            hr.append(h0 + frac * dth)
            ss.append(np.full(n, s_now))
            ts.append(t_now + frac * abs(dth) / omega)
            drive.append(np.zeros(n, dtype=bool))
            t_now += abs(dth) / omega
            spin_s.append(s_now)
        else:  # stop
            p, h0, dur = prim[1], prim[2], prim[3]
            n = max(1, math.ceil(dur / 0.05))
            frac = np.linspace(0.0, 1.0, n + 1)[1:]
            xs.append(np.full(n, p[0]))
            ys.append(np.full(n, p[1]))
            hp.append(np.full(n, h0))
            hr.append(np.full(n, h0))
            ss.append(np.full(n, s_now))
            ts.append(t_now + frac * dur)
            drive.append(np.zeros(n, dtype=bool))
            t_now += dur
    p0 = prims[0][1]
    x = np.concatenate([[p0[0]], *xs])
    y = np.concatenate([[p0[1]], *ys])
    h_path = np.concatenate([[prims[0][2]], *hp])
    h_rob = np.concatenate([[prims[0][2]], *hr])
    s = np.concatenate([[0.0], *ss])
    t = np.concatenate([[0.0], *ts])
    moving = np.concatenate([[False], *drive])
    total_s = s_now

    # Lateral weave: smoothed noise along s, zero at the start/end and at turns in place.
    offset, slope = _weave(s, total_s, spin_s, style, rng)
    x = x - offset * np.sin(h_path)
    y = y + offset * np.cos(h_path)
    follow = np.where(moving, np.arctan(slope), 0.0) if style.heading_follows_weave else 0.0
    theta = h_rob + follow

    # Scan times.
    if rate_hz is None:
        idx = _paper_samples(x, y, theta, t)
        t_scan = t[idx]
        poses = np.column_stack((x[idx], y[idx], _wrap(theta[idx])))
    else:
        period = 1.0 / rate_hz
        n_scans = math.ceil(t[-1] / period - 1e-9) + 1
        t_scan = np.arange(n_scans) * period
        t_ext = np.append(t, t_scan[-1] + 1.0)  # standing at the end until the last scan
        unwrapped = np.unwrap(theta)

        def at(v: FloatArray) -> FloatArray:
            return np.asarray(np.interp(t_scan, t_ext, np.append(v, v[-1])), dtype=np.float64)

        poses = np.column_stack((at(x), at(y), _wrap(at(unwrapped))))
    # Heading wobble: AR(1) in time, correlated over ~0.3 s (nearly independent between the
    # paper setting's scans, smooth at 40 Hz); none on the first and last scan.
    if style.wobble_deg > 0 and poses.shape[0] > 2:
        white = np.asarray(rng.normal(0.0, math.radians(style.wobble_deg), poses.shape[0]))
        a = np.asarray(np.exp(-np.diff(t_scan, prepend=t_scan[0]) / 0.3), dtype=np.float64)
        wob = np.zeros(poses.shape[0])
        for i in range(1, poses.shape[0]):
            wob[i] = a[i] * wob[i - 1] + math.sqrt(1.0 - a[i] ** 2) * white[i]
        wob[0] = wob[-1] = 0.0
        poses[:, 2] = _wrap(poses[:, 2] + wob)
    # The route closes: the last pose is the first (up to the weave's sampling, < 1 mm).
    poses[-1] = poses[0]
    stamps = start_ns + np.rint(t_scan * 1e9).astype(np.int64)
    travelled = float(np.hypot(np.diff(x), np.diff(y)).sum())
    return Trajectory(
        stamps_ns=stamps,
        poses=np.ascontiguousarray(poses),
        loop_length_m=travelled,
        path_length_m=travelled,
    )


def _insert_events(
    prims: list[tuple[Any, ...]], style: PathStyle, rng: np.random.Generator
) -> list[tuple[Any, ...]]:
    """Split long straights to insert the style's stops and 360 deg turns in place."""
    events = ["stop"] * style.stops + ["spin"] * style.spins
    rng.shuffle(events)
    out = list(prims)
    for event in events:
        long_lines = [i for i, p in enumerate(out) if p[0] == "line" and p[3] > 8.0]
        if not long_lines:
            break
        i = int(long_lines[int(rng.integers(len(long_lines)))])
        _, p, h, length = out[i]
        cut = float(rng.uniform(3.0, length - 3.0))
        q = p + cut * np.array([math.cos(h), math.sin(h)])
        if event == "stop":
            mid: tuple[Any, ...] = ("stop", q, h, float(rng.uniform(2.0, 6.0)))
        else:
            mid = ("spin", q, h, float(rng.choice([-1.0, 1.0])) * 2.0 * math.pi)
        out[i : i + 1] = [("line", p, h, cut), mid, ("line", q, h, length - cut)]
    return out


def _weave(
    s: FloatArray, total_s: float, spin_s: Sequence[float], style: PathStyle,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """Lateral offset (m) and its slope d offset / d s at the dense samples' ``s``."""
    if style.weave_std_m <= 0 or total_s <= 0:
        return np.zeros_like(s), np.zeros_like(s)
    step = 0.05
    grid = np.arange(0.0, total_s + step, step)
    white = rng.normal(0.0, 1.0, grid.shape[0] + 200)
    sigma = style.weave_corr_m / step
    half = int(4 * sigma) + 1
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    smooth = np.convolve(white, kernel, mode="same")[100 : 100 + grid.shape[0]]
    smooth *= style.weave_std_m / max(float(smooth.std()), 1e-12)
    # Keep clear of walls and clutter: at most 2.3 std (0.35 m at the ring's 0.15 m).
    limit = 2.3 * style.weave_std_m
    smooth = limit * np.tanh(smooth / limit)
    ramp = 1.5
    env = np.clip(np.minimum(grid, total_s - grid) / ramp, 0.0, 1.0)
    for sp in spin_s:
        env = np.minimum(env, np.clip((np.abs(grid - sp) - 0.3) / ramp, 0.0, 1.0))
    env = 0.5 - 0.5 * np.cos(math.pi * env)
    off_grid = smooth * env
    slope_grid = np.gradient(off_grid, step)
    return np.interp(s, grid, off_grid), np.interp(s, grid, slope_grid)


def _paper_samples(x: FloatArray, y: FloatArray, theta: FloatArray, t: FloatArray) -> FloatArray:
    """Indices of the paper's scans: every 0.3 m or 10 deg, every 1 s standing still; the
    last sample (the start pose again) always."""
    rot = math.radians(PAPER_ROTATION_DEG)
    xs, ys, ths, tl = x.tolist(), y.tolist(), theta.tolist(), t.tolist()
    keep = [0]
    lx, ly, lth, lt = xs[0], ys[0], ths[0], tl[0]
    for i in range(1, len(xs)):
        dth = abs((ths[i] - lth + math.pi) % (2.0 * math.pi) - math.pi)
        if (
            math.hypot(xs[i] - lx, ys[i] - ly) >= PAPER_SPACING_M
            or dth >= rot
            or tl[i] - lt >= _STILL_PERIOD_S
        ):
            keep.append(i)
            lx, ly, lth, lt = xs[i], ys[i], ths[i], tl[i]
    last = len(xs) - 1
    if keep[-1] != last:
        near = math.hypot(xs[last] - lx, ys[last] - ly) < PAPER_SPACING_M * 0.25
        if near and len(keep) > 1 and tl[last] - tl[keep[-2]] < _STILL_PERIOD_S * 1.5:
            keep[-1] = last
        else:
            keep.append(last)
    return np.asarray(keep, dtype=np.int64)


def with_features(gw: GeneratedWorld, **changes: Any) -> GeneratedWorld:
    """The same world and path with other features (``walkers``, ``glass``, ``blocker_prob``).

    Walkers and glass change the geometry, so the world is generated again with them.
    """
    features = replace(gw.features, **changes)
    return generate(
        gw.family,
        gw.seed,
        features=features,
        style=gw.style,
        scan_rate_hz=gw.scan_rate_hz,
        speed_mps=gw.speed_mps,
        model=gw.model,
    )
