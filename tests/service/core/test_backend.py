"""The back end on known answers: the robust graph, the loop search and its checks, submaps."""

from __future__ import annotations

import math
import pickle
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from scenes import MODEL, scan_of, world_of

from sensor_agent.sim.world import World, simulate_scan
from service.core.backend.graph import PoseGraph
from service.core.backend.loops import LoopParams, verify
from service.core.backend.params import GraphParams
from service.core.maps.submaps import Submap, SubmapBuilder, SubmapParams
from service.core.types import LaserScan, Pose2D

pytestmark = pytest.mark.timeout(120)


def _room(x0: float) -> list[list[float]]:
    """An 8 x 6 m closed room at x0 with an off-centre box and a wall stub: no symmetry."""
    return [
        [x0, 0, x0 + 8, 0],
        [x0 + 8, 0, x0 + 8, 6],
        [x0 + 8, 6, x0, 6],
        [x0, 6, x0, 0],
        [x0 + 5, 4, x0 + 5.6, 4],  # box
        [x0 + 5.6, 4, x0 + 5.6, 4.8],
        [x0 + 5.6, 4.8, x0 + 5, 4.8],
        [x0 + 5, 4.8, x0 + 5, 4],
        [x0 + 2, 0, x0 + 2, 1.5],  # stub
    ]


def _submap(world: World, poses: list[Pose2D], rng: np.random.Generator) -> SubmapBuilder:
    builder = SubmapBuilder(SubmapParams(nodes_per_submap=len(poses)))
    for node, pose in enumerate(poses):
        scan = scan_of(world, pose, rng)
        builder.add_node(node, pose, builder.node_points(scan.points_xy_m()), scan)
    assert builder.submaps[0].finished
    return builder


def _anchor_poses() -> list[Pose2D]:
    return [Pose2D(1.0 + 0.3 * k, 2.5 + 0.05 * k, 0.02 * k) for k in range(10)]


def test_loop_search_finds_a_known_offset() -> None:
    rng = np.random.default_rng(3)
    world = world_of(_room(0.0), 8.0, 6.0)
    builder = _submap(world, _anchor_poses(), rng)
    sub = builder.submaps[0]
    truth = Pose2D(6.4, 1.2, math.radians(91.0))  # the query, in the world = anchor frame here
    anchor = _anchor_poses()[0]
    true_rel = anchor.between(truth)
    points = builder.node_points(scan_of(world, truth, rng).points_xy_m())
    guess = Pose2D(true_rel.x_m + 0.35, true_rel.y_m - 0.25, true_rel.theta_rad + math.radians(0.3))
    result = verify(sub, builder.field_of(sub), 99, points, guess, np.eye(2) * 0.3**2, LoopParams())
    assert result.accepted, result
    assert result.relative is not None
    assert math.hypot(result.relative.x_m - true_rel.x_m, result.relative.y_m - true_rel.y_m) < 0.02
    assert abs(result.relative.theta_rad - true_rel.theta_rad) < math.radians(0.35)
    assert result.cov_xy is not None
    assert np.sqrt(np.linalg.eigvalsh(result.cov_xy)).max() < 0.1


def test_a_match_looser_than_the_graphs_own_guess_is_refused() -> None:
    """The same good placement is a closure when the graph is less sure of the place than the
    match (σ 0.3 m against the match's few cm), and refused when the graph is surer."""
    rng = np.random.default_rng(3)
    world = world_of(_room(0.0), 8.0, 6.0)
    builder = _submap(world, _anchor_poses(), rng)
    sub = builder.submaps[0]
    truth = Pose2D(6.4, 1.2, math.radians(91.0))
    true_rel = _anchor_poses()[0].between(truth)
    points = builder.node_points(scan_of(world, truth, rng).points_xy_m())
    field = builder.field_of(sub)
    loose_graph = verify(sub, field, 99, points, true_rel, np.eye(2) * 0.3**2, LoopParams())
    assert loose_graph.accepted, loose_graph
    assert loose_graph.cov_xy is not None
    match_m = float(np.sqrt(np.linalg.eigvalsh(loose_graph.cov_xy)).max())
    chain = np.eye(2) * (0.5 * match_m) ** 2
    sure_graph = verify(sub, field, 99, points, true_rel, chain, LoopParams())
    assert not sure_graph.accepted
    assert sure_graph.reason == "ambiguous"
    unchecked = LoopParams(max_match_to_chain=math.inf)
    assert verify(sub, field, 99, points, true_rel, chain, unchecked).accepted


