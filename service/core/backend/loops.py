"""Loop search: a node's scan against an older submap, translation-first, with its checks.

The heading is absolute (the building's walls), so a candidate match needs no rotation search
beyond a small residual: a few angles around the graph's relative heading, each a pure 2-D
translation search. Branch and bound over one coarse level makes it exact and cheap: a coarse
score (on the submap's sliding-maximum field) bounds every fine score in its block, so only the
blocks whose bound beats the best fine score so far are refined.

A closure is kept only when it passes these checks, and each refusal is counted by reason:
- `low_score`: the best mean likelihood of the scan's points is below `min_score`;
- `ambiguous`: another placement farther than `ambiguity_separation_m` scores nearly as well
  (a twin room, a periodic wall, a corridor's length), or a dense query's peak, refined on
  the points the submap observed at every shift near it (`refine_peak`), keeps moving, or the
  score's spread puts more σ on some axis than `max_match_sigma_m`, or than the graph's own
  guess has (`max_match_to_chain` × the chain's σ). A
  ridge could be kept as a closure with a long covariance instead; measured on ACES, such
  closures did harm (mean relation error 0.096 m rejecting them, 0.19-0.27 m keeping them),
  so a closure must pin both axes;
- `inconsistent`: the correction it asks for is outside the graph's own uncertainty
  (a χ² gate on the offset from the graph's guess, with the chain's covariance);
- `few_points`: fewer than `min_points` points in the query.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from service.core.maps.submaps import LikelihoodField, Submap
from service.core.types import (
    FloatArray,
    Pose2D,
    largest_eigenvalue_2x2,
    mahalanobis_sq_2x2,
    parabolic_offset,
    rotate_points,
)

BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class LoopParams:
    min_node_gap: int = 60  # a submap's nodes must be this many nodes older than the query
    search_every_nodes: int = 3  # a node searches for closures every this many nodes
    max_candidates: int = 3  # nearest submaps searched per query
    base_radius_m: float = 4.0  # candidate submaps' centres within this + the window
    window_sigmas: float = 3.0  # translation window: ± this × the chain's σ ...
    window_min_m: float = 0.5  # ... at least this ...
    window_max_m: float = 6.0  # ... at most this
    rotation_half_deg: float = 1.0  # residual rotation searched around the graph's
    rotation_step_deg: float = 0.5
    min_score: float = 0.55  # mean likelihood of the scan's observed points at the best placement
    min_known_fraction: float = 0.5  # at least this share of the points in observed space
    ambiguity_ratio: float = 0.9  # a rival this close to the best: ambiguous
    ambiguity_separation_m: float = 0.5  # ... if at least this far from it
    chi2_gate: float = 11.8  # 2 dof, 99.7 %: offset from the guess vs the chain covariance
    min_points: int = 40  # query scans with fewer points are not searched
    max_refined_blocks: int = 96  # branch and bound: fine searches per query and submap, at most
    response_max_half_m: float = 1.0  # a closure's covariance: the score's spread within ± this
    response_cells: int = 20  # ... sampled on this many steps each side
    response_temperature: float = 0.01  # p ∝ exp((score - best) / this)
    # Dense queries only (at least this many kept points): on sparse SICK scans (ACES, Intel)
    # the refined peaks were no nearer the optimised graph's.
    refine_min_points: int = 250
    refine_half_m: float = 0.3  # the peak is refined within ± this of the placement ...
    refine_cells: int = 12  # ... on this many steps each side (2.5 cm) ...
    refine_moves: int = 6  # ... searched this often at most while the best moves
    match_sigma_floor_m: float = 0.02  # a closure's translation σ, at least
    max_match_sigma_m: float = 0.6  # a closure this loose along its worst axis says nothing
    max_match_to_chain: float = 1.0  # ... and one looser than this × the chain's σ adds nothing
    match_sigma_deg: float = 0.3  # σ of a closure's rotation


@dataclass(frozen=True, slots=True)
class Placement:
    """The best pose of a scan in a submap's frame, and how it scored."""

    pose: Pose2D
    score: float
    rival_score: float  # best score farther than the separation from `pose`
    points_m: FloatArray  # the scan's points at `pose`'s rotation (`refine_peak`, `response_cov`)
    response_half_m: float  # the half window `response_cov` spreads the score over


