"""One scan matched against one submap: a correlative search, then Gauss-Newton, one objective.

The objective over the pose T = (x, y, θ) of the scan in the map frame:

    cost(T) = w / N · Σ_i r(M(T·p_i))²               the scan against the submap's field M
            + (T - T_pred)ᵀ Σ_pred⁻¹ (T - T_pred)      the motion prior
            + ρ(((θ - θ_wall) / σ_wall)²)              the walls' heading prior, robust (Huber)

M = exp(-d²/2σ²) holds the distance d to the nearest surface, so r = √(-2 ln M) = d/σ: each
point is a point-to-surface residual, quadratic near a wall (a Gauss-Newton Hessian that does
not vanish at the optimum, as (1 - M)² does), and capped at `max_residual_sigmas` so that a
point on something the submap never saw (a person, a new room) costs a constant, not a pull.
`w` (`MatchOptions.scan_weight`) is the scan's information: as many independent points as
that. The mean over points, not the sum, because neighbouring points of a scan are not
independent evidence (Cartographer scales its occupied-space residuals the same way).

1. *Search* (Olson 2009; Cartographer's `RealTimeCorrelativeScanMatcher2D`): every rotation in
   a window, every whole-cell translation in a window, the scan scored by cell lookup; the
   lowest cost wins (found by branch and bound, `search.py`, not by scoring every pose). The
   windows are ±3σ of the prediction, so at 40 Hz it is a few cells
   and at one scan per 0.3 m it is wide.
2. *Refine* (hector's `ScanMatcher`, Cartographer's `CeresScanMatcher2D`): Gauss-Newton on the
   bilinear field from the search's best pose, priors as residuals.
3. *The weakest axis from the response* (Olson's covariance, along one direction): along the
   direction the Hessian says least about, the scan's cost is read at whole cells over the
   prior's window; that response's spread is the scan's information there and its mean, fused
   with the prediction, the estimate there. Elsewhere the Hessian stands.
4. *Covariance*: the inverse of the Hessian so corrected. A plain corridor gives the scan no
   information along its axis, so there only the prior's σ remains: long along, short across.

The motion prior is a max-mixture: that Gaussian; optionally a second Gaussian, another model
of the same motion (`Priors.second`: constant velocity when the first is odometry), at a fixed
cost (`second_cost`); or at a fixed cost (`broad_cost`) anywhere in a broad window. A component
with a cost is matched (steps 1-4 under its prior) only when the best match so far costs more
than that, the only case where it can win (`match`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from service.core.frontend import kernels
from service.core.frontend.likelihood import LikelihoodGrid, off_surface_cost
from service.core.frontend.search import Lattice, lattice_search
from service.core.types import FloatArray, Pose2D, wrap_angle


@dataclass(frozen=True, slots=True)
class MatchOptions:
    scan_weight: float = 50.0  # w: a scan counts as this many independent points
    max_residual_sigmas: float = 3.0  # a point farther than this × σ from a surface: an outlier
    search_sigmas: float = 3.0  # search window: ± this × the prediction's σ, per axis
    search_min_m: float = 0.05  # ... but at least this (one cell) ...
    search_max_m: float = 1.0  # ... and at most this
    search_min_rad: float = math.radians(0.5)
    search_max_rad: float = math.radians(25.0)
    search_points: int = 200  # scan points scored by the search (evenly subsampled)
    refine_iterations: int = 12
    # A Gauss-Newton step that raises the cost is halved at most this many times before the
    # refine stops; each halving is one more evaluation of the scan. 2 is 10 % faster per scan
    # but Intel's local rotation error grows (docs/estimator.md, "Speed"): 6 is kept.
    refine_halvings: int = 6
    # The refinement has converged when its next step would move no scan point by more than
    # this (1 % of a cell). Without it, the last step of nearly every scan (median 0.04 mm)
    # was tried and halved 6 times, failing: two thirds of the refinement's evaluations.
    refine_tolerance_m: float = 0.0005
    wall_huber: float = 2.0  # the wall prior's residual is linear beyond this many σ
    # The motion prior is a mixture: the prediction's Gaussian, or, at this cost (-2 ln of its
    # weight), anywhere in a broad window (stamps that lie, a stale scan, a kick). Searched
    # only when the match costs more than this, since it can only win then.
    broad_cost: float = 150.0
    second_cost: float = 20.0  # -2 ln of the weight of the second component (`Priors.second`)
    broad_search_m: float = 1.0  # the broad window: ± this in x and y ...
    broad_search_rad: float = math.radians(90.0)  # ... and ± this in θ


@dataclass(frozen=True, slots=True)
class Priors:
    """The match's priors: where the motion model puts the scan, and the walls' heading."""

    predicted: Pose2D
    cov_pred: FloatArray  # (3, 3), map axes
    wall_heading_rad: float | None = None  # absolute heading the walls say (nearest member)
    wall_sigma_rad: float = math.inf
    # The motion prior's second component, (pose, covariance), at `second_cost`: another model
    # of the same motion (constant velocity when the first is odometry). None: none.
    second: tuple[Pose2D, FloatArray] | None = None
    info_pred: FloatArray = field(init=False, repr=False)  # cov_pred⁻¹, used by every step

    def __post_init__(self) -> None:
        info = np.ascontiguousarray(np.linalg.inv(self.cov_pred), dtype=np.float64)
        object.__setattr__(self, "info_pred", info)


@dataclass(frozen=True, slots=True)
class MatchResult:
    pose: Pose2D
    covariance: FloatArray  # (3, 3): posterior, map axes (inverse Hessian, priors included)
    scan_information: FloatArray  # (3, 3): the scan's own part of the Hessian
    score: float  # mean field value of the scan's points at the pose, in [0, 1]
    searched_cells: int  # poses scored by the search
    cost: float  # the objective at the refined pose (the broad component's includes its cost)
    broad: bool = False  # won by the motion prior's broad component: the prediction was wrong
    second: bool = False  # won by its second component (`Priors.second`)


def _wall_cost(priors: Priors, theta_rad: float, huber: float) -> float:
    """The wall prior's cost at `theta_rad`: Huber's, on the residual in σ."""
    if priors.wall_heading_rad is None or not math.isfinite(priors.wall_sigma_rad):
        return 0.0
    a = abs(wrap_angle(theta_rad - priors.wall_heading_rad) / priors.wall_sigma_rad)
    return a * a if a <= huber else 2.0 * huber * a - huber * huber


def _scored_points(points_xy_m: FloatArray, opts: MatchOptions) -> FloatArray:
    """The scan points the correlative steps score: at most `search_points`, evenly spaced."""
    n = points_xy_m.shape[0]
    if n <= opts.search_points:
        return points_xy_m
    return points_xy_m[_evenly_spaced(n, opts.search_points)]


@lru_cache(maxsize=64)
def _evenly_spaced(n: int, k: int) -> npt.NDArray[np.int64]:
    """k indices evenly spaced over 0..n-1 (scans of one laser have a few sizes: cached)."""
    out = np.linspace(0, n - 1, k).astype(np.int64)
    out.flags.writeable = False
    return out


def search(
    grid: LikelihoodGrid, points_xy_m: FloatArray, priors: Priors, opts: MatchOptions
) -> tuple[Pose2D, int]:
    """The lowest-cost pose on the search lattice around the prediction (cell lookup), and how
    many poses and blocks were scored. Branch and bound (`search.lattice_search`): the same
    pose as scoring every lattice pose (`_brute_force_search`), for a fraction of the work."""
    costs = grid.residual_costs(opts.max_residual_sigmas)
    h, w = costs.shape
    if not h or not w or points_xy_m.shape[0] == 0:
        return priors.predicted, 0
    pts = _scored_points(points_xy_m, opts)
    thetas, half_rows, half_cols = _window(grid, pts, priors, opts)
    lattice = Lattice(
        thetas_rad=thetas,
        half_rows=half_rows,
        half_cols=half_cols,
        predicted_xy_m=(priors.predicted.x_m, priors.predicted.y_m),
        predicted_theta_rad=priors.predicted.theta_rad,
        info_pred=priors.info_pred,
        scan_weight=opts.scan_weight,
        wall_heading_rad=priors.wall_heading_rad,
        wall_sigma_rad=priors.wall_sigma_rad,
        wall_huber=opts.wall_huber,
    )
    off_surface = off_surface_cost(opts.max_residual_sigmas)
    k, di, dj, scored = lattice_search(grid, costs, off_surface, pts, lattice)
    res = grid.resolution_m
    pose = Pose2D(
        float(priors.predicted.x_m + dj * res),
        float(priors.predicted.y_m + di * res),
        wrap_angle(float(thetas[k])),
    )
    return pose, scored


def _window(
    grid: LikelihoodGrid, pts: FloatArray, priors: Priors, opts: MatchOptions
) -> tuple[FloatArray, int, int]:
    """The search lattice: its rotations (ascending), and its half widths in rows (map y) and
    columns (map x), in cells. ±`search_sigmas` σ of the prediction, in whole cells, rotations
    at the step one cell subtends at the farthest point; θ narrowed to the walls' heading."""
    n = pts.shape[0]
    res = grid.resolution_m
    sig = np.sqrt(np.maximum(np.diag(priors.cov_pred), 0.0))
    half_x = float(np.clip(opts.search_sigmas * sig[0], opts.search_min_m, opts.search_max_m))
    half_y = float(np.clip(opts.search_sigmas * sig[1], opts.search_min_m, opts.search_max_m))
    half_t = float(np.clip(opts.search_sigmas * sig[2], opts.search_min_rad, opts.search_max_rad))
    max_r = float(np.max(np.hypot(pts[:, 0], pts[:, 1]))) if n else 1.0
    step_t = max(math.atan2(res, max(max_r, 1.0)), math.radians(0.05))
    wall = priors.wall_heading_rad
    centre_t = priors.predicted.theta_rad
    if wall is not None and math.isfinite(priors.wall_sigma_rad):
        # θ is narrow where the walls anchor it: the window covers the walls' heading and the
        # prediction, no more than the prediction's own window.
        d = wrap_angle(wall - centre_t)
        if abs(d) <= half_t:
            lo = min(0.0, d) - opts.search_sigmas * priors.wall_sigma_rad
            hi = max(0.0, d) + opts.search_sigmas * priors.wall_sigma_rad
            lo, hi = max(lo, -half_t), min(hi, half_t)
            centre_t, half_t = centre_t + 0.5 * (lo + hi), 0.5 * (hi - lo)
    n_t = math.ceil(half_t / step_t)
    thetas: FloatArray = centre_t + step_t * np.arange(-n_t, n_t + 1, dtype=np.float64)
    return thetas, math.ceil(half_y / res), math.ceil(half_x / res)


