"""Real-time correlative scan matcher (Olson 2009, "Real-Time Correlative Scan Matching", Sec. III-IV).

Every pose on a lattice around the predicted pose — x, y in grid cells, θ in steps of the
angular-step rule — is scored by the mean grid value under the scan's points; the best one
wins. The grid values are chosen by measurement: by default a likelihood field (a Gaussian
of the distance to the nearest occupied cell, σ = 0.1 m, kept exact incrementally as cells
change; ``ProbabilityGrid.compute_field`` is its Euclidean-distance-transform oracle). Scoring
the hit probabilities instead, as Cartographer does, biased matches: a fresh wall's free
cells (0.49) score almost like its hits (0.55) while cells behind it are unknown (0.12), so
scans slid toward the sensor and lost part of every step along corridors (the figures are in
the README, "Measurements behind the defaults"). ``score_grid: probability`` keeps that option.

``branch_depth > 0`` runs the coarse-to-fine search (Olson's low-resolution upper bounds,
here the max-pooled grids of Hess et al. 2016) instead of scoring every candidate; it
returns the same best pose. The exhaustive mode also yields the match quality: the margin
to the best separated peak and a covariance from the score distribution (Olson 2009,
Sec. IV: weights exp(N·(s − s_best)), i.e. the summed probability treated as a log-likelihood).

The covariance is taken from the scores *without* the delta penalty (the penalty is a
preference for the prediction, not evidence from the scan), in the map (submap grid) x/y
axes. A window can be as small as one cell, which truncates the distribution (and a 3 × 3
lattice cannot even step along a corridor that is not axis-aligned), so the moment
covariance is widened to cover the curvature (Laplace) covariance of the log-likelihood at
the peak, fitted on its 3 × 3 × 3 neighbourhood; directions the scan does not bound (less
curvature than the prior's information) get the variance of an unmatched scan
(``unmatched_covariance``: σ = the largest search windows). A match is thus never trusted
less than pure prediction, nor more than its window and its curvature show.

With ``prior_sigma`` (``match``) the prediction is a prior as well as the window's centre
(Olson 2009, Sec. III: the posterior is the scan's likelihood times the motion model's prior).
Cartographer's delta penalty, exp(−(w_t·d + w_r·|Δθ|)²) with w = 0.1, costs a candidate 0.15 m
away 0.02 % of its score; a scanner whose range ends inside a corridor scores the newest stretch
of the walls on cells no scan has observed yet at its true pose, and on mapped wall slid back
one step: 0.1 to 0.3 % more, so local SLAM loses travel along such corridors (the frontend
passes the odometry's σ unless ``real_time_matcher.window_sigmas`` is 0; on by default: README).
The translation from the prediction is then taken as Gaussian with that σ, and each candidate's
mean score is multiplied by exp(−d²/(2σ²N)), N the scan's points: the posterior's own weighing
when the mean score is read as a per-point likelihood of N independent points (the covariance's
reading above). A clearly better fit anywhere in the window still wins. Scores that still rise at the
window's edge (local SLAM's sign that the true pose lies beyond it) become a peak inside it
once the prior falls off there: ``scan_on_edge`` keeps what the scan's own scores said, and
local SLAM treats such a peak below its trust limit as on the edge.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam2d.matching import _kernels
from slam2d.matching.search import (DeltaPenalty, MatchGrid, PrecomputationStack, SearchParameters, branch_and_bound,
                                    exhaustive, quantized_up, search_region)


@dataclass
class MatchResult:
    pose: np.ndarray          # best lattice pose (x, y, theta)
    score: float              # mean grid value in [0, 1]
    candidates: int
    scores: np.ndarray | None = None  # every candidate's score (exhaustive mode)
    params: SearchParameters | None = None
    num_points: int = 0
    on_edge: bool = False     # the best pose lies on the search window's edge
    #: the best pose before the prediction's prior (``prior_sigma``) lies on the edge: the scan's
    #: own scores still rise there (equal to ``on_edge`` without a prior)
    scan_on_edge: bool = False
    escalated: bool = False   # found by the repeated search with the largest windows
    raw_scores: np.ndarray | None = None  # the scores without the delta penalty (exhaustive mode)
    prior: np.ndarray | None = None       # covariance of an unmatched scan (the truncation ceiling)

    @property
    def margin(self) -> float | None:
        """Best score minus the best score outside the peak's neighbourhood (exhaustive mode)."""
        if self.scores is None:
            return None
        a, iy, ix = np.unravel_index(int(np.argmax(self.scores)), self.scores.shape)
        return _margin(self.scores, a, iy, ix)

    @property
    def covariance(self) -> np.ndarray | None:
        """3×3 covariance (map x/y axes, θ) from the unpenalized score distribution (exhaustive
        mode), computed on demand; truncated directions get the unmatched variance."""
        if self.scores is None:
            return None
        raw = self.scores if self.raw_scores is None else self.raw_scores
        return _covariance(raw, self.params, self.num_points, self.prior)