def test_finished_submaps_hold_points_and_mask_and_build_their_field_on_demand() -> None:
    """A finished submap keeps its points and observed mask, not its likelihood field: the
    field is built for the loop search, cached for the few most recent, left out of
    checkpoints, and the same whether cached or rebuilt."""
    rng = np.random.default_rng(3)
    world = world_of(_room(0.0), 8.0, 6.0)
    poses = _anchor_poses()
    builder = SubmapBuilder(SubmapParams(nodes_per_submap=4, cached_fields=2))
    for node, pose in enumerate(poses):
        scan = scan_of(world, pose, rng)
        builder.add_node(node, pose, builder.node_points(scan.points_xy_m()), scan)
    finished = [sub for sub in builder.submaps if sub.finished]
    assert len(finished) >= 3
    assert all(sub.likelihood is None and sub.observed_mask is not None for sub in finished)
    first = builder.field_of(finished[0])
    assert builder.field_of(finished[0]) is first  # cached
    builder.field_of(finished[1])
    builder.field_of(finished[2])  # the cache holds 2: the least recently used goes
    assert finished[0].likelihood is None
    assert finished[2].likelihood is not None
    rebuilt = builder.field_of(finished[0])
    assert np.array_equal(rebuilt.fine, first.fine)
    assert np.array_equal(rebuilt.known, first.known)
    restored = pickle.loads(pickle.dumps(builder))
    assert all(sub.likelihood is None for sub in restored.submaps)
    again = restored.field_of(restored.submaps[finished[0].index])
    assert np.array_equal(again.fine, first.fine)
    assert len(pickle.dumps(finished[0])) < 0.25 * first.fine.nbytes


def test_a_twin_room_would_match_without_the_checks_and_is_refused_with_them() -> None:
    """Two identical rooms 12 m apart: a scan in the second matches the first perfectly."""
    rng = np.random.default_rng(5)
    world = world_of(_room(0.0) + _room(12.0), 20.0, 6.0)
    builder = _submap(world, _anchor_poses(), rng)
    sub = builder.submaps[0]
    anchor = _anchor_poses()[0]
    truth = Pose2D(12.0 + 3.1, 2.6, 0.05)  # in the second room
    true_rel = anchor.between(truth)
    points = builder.node_points(scan_of(world, truth, rng).points_xy_m())
    guess = Pose2D(true_rel.x_m - 0.2, true_rel.y_m + 0.1, true_rel.theta_rad)  # a good graph
    chain_cov = np.eye(2) * 0.15**2

    unchecked = LoopParams(
        window_min_m=14.0, window_max_m=14.0, ambiguity_separation_m=100.0, chi2_gate=math.inf
    )
    wrong = verify(sub, builder.field_of(sub), 99, points, guess, chain_cov, unchecked)
    assert wrong.accepted
    assert wrong.relative is not None
    # The twin: 12 m from the truth, the same place in the other room.
    assert abs(wrong.relative.x_m - (true_rel.x_m - 12.0 * math.cos(anchor.theta_rad))) < 0.3
    assert math.hypot(wrong.relative.x_m - true_rel.x_m, wrong.relative.y_m - true_rel.y_m) > 11.0

    checked = verify(sub, builder.field_of(sub), 99, points, guess, chain_cov, LoopParams())
    assert not checked.accepted
    assert checked.reason in {"low_score", "inconsistent", "ambiguous"}