@dataclass(frozen=True, slots=True)
class LoopResult:
    """What one search of one submap gave: a constraint, or the reason there is none."""

    submap: int
    anchor_node: int
    query_node: int
    accepted: bool
    reason: str  # "accepted", "low_score", "ambiguous", "inconsistent", "few_points"
    relative: Pose2D | None = None  # query node in the anchor's frame
    cov_xy: FloatArray | None = None  # (2, 2) of `relative`'s translation, anchor frame
    score: float = 0.0
    correction_m: float = 0.0  # how far the closure moves the query from the graph's guess


def _shifted_cells(
    field: LikelihoodField, pts: FloatArray, xs: FloatArray, ys: FloatArray
) -> tuple[npt.NDArray[np.int64], BoolArray]:
    """(ny, nx, n) flat cell index of every point shifted by every (x, y), clipped to the grid,
    and whether it fell inside (`take` on the raveled grids: faster than 2-D indexing)."""
    h, w = field.fine.shape
    res = field.resolution_m
    # Cell indices separate: column = floor((px + x - ox) / res), row likewise.
    cols = np.floor((pts[:, 0][None, :] + xs[:, None] - field.origin_m[0]) / res).astype(np.int64)
    rows = np.floor((pts[:, 1][None, :] + ys[:, None] - field.origin_m[1]) / res).astype(np.int64)
    col_ok = (cols >= 0) & (cols < w)
    row_ok = (rows >= 0) & (rows < h)
    cols = np.clip(cols, 0, w - 1)
    rows = np.clip(rows, 0, h - 1)
    inside: BoolArray = row_ok[:, None, :] & col_ok[None, :, :]
    return rows[:, None, :] * w + cols[None, :, :], inside


def _scores(  # noqa: PLR0917 - the field, the points and the shifts to score them at
    field: LikelihoodField,
    pts: FloatArray,
    xs: FloatArray,
    ys: FloatArray,
    coarse: bool,
    min_known: float,
) -> FloatArray:
    """(len(ys), len(xs)) scores of `pts` shifted by every (x, y).

    Fine: the mean over the points of the field where the submap observed the space, and of
    the field's prior (`unknown_value`) where it did not; 0 where fewer than `min_known` of the
    points are in observed space. Coarse: the same mean on the coarse field (which is at least
    the prior everywhere), a bound of every fine score in the block.
    """
    grid = field.coarse if coarse else field.fine
    n = pts.shape[0]
    cells, inside = _shifted_cells(field, pts, xs, ys)  # (ny, nx, n)
    u = field.unknown_value
    if coarse:
        vals = np.where(inside, grid.ravel().take(cells), u)
        out: FloatArray = vals.sum(axis=2, dtype=np.float64) / n
        return out
    known = field.known.ravel().take(cells) * inside  # (ny, nx, n)
    total = (grid.ravel().take(cells) * known).sum(axis=2, dtype=np.float64)
    n_known = known.sum(axis=2, dtype=np.float64)
    score = (total + u * (n - n_known)) / n
    return np.where(n_known >= min_known * n, score, 0.0)