def unmatched_covariance(linear_window: float, angular_window: float) -> np.ndarray:
    """Covariance of a scan whose pose is pure prediction: σ = the largest search windows. No
    distribution inside those windows has a larger variance, so a matched scan is never trusted
    less than an unmatched one."""
    return np.diag([linear_window ** 2, linear_window ** 2, angular_window ** 2])


class RealTimeCorrelativeScanMatcher:
    def __init__(self, linear_window: float, angular_window: float, branch_depth: int = 0,
                 translation_delta_cost_weight: float = 0.0, rotation_delta_cost_weight: float = 0.0,
                 quantize: bool = False):
        """``quantize``: branch-and-bound over the grid as uint8 (``search.quantized_up``; values in
        [0, 1]): its scores are the float scores rounded up by less than 1/255."""
        self.quantize = quantize
        self.linear_window = linear_window
        self.angular_window = angular_window
        self.branch_depth = branch_depth
        self.penalty = DeltaPenalty(translation_delta_cost_weight, rotation_delta_cost_weight)
        self.prior = unmatched_covariance(linear_window, angular_window)

    def match(self, grid: MatchGrid, predicted, points: np.ndarray, min_score: float = 0.0,
              linear_window: float | None = None, angular_window: float | None = None,
              largest: tuple[float, float] | None = None, prior_sigma: float = 0.0) -> MatchResult | None:
        """Best pose around ``predicted``; smaller windows than the largest ones (``largest``, default
        the configured ones) may be given: then a best pose on the window's edge repeats the
        search with the largest windows. ``prior_sigma`` [m]: the prediction's translation error
        as a Gaussian prior on both searches (module docstring; the exhaustive search only)."""
        if prior_sigma > 0 and self.branch_depth > 0:
            raise ValueError("the prediction's prior needs the exhaustive search (branch_depth 0)")
        top_lin, top_ang = (self.linear_window, self.angular_window) if largest is None else largest
        lin = top_lin if linear_window is None else min(linear_window, top_lin)
        ang = top_ang if angular_window is None else min(angular_window, top_ang)
        res = self._match(grid, predicted, points, min_score, lin, ang, prior_sigma=prior_sigma)
        if res is not None and res.on_edge and (lin < top_lin or ang < top_ang):
            wide = self._match(grid, predicted, points, min_score, top_lin, top_ang, prior_sigma=prior_sigma)
            if wide is not None:
                wide.escalated = True
                return wide
        return res

    def stack_for(self, grid: MatchGrid, around=None, reach: float = 0.0) -> PrecomputationStack:
        """The branch-and-bound precomputation of ``grid``, to share among several searches of one scan.

        ``around``: the poses the searches (with this matcher's windows) will start from, for points
        at most ``reach`` metres away: only the cells they can read are pooled (``search_region``),
        and the searches return the same as over the whole grid."""
        crop = None
        w = int(math.ceil(self.linear_window / grid.resolution))
        if around is not None:
            crop = search_region(grid.values.shape, grid.origin, grid.resolution, around, reach, w, self.branch_depth)
        if crop is None:
            return PrecomputationStack(quantized_up(grid) if self.quantize else grid, self.branch_depth)
        r0, r1, c0, c1 = crop
        part = MatchGrid(np.ascontiguousarray(grid.values[r0:r1, c0:c1]),
                         np.asarray(grid.origin, dtype=float) + grid.resolution * np.array([c0, r0], dtype=float),
                         grid.resolution, grid.unknown)
        stack = PrecomputationStack(quantized_up(part) if self.quantize else part, self.branch_depth, (c0, r0))
        stack.linear_cells = w
        return stack

    def _match(self, grid, predicted, points, min_score, linear_window, angular_window, stack=None, prior_sigma=0.0):
        params = SearchParameters.make(linear_window, angular_window, grid.resolution, points)
        cells = grid.cells(points, predicted, params.angles)
        w = params.linear_cells
        res = grid.resolution
        n_cand = cells.shape[0] * (2 * w + 1) ** 2
        if self.branch_depth > 0:
            stack = self.stack_for(grid) if stack is None else stack
            if stack.linear_cells is not None and w > stack.linear_cells:
                raise ValueError(f"a window of {w} cells on a stack cropped for {stack.linear_cells}")
            scale = 255.0 if stack.grid.values.dtype == np.uint8 and grid.values.dtype != np.uint8 else 1.0
            found = branch_and_bound(stack, cells, w, min_score * scale, self.penalty, params.angles)
            if found is None:
                return None
            a, dx, dy, score = found
            if scale != 1.0:  # the quantized grid chose the pose; its score is the float grid's there
                score = float(_kernels.score_candidates(grid.values, cells, np.array([[a, dx, dy]], np.int32),
                                                        np.float32(grid.unknown))[0])
                score *= _kernels._penalty(self.penalty.translation_weight, self.penalty.rotation_weight, res,
                                           float(params.angles[a]), dx, dy, 1)
            pose = np.array([predicted[0] + dx * res, predicted[1] + dy * res, predicted[2] + params.angles[a]])
            edge = max(abs(dx), abs(dy)) == w or a in (0, len(params.angles) - 1)
            return MatchResult(pose, score, n_cand, on_edge=edge, scan_on_edge=edge)
        raw = exhaustive(grid, cells, w)
        scores = raw.copy()
        _kernels.apply_delta_penalty(scores, np.ascontiguousarray(params.angles, dtype=np.float64),
                                     float(self.penalty.translation_weight), float(self.penalty.rotation_weight),
                                     float(res))
        def best_on_edge():
            a, iy, ix = np.unravel_index(int(np.argmax(scores)), scores.shape)
            return (a, iy, ix), iy in (0, 2 * w) or ix in (0, 2 * w) or a in (0, len(params.angles) - 1)

        scan_edge = None
        if prior_sigma > 0:
            scan_edge = best_on_edge()[1]
            _kernels.apply_translation_prior(scores, float(res), float(prior_sigma), float(max(1, points.shape[0])))
        (a, iy, ix), edge = best_on_edge()
        best = float(scores[a, iy, ix])
        if best <= min_score:
            return None
        pose = np.array([predicted[0] + (ix - w) * res, predicted[1] + (iy - w) * res, predicted[2] + params.angles[a]])
        return MatchResult(pose, best, n_cand, scores, params, points.shape[0], on_edge=edge, raw_scores=raw,
                           prior=self.prior, scan_on_edge=edge if scan_edge is None else scan_edge)