def _brute_force_search(
    grid: LikelihoodGrid, points_xy_m: FloatArray, priors: Priors, opts: MatchOptions
) -> tuple[Pose2D, int]:
    """`search` by scoring every lattice pose: the reference the branch and bound must match
    (tests, `bench.search_speed`)."""
    costs = grid.residual_costs(opts.max_residual_sigmas)
    h, w = costs.shape
    if not h or not w:
        return priors.predicted, 0
    pts = _scored_points(points_xy_m, opts)
    res = grid.resolution_m
    thetas, ny, nx = _window(grid, pts, priors, opts)
    dj = np.arange(-nx, nx + 1)
    di = np.arange(-ny, ny + 1)
    info_pred = priors.info_pred
    px, py = priors.predicted.x_m, priors.predicted.y_m
    best = (math.inf, priors.predicted)
    c, s = np.cos(thetas), np.sin(thetas)
    # (K, N) map coordinates of the points at the predicted translation, every rotation.
    mx = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1] + px
    my = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1] + py
    rows0 = np.rint((my - grid.origin_m[1]) / res - 0.5).astype(np.int64)
    cols0 = np.rint((mx - grid.origin_m[0]) / res - 0.5).astype(np.int64)
    # The translation offsets, the same for every rotation.
    dx = dj[None, :] * res + np.zeros((di.shape[0], 1))
    dy = di[:, None] * res + np.zeros((1, dj.shape[0]))
    for k in range(thetas.shape[0]):
        rows = np.clip(rows0[k][None, None, :] + di[:, None, None], 0, h - 1)
        cols = np.clip(cols0[k][None, None, :] + dj[None, :, None], 0, w - 1)
        scan_cost = opts.scan_weight * costs[rows, cols].mean(axis=2, dtype=np.float64)
        dt = wrap_angle(float(thetas[k]) - priors.predicted.theta_rad)
        prior = kernels.prior_cost(info_pred, dx, dy, dt)
        total = scan_cost + prior + _wall_cost(priors, float(thetas[k]), opts.wall_huber)
        flat = int(np.argmin(total))
        if total.flat[flat] < best[0]:
            a, b = divmod(flat, dj.shape[0])
            best = (
                float(total.flat[flat]),
                Pose2D(
                    float(px + dj[b] * res), float(py + di[a] * res), wrap_angle(float(thetas[k]))
                ),
            )
    return best[1], int(thetas.shape[0] * di.shape[0] * dj.shape[0])