def place_scan(
    field: LikelihoodField,
    points_m: FloatArray,
    guess: Pose2D,
    half_window_m: float,
    params: LoopParams,
) -> Placement:
    """Best placement of `points_m` (query frame) in the field's frame, near `guess`."""
    res = field.resolution_m
    block = res * field.coarse_factor
    n_rot = max(0, round(params.rotation_half_deg / params.rotation_step_deg))
    half = max(1, math.ceil(half_window_m / block))
    best = (-1.0, guess)
    rotated: dict[float, FloatArray] = {}  # the query points at each searched rotation
    xs = guess.x_m + block * np.arange(-half, half + 1, dtype=np.float64)
    ys = guess.y_m + block * np.arange(-half, half + 1, dtype=np.float64)
    # Every block with a bound > 0, as arrays (thousands per search: no Python tuples), in
    # rotation then row-major order; the stable sort by bound keeps that order among ties.
    bounds, thetas, block_x, block_y = [], [], [], []
    for k in range(-n_rot, n_rot + 1):
        theta = guess.theta_rad + math.radians(k * params.rotation_step_deg)
        pts = rotated[theta] = rotate_points(points_m, theta)
        coarse = _scores(field, pts, xs, ys, True, params.min_known_fraction)
        rows, cols = np.nonzero(coarse > 0.0)
        bounds.append(coarse[rows, cols])
        thetas.append(np.full(rows.shape[0], theta))
        block_x.append(xs[cols])
        block_y.append(ys[rows])
    bound_all = np.concatenate(bounds)
    order = np.argsort(-bound_all, kind="stable")[: params.max_refined_blocks]
    candidates = zip(
        bound_all[order].tolist(),
        np.concatenate(thetas)[order].tolist(),
        np.concatenate(block_x)[order].tolist(),
        np.concatenate(block_y)[order].tolist(),
        strict=True,
    )
    offsets = res * np.arange(field.coarse_factor, dtype=np.float64)
    fine_peaks: list[tuple[float, float, float, float]] = []  # (score, theta, x, y) per block
    for bound, theta, x0, y0 in candidates:
        # A rival needs only to beat the ambiguity threshold, not the best: refine blocks whose
        # bound could reach it, so the rival score is exact where it matters.
        floor = params.ambiguity_ratio * max(best[0], params.min_score)
        if bound < floor:
            break
        pts = rotated[theta]
        fine = _scores(field, pts, x0 + offsets, y0 + offsets, False, params.min_known_fraction)
        iy, ix = np.unravel_index(int(np.argmax(fine)), fine.shape)
        score = float(fine[iy, ix])
        x, y = x0 + float(offsets[ix]), y0 + float(offsets[iy])
        fine_peaks.append((score, theta, x, y))
        if score > best[0]:
            best = (score, Pose2D(x, y, theta))
    pose, best_score = best[1], max(best[0], 0.0)
    cached = rotated.get(pose.theta_rad)
    # Nothing refined (no block passed): the guess itself, at the guess' rotation.
    pts = cached if cached is not None else rotate_points(points_m, pose.theta_rad)
    rival = max(
        (
            score
            for score, _, x, y in fine_peaks
            if math.hypot(x - pose.x_m, y - pose.y_m) > params.ambiguity_separation_m
        ),
        default=0.0,
    )
    half_m = min(half_window_m, params.response_max_half_m)
    return Placement(pose, best_score, rival, pts, half_m)


def _known_at_every_shift(field: LikelihoodField, pts: FloatArray, d: FloatArray) -> BoolArray:
    """(n,): the points that lie in the submap's observed space at every shift (x, y) in d × d."""
    cells, inside = _shifted_cells(field, pts, d, d)
    known: BoolArray = (field.known.ravel().take(cells) > 0.5) & inside
    out: BoolArray = np.all(known, axis=(0, 1))
    return out


def refine_peak(field: LikelihoodField, placement: Placement, params: LoopParams) -> Pose2D | None:
    """The placement's peak, scored on the query points that lie in observed space at every
    shift of a small window around it; None where there is no peak near the placement.

    The placement's own score mixes the field at observed points with the field's prior at
    the others, and which points are observed changes with the shift: where a corridor leaves
    the submap's observed space, the score rises with the overlap, not with the fit (0.2 m
    along synthetic corridors). On a point set that does not change with the shift the score
    measures the fit alone, read between cell centres. The window (`refine_half_m`) is just
    wider than a wall's band of observed cells (the field's bumps), so that a point beyond a
    wall's last hit, in the bump's tail, leaves the set; the set is chosen around the current
    peak, so the search moves to the best shift and searches again until it stays. None: still
    moving after `refine_moves`, or farther than the window from the placement (a ridge, or a
    peak the placement did not find). With fewer than `min_points` such points the
    placement's own peak stays.
    """
    n, half_m = params.refine_cells, params.refine_half_m
    d = np.linspace(-half_m, half_m, 2 * n + 1)
    step = float(d[1] - d[0])
    x_m, y_m = placement.pose.x_m, placement.pose.y_m
    for _ in range(params.refine_moves):
        pts = placement.points_m + np.array([x_m, y_m])
        pts = pts[_known_at_every_shift(field, pts, d)]
        if pts.shape[0] < params.min_points:  # too few to refine: the placement's own peak
            return Pose2D(x_m, y_m, placement.pose.theta_rad)
        # Interpolated between cell centres: the peak is wanted to less than a cell.
        shifted = pts[None, None, :, :] + np.stack(np.meshgrid(d, d), axis=-1)[:, :, None, :]
        scores = field.interpolate(shifted).mean(axis=2)  # scores[iy, ix]: row = y
        iy, ix = np.unravel_index(int(np.argmax(scores)), scores.shape)
        if abs(ix - n) <= 1 and abs(iy - n) <= 1:  # the peak stays: refine it between steps
            top = float(scores[iy, ix])
            px = d[ix] + step * parabolic_offset(scores[iy, ix - 1], top, scores[iy, ix + 1])
            py = d[iy] + step * parabolic_offset(scores[iy - 1, ix], top, scores[iy + 1, ix])
            return Pose2D(x_m + float(px), y_m + float(py), placement.pose.theta_rad)
        x_m, y_m = x_m + float(d[ix]), y_m + float(d[iy])
        moved_m = math.hypot(x_m - placement.pose.x_m, y_m - placement.pose.y_m)
        if moved_m > params.refine_half_m:
            break  # a refinement corrects the placement's bias, it does not search
    return None


