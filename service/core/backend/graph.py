"""The pose graph (gtsam): sequential constraints, the Manhattan heading, robust loop closures.

Nodes are the front end's keyframes. Factors:
- a prior on node 0 (the map frame is the first node's; without it the graph floats);
- `BetweenFactorPose2` between consecutive nodes, weighted by the front end's covariance;
- `PoseRotationPrior2D` on every node whose heading the front end anchored on the building's
  walls: the paper's absolute heading, said in the graph (behind a Huber kernel, since a wrong
  quadrant is possible);
- loop closures, `BetweenFactorPose2` behind a robust kernel: one wrong closure must not bend
  the map (slam_toolbox#167, cartographer_ros#533).

The kernel is Huber in iSAM2 (convex: a true closure with a large first residual still pulls the
graph into its basin, where a redescending kernel would leave it stuck at "closure ignored"),
then Cauchy in the final batch pass, started from the Huber estimate: a closure still far off
there is one the rest of the graph disagrees with, and Cauchy takes its weight away.
Live, iSAM2 updates as nodes and closures arrive; `optimize_batch` is Levenberg-Marquardt over
everything.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from service.core.backend.params import GraphParams
from service.core.types import FloatArray, Pose2D

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Edge:
    """A constraint between two nodes, for reports and the graph endpoint."""

    from_node: int
    to_node: int
    kind: str  # "sequential" or "loop"


def _key(node: int) -> int:
    return int(gtsam.symbol("x", node))


def _pose2(p: Pose2D) -> gtsam.Pose2:
    return gtsam.Pose2(p.x_m, p.y_m, p.theta_rad)


def _to_pose(p: gtsam.Pose2) -> Pose2D:
    return Pose2D(float(p.x()), float(p.y()), float(p.theta()))


class PoseGraph:
    """Nodes, factors and the current estimate; pure computation, no IO."""

    def __init__(self, params: GraphParams | None = None) -> None:
        self.params = params if params is not None else GraphParams()
        self.graph = gtsam.NonlinearFactorGraph()
        self.initial = gtsam.Values()  # every node's first guess (for the batch pass)
        self.edges: list[Edge] = []
        self.heading_priors = 0
        self._loops: list[tuple[int, int, gtsam.Pose2, FloatArray]] = []
        self._isam = self._new_isam()
        self.isam_restarts = 0  # iSAM2 rebuilt from every factor after a failed update
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._estimate: gtsam.Values | None = None
        # `estimate` per node, read from `_estimate` (gtsam's lookup costs ~12 µs; the loop
        # search asks for every submap's anchor at every query). Cleared with `_estimate`.
        self._estimate_memo: dict[int, Pose2D] = {}
        self._count = 0
        # Every factor as plain data (kind, numbers), so the graph can be saved without gtsam
        # objects (`__getstate__`) and rebuilt (`__setstate__`).
        self._records: list[tuple[Any, ...]] = []

    def _new_isam(self, *, qr: bool = False) -> gtsam.ISAM2:
        isam_params = gtsam.ISAM2Params()
        isam_params.setRelinearizeThreshold(self.params.relinearize_threshold)
        if qr:
            isam_params.setFactorization("QR")
        return gtsam.ISAM2(isam_params)

    @property
    def node_count(self) -> int:
        return self._count

    def _add(self, factor: gtsam.NonlinearFactor, *, in_batch: bool = True) -> None:
        if in_batch:
            self.graph.add(factor)
        self._new_factors.add(factor)

    @staticmethod
    def _loop_factor(
        loop: tuple[int, int, gtsam.Pose2, FloatArray], kernel: gtsam.noiseModel.mEstimator.Base
    ) -> gtsam.BetweenFactorPose2:
        a, b, relative, cov = loop
        noise = gtsam.noiseModel.Robust.Create(kernel, gtsam.noiseModel.Gaussian.Covariance(cov))
        return gtsam.BetweenFactorPose2(_key(a), _key(b), relative, noise)

    def _with_loops(self, kernel: gtsam.noiseModel.mEstimator.Base) -> gtsam.NonlinearFactorGraph:
        """Every factor, the closures behind `kernel` (`self.graph` holds all but those)."""
        graph = gtsam.NonlinearFactorGraph(self.graph)
        for loop in self._loops:
            graph.add(self._loop_factor(loop, kernel))
        return graph

    def add_node(self, guess: Pose2D) -> int:
        """A new node at `guess` (map frame); returns its index. Node 0 gets the prior."""
        node = self._count
        self._count += 1
        value = _pose2(guess)
        self.initial.insert(_key(node), value)
        self._new_values.insert(_key(node), value)
        if node == 0:
            p = self.params
            sigmas = np.array([p.prior_sigma_m, p.prior_sigma_m, p.prior_sigma_rad])
            self._add_prior(tuple(guess), tuple(float(v) for v in sigmas))
        return node

    def _add_prior(self, pose: tuple[float, ...], sigmas: tuple[float, ...]) -> None:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(sigmas))
        self._add(gtsam.PriorFactorPose2(_key(0), gtsam.Pose2(*pose), noise))
        self._records.append(("prior", pose, sigmas))

    def add_sequential(self, a: int, b: int, relative: Pose2D, cov_in_a: FloatArray) -> None:
        """`relative` = pose of b in a's frame, with its covariance in a's frame."""
        noise = gtsam.noiseModel.Gaussian.Covariance(cov_in_a)
        self._add(gtsam.BetweenFactorPose2(_key(a), _key(b), _pose2(relative), noise))
        self.edges.append(Edge(a, b, "sequential"))
        self._records.append(("between", a, b, tuple(relative), np.array(cov_in_a, np.float64)))

    def add_heading_prior(self, node: int, theta_rad: float, sigma_rad: float) -> None:
        base = gtsam.noiseModel.Isotropic.Sigma(1, sigma_rad)
        robust = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(self.params.heading_huber_k), base
        )
        self._add(gtsam.PoseRotationPrior2D(_key(node), gtsam.Pose2(0.0, 0.0, theta_rad), robust))
        self.heading_priors += 1
        self._records.append(("heading", node, float(theta_rad), float(sigma_rad)))

    def add_loop(self, a: int, b: int, relative: Pose2D, cov_in_a: FloatArray) -> None:
        loop = (a, b, _pose2(relative), np.array(cov_in_a, dtype=np.float64))
        self._loops.append(loop)
        huber = gtsam.noiseModel.mEstimator.Huber.Create(self.params.loop_huber_k)
        self._add(self._loop_factor(loop, huber), in_batch=False)
        self.edges.append(Edge(a, b, "loop"))

    # -- saving and rebuilding (checkpoints: plain data, no gtsam objects) --------------------

    def __getstate__(self) -> dict[str, Any]:
        n = self._count
        initial = np.array(
            [tuple(_to_pose(self.initial.atPose2(_key(i)))) for i in range(n)], dtype=np.float64
        ).reshape(n, 3)
        current = np.array([tuple(self.estimate(i)) for i in range(n)], dtype=np.float64)
        return {
            "params": self.params,
            "initial": initial,
            "current": current.reshape(n, 3),
            "records": list(self._records),
            "loops": [
                (a, b, (float(r.x()), float(r.y()), float(r.theta())), cov)
                for a, b, r, cov in self._loops
            ],
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        """The same factors again, iSAM2 linearised at the saved estimate (so it stays there)."""
        self.__init__(state["params"])  # type: ignore[misc]
        initial = np.asarray(state["initial"], dtype=np.float64)
        current = np.asarray(state["current"], dtype=np.float64)
        for i in range(initial.shape[0]):
            self._count += 1
            self.initial.insert(_key(i), gtsam.Pose2(*initial[i]))
            self._new_values.insert(_key(i), gtsam.Pose2(*current[i]))
        for record in state["records"]:
            kind = record[0]
            if kind == "prior":
                self._add_prior(tuple(record[1]), tuple(record[2]))
            elif kind == "between":
                _, a, b, rel, cov = record
                self.add_sequential(int(a), int(b), Pose2D(*rel), np.asarray(cov))
            elif kind == "heading":
                self.add_heading_prior(int(record[1]), float(record[2]), float(record[3]))
        for a, b, rel, cov in state["loops"]:
            self.add_loop(int(a), int(b), Pose2D(*rel), np.asarray(cov))
        self.update()

    def update(self) -> None:
        """iSAM2 step with what was added since the last one."""
        if self._new_factors.size() == 0 and self._new_values.size() == 0:
            return
        try:
            self._isam.update(self._new_factors, self._new_values)
        except RuntimeError as exc:  # gtsam's IndeterminateSystemException
            # Cholesky squares the condition number: on a poorly conditioned graph (Intel with
            # odometry: three closures to one old node, gtsam 4.3) it fails where the same
            # factors solve by QR, which the rebuilt iSAM2 uses from then on. A failure of
            # that is a real one and propagates.
            log.warning(
                "iSAM2 update failed at %d nodes (%s); rebuilt from all %d factors with QR",
                self._count,
                str(exc).strip().splitlines()[0],
                self.graph.size() + len(self._loops),
            )
            self._restart_isam()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._estimate = None
        self._estimate_memo.clear()

    def _restart_isam(self) -> None:
        """A new iSAM2 (QR) with every factor, linearised at the last estimate (new nodes at
        their first guess)."""
        try:
            last = self._isam.calculateEstimate() if self._isam.size() > 0 else gtsam.Values()
        except RuntimeError:
            last = gtsam.Values()
        values = gtsam.Values()
        for i in range(self._count):
            key = _key(i)
            source = last if last.exists(key) else self._new_values
            values.insert(key, (source if source.exists(key) else self.initial).atPose2(key))
        huber = gtsam.noiseModel.mEstimator.Huber.Create(self.params.loop_huber_k)
        self._isam = self._new_isam(qr=True)
        self._isam.update(self._with_loops(huber), values)
        self.isam_restarts += 1

    def estimate(self, node: int) -> Pose2D:
        """The current estimate of a node (after `update`; else its first guess)."""
        memo = self._estimate_memo.get(node)
        if memo is not None:
            return memo
        if self._estimate is None and self._isam.size() > 0:
            self._estimate = self._isam.calculateEstimate()
        values = self._estimate
        if values is not None and values.exists(_key(node)):
            pose = _to_pose(values.atPose2(_key(node)))
        else:
            pose = _to_pose(self.initial.atPose2(_key(node)))
        self._estimate_memo[node] = pose
        return pose

    def estimates(self) -> list[Pose2D]:
        return [self.estimate(i) for i in range(self._count)]

    def optimize_batch(self) -> list[Pose2D]:
        """Levenberg-Marquardt over the whole graph from the iSAM2 estimate; returns all nodes."""
        if self._count == 0:
            return []
        self.update()
        start = gtsam.Values()
        for i in range(self._count):
            start.insert(_key(i), _pose2(self.estimate(i)))
        cauchy = gtsam.noiseModel.mEstimator.Cauchy.Create(self.params.loop_cauchy_k)
        graph = self._with_loops(cauchy)
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(self.params.batch_max_iterations)
        result = gtsam.LevenbergMarquardtOptimizer(graph, start, lm).optimize()
        self._estimate = result
        self._estimate_memo.clear()
        return [_to_pose(result.atPose2(_key(i))) for i in range(self._count)]