def _margin(scores, a, iy, ix, lin=2, ang=2) -> float:
    masked = scores.copy()
    masked[max(a - ang, 0):a + ang + 1, max(iy - lin, 0):iy + lin + 1, max(ix - lin, 0):ix + lin + 1] = -np.inf
    other = float(masked.max())
    return float(scores[a, iy, ix] - other) if np.isfinite(other) else float(scores[a, iy, ix])


def _covariance(scores, params: SearchParameters, n_points: int, prior: np.ndarray | None = None) -> np.ndarray:
    """Olson's covariance of the score distribution plus the lattice's own quantization (step²/12);
    with ``prior``, raised to cover the curvature (Laplace) covariance at the peak, which the
    window cannot truncate (module docstring; ``_kernels.laplace_cover``)."""
    res = params.resolution
    w = params.linear_cells
    offs = np.arange(-w, w + 1) * res
    angles = np.asarray(params.angles, dtype=np.float64)
    cov = np.empty((3, 3))
    _kernels.score_covariance(scores, offs, angles, float(n_points), cov)
    floor = np.array([res * res / 12.0, res * res / 12.0, params.angular_step ** 2 / 12.0])
    cov[np.diag_indices(3)] += floor
    if prior is not None:
        _kernels.laplace_cover(scores, float(n_points), float(res), float(params.angular_step),
                               np.sqrt(np.diag(prior)), cov)
    return cov


__all__ = ["RealTimeCorrelativeScanMatcher", "MatchResult", "unmatched_covariance"]