def test_a_periodic_corridor_is_ambiguous() -> None:
    """Identical door niches every 2 m: placements 2 m apart score alike; no closure."""
    walls = [[0.0, 0.0, 40.0, 0.0], [0.0, 2.4, 40.0, 2.4], [0.0, 0.0, 0.0, 2.4]]
    for k in range(4, 19):
        x = 2.0 * k
        walls += [[x, 2.4, x, 3.0], [x, 3.0, x + 0.9, 3.0], [x + 0.9, 3.0, x + 0.9, 2.4]]
    world = world_of(walls, 40.0, 3.0)
    rng = np.random.default_rng(7)
    poses = [Pose2D(16.0 + 0.3 * k, 1.2, 0.0) for k in range(10)]
    builder = SubmapBuilder(SubmapParams(nodes_per_submap=10))
    model = MODEL.with_(range_max_m=6.0)  # short reach: the corridor's ends are never seen
    for node, pose in enumerate(poses):
        sample = simulate_scan(world, pose, model, rng)
        scan = LaserScan(
            0, model.angle_min_rad, model.angle_increment_rad, sample.ranges_m,
            model.range_min_m, model.range_max_m,
        )  # fmt: skip
        builder.add_node(node, pose, builder.node_points(scan.points_xy_m()), scan)
    sub = builder.submaps[0]
    truth = Pose2D(18.1, 1.1, 0.0)
    sample = simulate_scan(world, truth, model, rng)
    query = LaserScan(
        0, model.angle_min_rad, model.angle_increment_rad, sample.ranges_m,
        model.range_min_m, model.range_max_m,
    )  # fmt: skip
    rel = poses[0].between(truth)
    points = builder.node_points(query.points_xy_m())
    result = verify(sub, builder.field_of(sub), 99, points, rel, np.eye(2) * 1.5**2, LoopParams())
    assert not result.accepted
    assert result.reason == "ambiguous"


def _square_chain(drift_per_step_m: float) -> tuple[list[Pose2D], list[Pose2D]]:
    """A 10 x 10 m square loop driven twice, every 0.5 m: truth, and a chain that drifts east."""
    truth: list[Pose2D] = []
    corners = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]
    for _lap in range(2):
        for side, (x0, y0) in enumerate(corners):
            theta = side * math.pi / 2
            for k in range(20):
                s = 0.5 * k
                truth.append(Pose2D(x0 + s * math.cos(theta), y0 + s * math.sin(theta), theta))
    drifted = [
        Pose2D(p.x_m + drift_per_step_m * i, p.y_m, p.theta_rad) for i, p in enumerate(truth)
    ]
    return truth, drifted


def _chain_graph(
    truth: list[Pose2D],
    drifted: list[Pose2D],
    closures: list[tuple[int, int, Pose2D]],
    params: GraphParams | None = None,
    *,
    at_node: tuple[int, Callable[[PoseGraph], None]] | None = None,
) -> PoseGraph:
    """The drifted chain with heading priors and `closures`, updated once at the end (and
    handed to `at_node`'s callback after that node, if given)."""
    graph = PoseGraph(params)
    for i, pose in enumerate(drifted):
        graph.add_node(pose)
        if i:
            rel = drifted[i - 1].between(pose)
            graph.add_sequential(i - 1, i, rel, np.diag([0.02**2, 0.02**2, math.radians(0.5) ** 2]))
        graph.add_heading_prior(i, truth[i].theta_rad, math.radians(0.3))
        if at_node is not None and i == at_node[0]:
            at_node[1](graph)
    for a, b, rel in closures:
        graph.add_loop(a, b, rel, np.diag([0.03**2, 0.03**2, math.radians(0.3) ** 2]))
    graph.update()
    return graph


def _solve(
    truth: list[Pose2D],
    drifted: list[Pose2D],
    closures: list[tuple[int, int, Pose2D]],
    params: GraphParams | None = None,
) -> list[Pose2D]:
    return _chain_graph(truth, drifted, closures, params).optimize_batch()


def _max_distance(a: list[Pose2D], b: list[Pose2D]) -> float:
    return max(math.hypot(p.x_m - q.x_m, p.y_m - q.y_m) for p, q in zip(a, b, strict=True))


def _disagreement(poses: list[Pose2D], truth: list[Pose2D], pairs: list[tuple[int, int]]) -> float:
    """Largest error of the map where it visits one place twice (metres)."""
    worst = 0.0
    for a, b in pairs:
        est, true = poses[a].between(poses[b]), truth[a].between(truth[b])
        worst = max(worst, math.hypot(est.x_m - true.x_m, est.y_m - true.y_m))
    return worst