def refine(
    grid: LikelihoodGrid, points_xy_m: FloatArray, start: Pose2D, priors: Priors, opts: MatchOptions
) -> tuple[Pose2D, FloatArray, FloatArray, float, float]:
    """Gauss-Newton from `start` (`kernels.gauss_newton`, compiled): (pose, posterior
    covariance, scan information, score, cost). The objective: the scan's capped r² on the
    bicubic field, weighted as `scan_weight` points, plus the motion prior's Mahalanobis term,
    plus the walls' Huber term on θ."""
    wall = priors.wall_heading_rad
    ox, oy = grid.origin_m
    pose, h, h_scan, score, cost = kernels.gauss_newton(
        grid.values, ox, oy, grid.resolution_m, np.ascontiguousarray(points_xy_m, dtype=np.float64),
        np.array([start.x_m, start.y_m, start.theta_rad]),
        np.array([priors.predicted.x_m, priors.predicted.y_m, priors.predicted.theta_rad]),
        priors.info_pred,
        math.nan if wall is None else wall, priors.wall_sigma_rad, opts.wall_huber,
        opts.scan_weight, opts.max_residual_sigmas, opts.refine_iterations, opts.refine_halvings,
        opts.refine_tolerance_m,
    )  # fmt: skip
    covariance = np.linalg.inv(h)
    return (
        Pose2D(float(pose[0]), float(pose[1]), float(pose[2])),
        0.5 * (covariance + covariance.T),
        h_scan,
        float(score),
        float(cost),
    )


