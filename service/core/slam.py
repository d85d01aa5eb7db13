"""One session's SLAM: the front end tracks every scan, the back end closes loops over nodes.

    scan ─▶ front end (`make_frontend`) ─▶ pose + covariance, published at once
                 │ keyframe
                 ▼
            node ─▶ submaps (frozen local point fields)
                 │                └──────▶ loop search (every few nodes, older submaps)
                 ▼                                   │ verified closure
            pose graph (gtsam iSAM2) ◀────────────────┘
                 │
                 ▼ optimised nodes ─▶ every scan corrected by its latest node's correction
                                    └──▶ map: chunks of drawn scans, each moved by its anchor's

`SlamSession` is one session's core, offline and live: front end, back end and map (which scans
are drawn, into which chunk: `maps.composed`). `mapping-service map` and the live service both
run it; the live service runs its back half (`integrate`) in a background thread.
`SlamSession.process` never waits for anything but its own scan's front end and, on a keyframe,
one bounded loop search. `finish` runs the final batch optimisation.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final, Literal, NamedTuple, Protocol

import numpy as np

from clients.wire import PoseFlag
from service.core.backend.loops import LoopParams, LoopResult, verify, window_m
from service.core.backend.params import GraphParams, rotate_covariance
from service.core.frontend.paper import PaperFrontEnd
from service.core.frontend.scan_matcher import MatcherParams, ScanMatcherFrontEnd
from service.core.maps.composed import ChunkedMap
from service.core.maps.grid import GridImage, OccupancyGrid
from service.core.maps.submaps import Submap, SubmapBuilder, SubmapParams
from service.core.types import FloatArray, LaserScan, Pose2D, PoseEstimate, frozen_array

if TYPE_CHECKING:
    from service.core.backend.graph import PoseGraph

# The map rule: every keyframe, and a scan at least this long (scan time) after the last one
# drawn, so slow motion still paints free space (0: keyframes only). In time, not in scans: a
# 40 Hz laser would otherwise draw eight times as often as a 5 Hz one, for the same map.
DEFAULT_DRAW_PERIOD_S: Final = 1.0

_NOT_ANCHORED = PoseFlag.DEGENERATE | PoseFlag.NON_MANHATTAN | PoseFlag.NO_DOMINANT_WALL


@dataclass(frozen=True, slots=True)
class SlamParams:
    loop_closure: bool = True  # False: the front end alone (today's tracker)
    heading_priors: bool = True  # the walls' absolute heading as a unary factor per node
    heading_prior_sigma_deg: float = 0.3  # its σ (the front end's anchored heading)
    max_query_range_m: float = 30.0  # a node's points beyond this are not kept
    update_every_nodes: int = 5  # iSAM2 steps this often (and after every closure)
    graph: GraphParams = field(default_factory=GraphParams)
    submaps: SubmapParams = field(default_factory=SubmapParams)
    loops: LoopParams = field(default_factory=LoopParams)


@dataclass(slots=True)
class LoopStats:
    accepted: int = 0
    rejected: dict[str, int] = field(default_factory=dict)  # reason -> count
    search_s: float = 0.0  # loop search
    optimise_s: float = 0.0  # iSAM2 and the final batch
    total_s: float = 0.0  # all of the back end: nodes, submaps, search, optimisation
    solver_restarts: int = 0  # iSAM2 rebuilt after a failed update (`PoseGraph.update`)
    closures: list[LoopResult] = field(default_factory=list)  # the accepted ones
    # The latest refused searches, for the live graph endpoint (bounded: Intel has ~1,600).
    recent_rejected: deque[LoopResult] = field(default_factory=lambda: deque(maxlen=256))


class _SubmapNodeIndex:
    """Every finished submap's node positions (anchor frames), in one array, so that a query's
    distance to all of them is one vectorised pass. A cache: never saved, rebuilt on demand.

    Submaps finish in the order they start (each holds a fixed number of nodes), so the
    finished ones are a prefix of the builder's list: `indexed` of them are in here.
    """

    def __init__(self) -> None:
        self.indexed = 0
        self.sub_index: list[int] = []  # per segment: its submap
        self.anchor_node: list[int] = []
        self.last_node = np.zeros(0, dtype=np.int64)
        self.starts = np.zeros(0, dtype=np.int64)  # per segment: its first row in `xy_m`
        self.lengths = np.zeros(0, dtype=np.int64)
        self.xy_m = np.zeros((0, 2))

    def extend(self, submaps: Sequence[Submap]) -> None:
        new = []
        while self.indexed < len(submaps) and submaps[self.indexed].finished:
            new.append(submaps[self.indexed])
            self.indexed += 1
        new = [sub for sub in new if sub.node_xy_m]  # (a submap without nodes is never near)
        if not new:
            return
        self.sub_index += [sub.index for sub in new]
        self.anchor_node += [sub.anchor_node for sub in new]
        self.last_node = np.concatenate([self.last_node, [sub.nodes[-1] for sub in new]])
        self.lengths = np.concatenate([self.lengths, [len(sub.node_xy_m) for sub in new]])
        self.starts = np.concatenate([[0], np.cumsum(self.lengths)[:-1]]).astype(np.int64)
        self.xy_m = np.concatenate([self.xy_m, *(np.asarray(sub.node_xy_m) for sub in new)])


class SlamBackend:
    """The back end alone: nodes, submaps, loop search, pose graph (pure computation, no IO).

    `SlamSession` drives it from the same thread as the front end (offline); the live service
    drives it from a background thread (`service.app.backend`), fed with the front end's
    keyframes. The map is the session's (`SlamSession`), not the back end's.
    """

    def __init__(self, params: SlamParams | None = None):
        self.params = params if params is not None else SlamParams()
        self._graph: PoseGraph | None = None  # made on first use (`graph`)
        self.submaps = SubmapBuilder(self.params.submaps)
        self.stats = LoopStats()
        self.node_frontend: list[Pose2D] = []  # each node's front-end pose
        self.node_points: list[FloatArray] = []  # each node's kept scan points, laser frame
        self.node_seq: list[int] = []  # each node's pose sequence (-1: unknown)
        self._chain_xy: list[FloatArray] = []  # prefix sums of sequential xy covariances (map)
        self._last_closure_node = -1
        self._optimised: list[Pose2D] | None = None
        self._near = _SubmapNodeIndex()

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        del state["_near"]  # a cache of the submaps
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._near = _SubmapNodeIndex()

    @property
    def graph(self) -> PoseGraph:
        """The pose graph, made at the first node: gtsam is imported then, so a session
        without loop closure (no node ever) never imports it."""
        if self._graph is None:
            from service.core.backend.graph import PoseGraph  # noqa: PLC0415  # gtsam

            self._graph = PoseGraph(self.params.graph)
        return self._graph

    @property
    def node_count(self) -> int:
        return len(self.node_frontend)

    def add_node(
        self,
        scan: LaserScan,
        pose: Pose2D,
        covariance: Sequence[float],
        flags: int,
        seq: int = -1,
    ) -> bool:
        """A keyframe becomes a node; True when a loop closure was accepted at it."""
        t0 = time.perf_counter()
        accepted = self.stats.accepted
        self._optimised = None
        cov_map = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
        if self.node_frontend:
            prev = self.node_frontend[-1]
            guess = self.graph.estimate(len(self.node_frontend) - 1).compose(prev.between(pose))
        else:
            guess = pose
        node = self.graph.add_node(guess)
        if node > 0:
            prev = self.node_frontend[-1]
            self.graph.add_sequential(
                node - 1, node, prev.between(pose), rotate_covariance(cov_map, prev.theta_rad)
            )
            self._chain_xy.append(self._chain_xy[-1] + cov_map[:2, :2])
        else:
            self._chain_xy.append(np.zeros((2, 2)))
        if self.params.heading_priors and not PoseFlag(flags) & _NOT_ANCHORED:
            self.graph.add_heading_prior(
                node, pose.theta_rad, math.radians(self.params.heading_prior_sigma_deg)
            )
        pts = scan.points_xy_m()
        pts = pts[np.hypot(pts[:, 0], pts[:, 1]) <= self.params.max_query_range_m]
        kept = frozen_array(self.submaps.node_points(pts))  # kept as it is for good
        self.node_frontend.append(pose)
        self.node_points.append(kept)
        self.node_seq.append(seq)
        self.submaps.add_node(node, pose, kept, scan)
        if node % self.params.update_every_nodes == 0:
            t1 = time.perf_counter()
            self.graph.update()
            self.stats.optimise_s += time.perf_counter() - t1
        if node % self.params.loops.search_every_nodes == 0:
            self._timed_search(node)
        self.stats.total_s += time.perf_counter() - t0
        self.stats.solver_restarts = self.graph.isam_restarts
        return self.stats.accepted > accepted

    # ------------------------------------------------------------------ loop search
    def _timed_search(self, query: int) -> None:
        t0 = time.perf_counter()
        self._search(query)
        self.stats.search_s += time.perf_counter() - t0

    def _chain_cov(self, a: int, b: int) -> FloatArray:
        """Uncertainty of b relative to a (map axes): the chain, or since the latest closure."""
        full = self._chain_xy[b] - self._chain_xy[a]
        c = self._last_closure_node
        if a < c < b:
            since = self._chain_xy[b] - self._chain_xy[c] + np.eye(2) * 0.1**2
            if np.trace(since) < np.trace(full):
                return since
        return full

    def _near_submaps(self, query: int, est_q: Pose2D) -> list[tuple[int, int, float]]:
        """(submap, anchor node, distance), in submap order, of each finished submap at least
        `min_node_gap` nodes older than `query` with a node within the widest window
        (`base_radius_m + window_max_m`) of where the graph puts the query.

        Nearness to where the robot was, not to what it saw (walls 30 m away).
        """
        p = self.params.loops
        near = self._near
        near.extend(self.submaps.submaps)
        eligible = np.flatnonzero(near.last_node <= query - p.min_node_gap)
        if eligible.size == 0:
            return []
        # The query in each anchor's frame, by the same scalar arithmetic as everywhere else.
        qx, qy = np.zeros(len(near.anchor_node)), np.zeros(len(near.anchor_node))
        for k in eligible:
            qx[k], qy[k], _ = self.graph.estimate(near.anchor_node[k]).between(est_q)
        x_m, y_m = near.xy_m[:, 0], near.xy_m[:, 1]
        node_dist = np.hypot(x_m - np.repeat(qx, near.lengths), y_m - np.repeat(qy, near.lengths))
        dist = np.minimum.reduceat(node_dist, near.starts)
        reach_m = p.base_radius_m + p.window_max_m  # `window_m` is at most `window_max_m`
        return [
            (near.sub_index[k], near.anchor_node[k], float(dist[k]))
            for k in eligible
            if dist[k] <= reach_m
        ]

    def _search(self, query: int) -> None:
        p = self.params.loops
        points = self.node_points[query]
        est_q = self.graph.estimate(query)
        candidates: list[tuple[float, int, FloatArray]] = []
        for sub_index, anchor, dist in self._near_submaps(query, est_q):
            cov = self._chain_cov(anchor, query)
            if dist <= p.base_radius_m + window_m(cov, p):
                candidates.append((dist, sub_index, cov))
        candidates.sort(key=lambda c: c[0])
        for _, index, cov_map in candidates[: p.max_candidates]:
            sub = self.submaps.submaps[index]
            est_a = self.graph.estimate(sub.anchor_node)
            guess = est_a.between(est_q)
            cov_a = rotate_covariance(
                np.block([[cov_map, np.zeros((2, 1))], [np.zeros((1, 2)), np.ones((1, 1))]]),
                est_a.theta_rad,
            )[:2, :2]
            result = verify(sub, self.submaps.field_of(sub), query, points, guess, cov_a, p)
            if not result.accepted:
                self.stats.rejected[result.reason] = self.stats.rejected.get(result.reason, 0) + 1
                self.stats.recent_rejected.append(result)
                continue
            assert result.relative is not None
            assert result.cov_xy is not None
            cov = np.zeros((3, 3))
            cov[:2, :2] = result.cov_xy  # in the anchor's frame, as the factor wants
            cov[2, 2] = math.radians(p.match_sigma_deg) ** 2
            self.graph.add_loop(sub.anchor_node, query, result.relative, cov)
            self.stats.accepted += 1
            self.stats.closures.append(result)
            self._last_closure_node = query
            t0 = time.perf_counter()
            self.graph.update()
            self.stats.optimise_s += time.perf_counter() - t0
            break  # one closure per query: the next query sees the corrected graph

    # ------------------------------------------------------------------ results
    def finish(self) -> list[Pose2D]:
        """Final batch optimisation (offline); returns the optimised nodes."""
        if self.node_frontend:
            t0 = time.perf_counter()
            last = self.node_count - 1
            if self.params.loop_closure and last % self.params.loops.search_every_nodes:
                # The run's last node, nearest its start on a loop: its last chance to close.
                self._timed_search(last)
            t1 = time.perf_counter()
            self._optimised = self.graph.optimize_batch()
            self.stats.optimise_s += time.perf_counter() - t1
            self.stats.total_s += time.perf_counter() - t0  # the last search included
            self.stats.solver_restarts = self.graph.isam_restarts
        return self.node_poses()

    @property
    def finished(self) -> bool:
        """`finish` ran and no node came since."""
        return self._optimised is not None

    def node_poses(self) -> list[Pose2D]:
        if self._optimised is not None:
            return list(self._optimised)
        return self.graph.estimates()

    def corrections(self) -> list[Pose2D]:
        """Per node: optimised ∘ front-end⁻¹, what moves a front-end pose into the graph."""
        return [
            opt.compose(fe.inverse())
            for opt, fe in zip(self.node_poses(), self.node_frontend, strict=True)
        ]

    def latest_correction(self) -> Pose2D:
        """The newest node's correction (identity before the first node): a front-end pose
        after it, moved by this, is where the graph puts it now."""
        if not self.node_frontend:
            return Pose2D(0.0, 0.0, 0.0)
        node = len(self.node_frontend) - 1
        return self.graph.estimate(node).compose(self.node_frontend[node].inverse())


FrontEndName = Literal["matcher", "paper"]
# The default first (`mapping-service map --front-end`, the service's `front_end` setting).
FRONT_ENDS: tuple[FrontEndName, ...] = ("matcher", "paper")
DEFAULT_FRONT_END: FrontEndName = FRONT_ENDS[0]


class Tracker(Protocol):
    """What the session needs of a front end: a pose per scan."""

    def process(self, scan: LaserScan) -> PoseEstimate: ...

    def reset(self) -> None: ...


class FrontEnd(Tracker, Protocol):
    """A front end of ours (`ScanMatcherFrontEnd`, `PaperFrontEnd`)."""

    @property
    def wall_families_rad(self) -> tuple[float, ...]: ...


def make_frontend(name: FrontEndName = DEFAULT_FRONT_END, use_odometry: bool = True) -> FrontEnd:
    """The named front end: "matcher" (one scan-to-submap match, `frontend.scan_matcher`: the
    default, `DEFAULT_FRONT_END`) or "paper" (the IROS 2010 method, offline only)."""
    if name == "matcher":
        return ScanMatcherFrontEnd(MatcherParams(use_odometry=use_odometry))
    if name == "paper":
        return PaperFrontEnd()  # the IROS 2010 method as stated: no odometry (`frontend.paper`)
    raise ValueError(f"unknown front end {name!r}; use one of {', '.join(FRONT_ENDS)}")


class Tracked(NamedTuple):
    """One scan after the front end: what the session's back half (back end and map) takes."""

    scan: LaserScan
    estimate: PoseEstimate
    node: bool  # becomes a graph node (a keyframe, with loop closure on)
    drawn: bool  # drawn into the map (keyframes and one per `draw_period_s`, usable)