def test_closures_remove_drift_and_a_wrong_one_is_kept_out() -> None:
    truth, drifted = _square_chain(0.01)
    lap = 80
    pairs = [(i, i + lap) for i in range(0, lap, 10)]
    closures = [(a, b, truth[a].between(truth[b])) for a, b in pairs]
    corrected = _solve(truth, drifted, closures)
    assert _disagreement(drifted, truth, pairs) > 0.7  # the drift doubles the map ...
    assert _disagreement(corrected, truth, pairs) < 0.05  # ... and the closures take it out

    wrong = (15, 120, Pose2D(3.0, -2.0, 0.0))  # a false closure between unrelated places
    with_wrong = _solve(truth, drifted, [*closures, wrong])
    assert _max_distance(with_wrong, corrected) < 0.05

    # Without the robust kernels, the same wrong closure bends the map: the test can fail.
    plain = GraphParams(loop_huber_k=1e9, loop_cauchy_k=1e9)
    bent = _solve(truth, drifted, [*closures, wrong], plain)
    assert _max_distance(bent, corrected) > 0.2


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_offline_loop_closure_closes_a_synthetic_loop() -> None:
    """A tuning world (paper setting, ~415 m loop) whose front end ends 0.19 m off its start.

    The seed is whichever the front end leaves open: seed 3's closes its own loop to 0.02 m,
    and seed 1's (0.15 m open) now finds no closure it may accept. Its honest covariance
    widens the search there until a rival peak makes the closure ambiguous (session 9)."""
    from bench.evaluate import make_sequence
    from service.offline import map_scans, trajectory_length_m

    seq = make_sequence(2)
    truth = [Pose2D(*map(float, p)) for p in seq.truth]
    true_gap = truth[0].between(truth[-1])

    def gap_m(poses: list[Pose2D]) -> float:
        err = true_gap.between(poses[0].between(poses[-1]))
        return math.hypot(err.x_m, err.y_m)

    frontend = map_scans(iter(seq.scans), use_odometry=False, loop_closure=False)
    closed = map_scans(iter(seq.scans), use_odometry=False, loop_closure=True)
    assert frontend.loops is None
    assert gap_m(frontend.poses) > 0.1  # the front end alone misses ...
    assert closed.loops is not None
    assert closed.loops.accepted >= 1
    assert gap_m(closed.poses) < 0.05  # ... the back end closes it (0.018 m measured)
    # Not by shrinking the loop: the path keeps its length (a frozen tracker has a gap of 0).
    true_length = trajectory_length_m(truth)
    assert abs(trajectory_length_m(closed.poses) - true_length) < 0.01 * true_length
    assert closed.frontend_poses == frontend.poses  # the front end is the same either way


@pytest.fixture(scope="module")
def world8_keyframes() -> tuple[list[tuple[LaserScan, Any]], list[Pose2D]]:
    """Tuning world 8 (paper setting, a ~415 m loop): its front end's keyframes and their truth."""
    from bench.evaluate import make_sequence
    from service.bridge import scan_to_laser
    from service.core.slam import make_frontend

    seq = make_sequence(8)
    frontend = make_frontend(use_odometry=False)
    keyframes, truth = [], []
    for i, scan in enumerate(seq.scans):
        laser = scan_to_laser(scan, use_odometry=False)
        estimate = frontend.process(laser)
        if estimate.is_keyframe:
            keyframes.append((laser, estimate))
            truth.append(Pose2D(*map(float, seq.truth[i])))
    return keyframes, truth


def _closures_offline(
    keyframes: list[tuple[LaserScan, Any]], loops: LoopParams
) -> tuple[list[Any], int]:
    from service.core.slam import SlamBackend, SlamParams

    backend = SlamBackend(SlamParams(loops=loops))
    for laser, estimate in keyframes:
        backend.add_node(laser, estimate.pose, estimate.covariance, int(estimate.flags))
    backend.finish()
    return backend.stats.closures, backend.node_count