def match(
    grid: LikelihoodGrid, points_xy_m: FloatArray, priors: Priors, opts: MatchOptions
) -> MatchResult:
    """The scan's pose in the map frame and how sure it is, under the mixture motion prior:
    matched around the prediction; where that costs more than `second_cost`, matched again
    under the second component if there is one, which wins if it costs `second_cost` less;
    where the best costs more than `broad_cost`, matched again over the broad window, which
    wins if it costs `broad_cost` less."""
    result = _match_component(grid, points_xy_m, priors, opts)
    if priors.second is not None and result.cost > opts.second_cost:
        second = Priors(*priors.second, priors.wall_heading_rad, priors.wall_sigma_rad)
        other = _match_component(grid, points_xy_m, second, opts)
        if other.cost + opts.second_cost < result.cost:
            result = replace(other, cost=other.cost + opts.second_cost, second=True)
    if result.cost <= opts.broad_cost:
        return result
    # The broad component: a Gaussian as wide as its window (it keeps the refinement and the
    # covariance well posed; at the window's edge it costs search_sigmas², little beside
    # broad_cost), no walls' prior (its nearest family member is picked for the prediction).
    broad_priors = Priors(priors.predicted, broad_covariance(opts))
    broad_opts = replace(
        opts, search_max_m=opts.broad_search_m, search_max_rad=opts.broad_search_rad
    )
    broad = _match_component(grid, points_xy_m, broad_priors, broad_opts)
    if broad.cost + opts.broad_cost < result.cost:
        return replace(broad, cost=broad.cost + opts.broad_cost, broad=True)
    return result


def broad_covariance(opts: MatchOptions) -> FloatArray:
    """The motion prior's broad component: a Gaussian as wide as the broad window."""
    sigma_m = opts.broad_search_m / opts.search_sigmas
    sigma_rad = opts.broad_search_rad / opts.search_sigmas
    return np.diag([sigma_m**2, sigma_m**2, sigma_rad**2])