def response_cov(field: LikelihoodField, placement: Placement, params: LoopParams) -> FloatArray:
    """The placement's (2, 2) covariance from the score's spread around it (Olson 2009), in the
    field's frame. Computed only for a placement that scored well enough to be checked further
    (most searches end at a low score: Intel, 1,225 of 1,804).

    The second moment about the peak, not about the mean: an elongated peak (a corridor that
    pins one axis well) reads as uncertain along it, and the peak itself stays the measurement
    (a mean slides along such a peak: it cost 0.1 m on a synthetic loop).
    """
    n, half_m, pose = params.response_cells, placement.response_half_m, placement.pose
    d = np.linspace(-half_m, half_m, 2 * n + 1)
    pts = placement.points_m
    scores = _scores(field, pts, pose.x_m + d, pose.y_m + d, False, params.min_known_fraction)
    top = max(placement.score, float(scores.max()))
    weights = np.exp((scores - top) / params.response_temperature)
    weights /= weights.sum()
    gx, gy = np.meshgrid(d, d)  # scores[iy, ix]: row = y
    cxx = float((weights * gx**2).sum())
    cyy = float((weights * gy**2).sum())
    cxy = float((weights * gx * gy).sum())
    floor = params.match_sigma_floor_m**2
    return np.array([[cxx + floor, cxy], [cxy, cyy + floor]])


def _loosest_sigma_m(cov_xy: FloatArray) -> float:
    """σ along the loosest axis of a 2×2 covariance."""
    return math.sqrt(max(largest_eigenvalue_2x2(cov_xy), 0.0))


def window_m(chain_cov_xy: FloatArray, params: LoopParams) -> float:
    sigma = _loosest_sigma_m(chain_cov_xy)
    return min(max(params.window_sigmas * sigma, params.window_min_m), params.window_max_m)


def verify(  # noqa: PLR0917 - the query, the candidate and the graph's view of them
    submap: Submap,
    field: LikelihoodField,
    query_node: int,
    points_m: FloatArray,
    guess: Pose2D,
    chain_cov_xy: FloatArray,
    params: LoopParams,
) -> LoopResult:
    """Search one submap for the query node; the checks decide (see the module docstring).

    `guess` is the query node in the anchor's frame (from the graph), `chain_cov_xy` the 2×2
    uncertainty of that guess, in the anchor's frame too.
    """
    refused = LoopResult(submap.index, submap.anchor_node, query_node, False, "few_points")
    if points_m.shape[0] < params.min_points:
        return refused
    placement = place_scan(field, points_m, guess, window_m(chain_cov_xy, params), params)
    d = np.array([placement.pose.x_m - guess.x_m, placement.pose.y_m - guess.y_m])
    result = replace(
        refused,
        relative=placement.pose,
        score=placement.score,
        correction_m=float(np.hypot(d[0], d[1])),
    )
    if placement.score < params.min_score:
        return replace(result, reason="low_score")
    dense = points_m.shape[0] >= params.refine_min_points
    peak = refine_peak(field, placement, params) if dense else placement.pose
    if peak is None:
        return replace(result, reason="ambiguous")
    cov_xy = response_cov(field, placement, params)
    d = np.array([peak.x_m - guess.x_m, peak.y_m - guess.y_m])
    result = replace(result, relative=peak, cov_xy=cov_xy, correction_m=float(np.hypot(*d)))
    loosest_m = _loosest_sigma_m(cov_xy)
    # A match looser than the graph's own guess adds little when right and misleads when wrong:
    # on tuning wings the closures 0.75 m off had 2.6-4 × the chain's σ, true ones ≤ 0.83 ×.
    chain_m = _loosest_sigma_m(chain_cov_xy)
    rival = placement.rival_score >= params.ambiguity_ratio * placement.score
    if rival or loosest_m > min(params.max_match_sigma_m, params.max_match_to_chain * chain_m):
        return replace(result, reason="ambiguous")
    cov = chain_cov_xy + cov_xy
    if mahalanobis_sq_2x2(d, cov) > params.chi2_gate:
        return replace(result, reason="inconsistent")
    return replace(result, accepted=True, reason="accepted")