def test_a_closure_is_not_pulled_along_a_corridor_leaving_the_submap(
    world8_keyframes: tuple[list[tuple[LaserScan, Any]], list[Pose2D]],
) -> None:
    """The loop's last scans against its first submap. The placement's score takes the field's
    prior wherever the submap did not observe, so where the corridor leaves the submap's
    observed space it rises with the overlap; the peak is refined on the points observed at
    every shift around it, and every closure lands within centimetres of the truth. (On the
    keyframes of the deleted projection cascade an unrefined closure landed 0.23 m along the
    corridor; the matcher's keyframes do not reproduce that: 0.02 m unrefined.)"""
    keyframes, truth = world8_keyframes

    def errors_m(loops: LoopParams) -> list[float]:
        out = []
        for c in _closures_offline(keyframes, loops)[0]:
            assert c.relative is not None
            true_rel = truth[c.anchor_node].between(truth[c.query_node])
            out.append(math.hypot(c.relative.x_m - true_rel.x_m, c.relative.y_m - true_rel.y_m))
        return out

    refined = errors_m(LoopParams())
    assert refined
    assert max(refined) < 0.04


def test_the_last_node_searches_for_its_loop_at_the_end_of_an_offline_run(
    world8_keyframes: tuple[list[tuple[LaserScan, Any]], list[Pose2D]],
) -> None:
    """Nodes search every third node; an offline run's last node, nearest its start on a loop,
    searches at `finish` when that schedule skipped it (here it closes the loop). The run ends
    at the loop's last keyframe that the schedule skips (the count is the front end's)."""
    keyframes, _ = world8_keyframes
    params = LoopParams()
    n = len(keyframes)
    while (n - 1) % params.search_every_nodes == 0:
        n -= 1
    closures, nodes = _closures_offline(keyframes[:n], params)
    assert nodes == n
    assert any(c.query_node == nodes - 1 for c in closures)