def _match_component(
    grid: LikelihoodGrid, points_xy_m: FloatArray, priors: Priors, opts: MatchOptions
) -> MatchResult:
    """Search, then refine, then read the weakest axis off the response."""
    start, cells = search(grid, points_xy_m, priors, opts)
    pose, covariance, h_scan, score, cost = refine(grid, points_xy_m, start, priors, opts)
    shift_m, h_weak = weakest_axis_from_response(grid, points_xy_m, pose, priors, h_scan, opts=opts)
    if h_weak is not h_scan:
        pose = Pose2D(pose.x_m + float(shift_m[0]), pose.y_m + float(shift_m[1]), pose.theta_rad)
        posterior = np.linalg.inv(np.linalg.inv(covariance) - h_scan + h_weak)
        covariance = np.asarray(0.5 * (posterior + posterior.T), dtype=np.float64)
        h_scan = h_weak
    return MatchResult(pose, covariance, h_scan, score, cells, cost)


def weakest_axis_from_response(
    grid: LikelihoodGrid,
    points_xy_m: FloatArray,
    pose: Pose2D,
    priors: Priors,
    h_scan: FloatArray,
    *,
    opts: MatchOptions,
) -> tuple[FloatArray, FloatArray]:
    """(shift of the pose in x, y; the scan's information) along the scan's weakest direction of
    translation, from the correlative response there (Olson 2009) where it says less than the
    Hessian.

    Along a corridor the Hessian measures the curvature of the nearest ripple of the field (no
    wall is drawn perfectly straight), not how well the scan pins the pose: trusted, each scan's
    ripple becomes a velocity, and the estimate random-walks along the corridor. The response,
    exp(-cost/2) at whole-cell steps over ±3σ of the prior along that direction (prior
    included), sees the whole window: its mean is the estimate there and its spread, less the
    prior's information, the scan's. A narrow peak gives back the Hessian's value (the smaller
    of the two is kept)."""
    evals, evecs = np.linalg.eigh(h_scan[:2, :2])
    u = evecs[:, 0]
    info_pred = priors.info_pred[:2, :2]
    prior_u = float(u @ info_pred @ u)
    res = grid.resolution_m
    half_m = min(
        max(opts.search_sigmas / math.sqrt(max(prior_u, 1e-12)), 2.0 * res), opts.search_max_m
    )
    steps = math.ceil(half_m / res)
    offsets = res * np.arange(-steps, steps + 1, dtype=np.float64)
    pts = _scored_points(points_xy_m, opts)
    looked_up = kernels.axis_lookup(
        grid.residual_costs(opts.max_residual_sigmas), *grid.origin_m, res,
        np.ascontiguousarray(pts), math.cos(pose.theta_rad), math.sin(pose.theta_rad),
        pose.x_m, pose.y_m, float(u[0]), float(u[1]), offsets,
        off_surface_cost(opts.max_residual_sigmas),
    )  # fmt: skip
    scan_cost = opts.scan_weight * looked_up.mean(axis=1)
    weight = np.exp(-0.5 * (scan_cost - scan_cost.min()))
    weight /= weight.sum()
    mean_m = float(weight @ offsets)
    var_m2 = float(weight @ (offsets - mean_m) ** 2) + res * res / 12.0
    # A flat response over the window still has the window's spread: that much is not the scan's.
    info_u = max(0.0, 1.0 / var_m2 - 3.0 / (half_m * half_m))
    # Along u, the scan's response (mean, info_u) and the prediction fused as two Gaussians.
    d = np.array([priors.predicted.x_m - pose.x_m, priors.predicted.y_m - pose.y_m])
    pred_u = float(u @ d)
    mean_m = (prior_u * pred_u + info_u * mean_m) / (prior_u + info_u)
    if info_u >= evals[0]:
        return np.zeros(2), h_scan
    e = np.array([u[0], u[1], 0.0])
    h = h_scan - (evals[0] - info_u) * np.outer(e, e)
    w_h, v_h = np.linalg.eigh(0.5 * (h + h.T))
    return mean_m * u, np.asarray((v_h * np.maximum(w_h, 0.0)) @ v_h.T)