class SlamSession:
    """One session's SLAM, offline and live alike: front end, back end and map (pure, no IO).

    Per scan, `process` runs the two halves in turn:
    - `track` (the front half): the front end's estimate, and the map rule: a scan is drawn
      when it is usable (never `DEGENERATE`: its pose is only a prediction) and it is a
      keyframe, the first scan, or `draw_period_s` of scan time after the last one drawn;
    - `integrate` (the back half): a keyframe becomes a graph node (loop search, iSAM2); a
      drawn scan is ray-cast once at its front-end pose: with loop closure into the map chunk
      of its latest node's stretch of travel (`maps.composed.ChunkedMap`, frozen once the next
      stretch begins), without it into the one grid. Nothing per scan is kept.
    The live service runs `track` on its per-scan path and `integrate` in a background thread
    (`service.app.backend`): the same calls in the same order, so the same graph and map.
    `map_image` composes the chunks at their anchors' current corrections; `finish` runs the
    final search and batch optimisation and returns every scan's corrected pose.

    `map_resolution_m` None: no map (the back end alone, as benchmarks use it);
    `keep_trajectory` False: no per-scan record (the live service records its poses itself);
    `frontend` None: the default front end (`make_frontend()`, the matcher); the service and
    `mapping-service map` pass theirs by name (`make_frontend`).
    """

    # Defaults for a session restored from a checkpoint written before the map rule was in
    # scan time (it restores attributes one by one: `service.app.statecodec`).
    draw_period_s: float = DEFAULT_DRAW_PERIOD_S
    _drawn_stamp_ns: int | None = None

    def __init__(
        self,
        params: SlamParams | None = None,
        frontend: Tracker | None = None,
        *,
        map_resolution_m: float | None = None,
        draw_period_s: float = DEFAULT_DRAW_PERIOD_S,
        keep_trajectory: bool = True,
    ) -> None:
        self.params = params if params is not None else SlamParams()
        self.frontend: Tracker = frontend if frontend is not None else make_frontend()
        self.backend = SlamBackend(self.params)
        self.draw_period_s = float(draw_period_s)
        self.map_resolution_m = map_resolution_m
        self.keep_trajectory = keep_trajectory
        # Front half: scans tracked, the stamp of the last one drawn.
        self._tracked = 0
        self._drawn_stamp_ns: int | None = None
        # Back half.
        self._scan_node: list[int] = []  # per scan: its latest node (-1: none yet)
        self._scan_frontend: list[Pose2D] = []
        # Drawn scans kept for drawing at corrected poses (loop closure): scan, pose, node.
        # The map: with loop closure, chunks moved by their anchors' corrections; without,
        # one grid at the front-end poses (no correction ever moves it).
        self._grid: OccupancyGrid | None = None
        self._chunks: ChunkedMap | None = None
        if map_resolution_m is not None:
            if self.params.loop_closure:
                self._chunks = ChunkedMap(map_resolution_m)
            else:
                self._grid = OccupancyGrid(map_resolution_m)
        self.integrate_ns: list[int] = []  # time of each scan drawn (`keep_trajectory` only)

    @property
    def graph(self) -> PoseGraph:
        return self.backend.graph

    @property
    def submaps(self) -> SubmapBuilder:
        return self.backend.submaps

    @property
    def stats(self) -> LoopStats:
        return self.backend.stats

    @property
    def node_frontend(self) -> list[Pose2D]:
        return self.backend.node_frontend

    # ------------------------------------------------------------------ per scan
    def process(self, scan: LaserScan, seq: int = -1) -> PoseEstimate:
        """The front end's estimate for `scan`; a keyframe also becomes a graph node."""
        tracked = self.track(scan)
        self.integrate(tracked, seq)
        return tracked.estimate

    def track(self, scan: LaserScan) -> Tracked:
        """The front half: the front end's estimate, and what the back half does with it."""
        return self.select(scan, self.frontend.process(scan))

    def select(self, scan: LaserScan, estimate: PoseEstimate) -> Tracked:
        """The map rule and the node rule for an estimate (`track` without the front end)."""
        self._tracked += 1
        usable = not estimate.flags & PoseFlag.DEGENERATE
        last = self._drawn_stamp_ns
        due = self.draw_period_s > 0 and (
            last is None or scan.stamp_ns - last >= self.draw_period_s * 1e9
        )
        drawn = self.has_map and usable and (estimate.is_keyframe or due or self._tracked == 1)
        if drawn:
            self._drawn_stamp_ns = scan.stamp_ns
        node = self.params.loop_closure and estimate.is_keyframe
        return Tracked(scan, estimate, node, drawn)

    def integrate(self, tracked: Tracked, seq: int = -1) -> bool:
        """The back half: the node, the map; True when a loop closure was accepted."""
        estimate = tracked.estimate
        closure = False
        if tracked.node:
            closure = self.backend.add_node(
                tracked.scan, estimate.pose, estimate.covariance, int(estimate.flags), seq
            )
        node = self.backend.node_count - 1
        if self.keep_trajectory:
            self._scan_node.append(node)
            self._scan_frontend.append(estimate.pose)
        if tracked.drawn:
            t0 = time.perf_counter_ns()
            if self._chunks is not None:
                self._chunks.draw(tracked.scan, estimate.pose, node)
            else:
                assert self._grid is not None
                self._grid.integrate(tracked.scan, estimate.pose)
            if self.keep_trajectory:
                self.integrate_ns.append(time.perf_counter_ns() - t0)
        return closure

    def observe(self, scan: LaserScan, estimate: PoseEstimate) -> None:
        """The back half of `process` for an estimate made by the caller (timed apart)."""
        self.integrate(self.select(scan, estimate))

    # ------------------------------------------------------------------ results
    def finish(self) -> list[Pose2D]:
        """Final search and batch optimisation; the corrected pose of every scan processed
        (with `keep_trajectory`)."""
        if self.params.loop_closure and self.backend.node_count and not self.backend.finished:
            self.backend.finish()
        return self.corrected_poses()

    def node_poses(self) -> list[Pose2D]:
        return self.backend.node_poses()

    def corrected_poses(self) -> list[Pose2D]:
        """Every scan's front-end pose moved by its latest node's correction."""
        if not self.backend.node_count:
            return list(self._scan_frontend)
        corrections = self.backend.corrections()
        out = []
        for node, pose in zip(self._scan_node, self._scan_frontend, strict=True):
            out.append(pose if node < 0 else corrections[node].compose(pose))
        return out

    def map_image(self) -> GridImage:
        """The map at the current corrections. With loop closure: the chunks (`ChunkedMap`)
        composed, each moved by its anchor node's correction (optimised ∘ front-end⁻¹), a cost
        that grows with the chunks, not the scans; without: the one grid."""
        if self._chunks is not None:
            return self._chunks.compose(self.backend.corrections())
        if self._grid is None:
            raise ValueError("this session keeps no map (map_resolution_m is None)")
        return self._grid.snapshot()

    @property
    def has_map(self) -> bool:
        return self._grid is not None or self._chunks is not None

    @property
    def map_bytes(self) -> int:
        """The map's memory: its grid, or its chunks' tiles."""
        if self._chunks is not None:
            return self._chunks.nbytes
        return self._grid.memory_bytes() if self._grid is not None else 0