def test_the_vectorised_submap_nearness_is_the_submap_by_submap_one(
    world8_keyframes: tuple[list[tuple[LaserScan, Any]], list[Pose2D]],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The loop search's candidates come from one vectorised pass over every submap's nodes
    (`SlamBackend._near_submaps`), an index that a checkpoint drops and rebuilds: at every query
    it returns what the plain loop over the submaps returns, bit for bit."""
    from service.core.slam import SlamBackend, SlamParams

    keyframes, _ = world8_keyframes
    backend = SlamBackend(SlamParams())
    half = len(keyframes) // 2
    for laser, estimate in keyframes[:half]:
        backend.add_node(laser, estimate.pose, estimate.covariance, int(estimate.flags))
    backend = pickle.loads(pickle.dumps(backend))  # as a checkpoint restores it
    vectorised = backend._near_submaps
    p = backend.params.loops
    near_counts = []

    def checked(query: int, est_q: Pose2D) -> list[tuple[int, int, float]]:
        want = []
        for sub in backend.submaps.submaps:
            if not sub.finished or sub.nodes[-1] > query - p.min_node_gap:
                continue
            q_in_a = backend.graph.estimate(sub.anchor_node).between(est_q)
            xy = np.asarray(sub.node_xy_m)
            dist = float(np.min(np.hypot(xy[:, 0] - q_in_a.x_m, xy[:, 1] - q_in_a.y_m)))
            if dist <= p.base_radius_m + p.window_max_m:
                want.append((sub.index, sub.anchor_node, dist))
        got = vectorised(query, est_q)
        assert got == want
        near_counts.append(len(got))
        return got

    monkeypatch.setattr(backend, "_near_submaps", checked)
    for laser, estimate in keyframes[half:]:
        backend.add_node(laser, estimate.pose, estimate.covariance, int(estimate.flags))
    backend.finish()
    assert sum(near_counts) > 0  # the loop's end was near its start
    assert backend.stats.accepted > 0


def test_a_submap_saved_with_its_field_by_an_older_version_still_loads() -> None:
    rng = np.random.default_rng(4)
    world = world_of(_room(0.0), 8.0, 6.0)
    builder = _submap(world, _anchor_poses(), rng)
    sub = builder.submaps[0]
    field = builder.field_of(sub)
    old_state = {name: getattr(sub, name) for name in ("index", "anchor_node", "nodes", "chunks")}
    old_state |= {
        "anchor_pose_frontend": sub.anchor_pose_frontend,
        "node_xy_m": sub.node_xy_m,
        "observed": None,
        "likelihood": field,  # what the older version kept, and no mask
    }
    loaded = Submap.__new__(Submap)
    loaded.__setstate__(old_state)
    assert loaded.finished
    assert loaded.likelihood is None
    rebuilt = SubmapBuilder(builder.params).field_of(loaded)
    xy = np.stack(np.meshgrid(np.arange(-2.0, 10.0, 0.05), np.arange(-2.0, 8.0, 0.05)), axis=-1)
    assert np.array_equal(rebuilt.lookup(xy), field.lookup(xy))  # the same field, cell for cell
    assert np.array_equal(rebuilt.lookup(xy, known=True), field.lookup(xy, known=True))


class _FailingOnce:
    """iSAM2 whose next update raises as gtsam does on a poorly conditioned system (Intel with
    odometry hit it at node 283; no small graph reproduces gtsam's Cholesky failing)."""

    def __init__(self, isam: Any) -> None:
        self._isam, self.failed = isam, False

    def update(self, *args: Any) -> None:
        if not self.failed:
            self.failed = True
            raise RuntimeError("Indeterminate linear system detected while working near x5")
        self._isam.update(*args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._isam, name)


def _square_graph(*, fail: bool = False) -> PoseGraph:
    """The square loop's graph with its closures, updated at node 100 and at the end; with
    `fail`, the update at the end fails once."""
    truth, drifted = _square_chain(0.01)
    closures = [(a, a + 80, truth[a].between(truth[a + 80])) for a in range(0, 80, 10)]

    def at_100(graph: PoseGraph) -> None:
        graph.update()
        if fail:
            graph._isam = _FailingOnce(graph._isam)

    return _chain_graph(truth, drifted, closures, at_node=(100, at_100))


def test_a_failed_isam2_update_is_rebuilt_from_every_factor() -> None:
    clean = _square_graph()
    graph = _square_graph(fail=True)  # the closures' update fails, and is rebuilt
    assert (clean.isam_restarts, graph.isam_restarts) == (0, 1)
    assert _max_distance(graph.estimates(), clean.estimates()) < 0.01
    assert _max_distance(graph.optimize_batch(), clean.optimize_batch()) < 1e-4
    last = graph.add_node(graph.estimate(graph.node_count - 1))  # and it goes on updating
    graph.add_sequential(last - 1, last, Pose2D(0.0, 0.0, 0.0), np.diag([1e-4, 1e-4, 1e-4]))
    graph.update()
    assert _max_distance([graph.estimate(last)], [graph.estimate(last - 1)]) < 1e-3
    assert graph.isam_restarts == 1


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_every_closure_on_a_tuning_wing_is_near_the_truth(tmp_path: Any) -> None:
    """Tuning wing 13, mapped from its MCAP as the CLI does: every closure within 0.2 m of the
    truth. (On the deleted projection cascade's keyframes a placement 0.76 m from the truth
    passed every other check here, with a match σ of 0.42 m against the chain's 0.11 m; the
    matcher's keyframes do not reproduce it. `max_match_to_chain` alone:
    `test_a_match_looser_than_the_graphs_own_guess_is_refused`.)"""
    from bench.worlds import read_tum, write_world
    from clients.logs import iter_log_scans
    from sensor_agent.sim import families
    from service.bridge import scan_to_laser
    from service.core.slam import make_frontend

    paths = write_world(families.generate("wing", 13), tmp_path)
    stamps, truth_xyt = read_tum(paths["tum"])
    frontend = make_frontend(use_odometry=False)
    keyframes, truth = [], []
    for scan in iter_log_scans(paths["mcap"], use_odom=False):
        laser = scan_to_laser(scan)
        estimate = frontend.process(laser)
        if estimate.is_keyframe:
            keyframes.append((laser, estimate))
            i = int(np.argmin(np.abs(stamps - laser.stamp_ns)))
            truth.append(Pose2D(*map(float, truth_xyt[i])))

    def worst_closure_m(loops: LoopParams) -> float:
        out = 0.0
        for c in _closures_offline(keyframes, loops)[0]:
            true_rel = truth[c.anchor_node].between(truth[c.query_node])
            out = max(out, math.hypot(c.relative.x_m - true_rel.x_m, c.relative.y_m - true_rel.y_m))
        return out

    assert worst_closure_m(LoopParams()) < 0.2
