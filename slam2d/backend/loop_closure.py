"""Loop-closure constraints (Hess et al. 2016, Sec. V): a node's scan is matched against a finished
submap by branch-and-bound correlative search over precomputed max-pooled grids, scored as the
mean value under the scan's points; matches above ``min_score`` are refined below cell size and
then verified before they become constraints.

What is scored (``loop_closure.score_grid``): the submap's hit probabilities (Cartographer), or
its likelihood field (Olson 2009, Sec. III: a Gaussian of the distance to the nearest cell likelier
occupied than free, the field local SLAM matches against). A probability says how often a cell
was seen hit and missed, so a submap whose cells were each seen by a few scans (scans far apart,
an open hall) reads about 0.55 on its walls and 0.45 on its floor: a scan scores nearly the same
at its true pose and a metre off, and the margin below cannot separate them. The field reads 1 on
a wall and 0 a few σ off it however often the cell was seen. The caller chooses per submap
(``global_slam.py``; ``auto``: the field where the submap's own nodes score low on its
probabilities). The field decides *whether and where* a scan matches (search, re-score, margin);
the probabilities *place* it: the refinement below cell size climbs them (``refinement_grid``;
on the field, whose Gaussian blur flattens the peak, the relations error of dense logs grew), and
an accepted match's covariance comes from their score surface (the field's sharper surface gave
loops too much weight against local SLAM). How high a right match scores still depends on the
submap, so the caller lowers ``min_score`` for a submap whose own nodes score low at their own
poses (``self_score``):

- re-score: the mean value at the refined pose (nearest cell) must still reach ``min_score``
  (the lattice score alone can be a lucky cell);
- ambiguity: an exhaustive search on the lattice around the refined pose (``margin_window``)
  finds the best *separated* local maximum (outside ``margin_exclusion`` of the peak); the
  peak must beat it by ``min_margin`` (a corridor's slide, repeated doors), and the peak must be
  the refined pose itself (within ``margin_exclusion``): a branch-and-bound best on the edge of
  its window can refine onto the slope of a better pose just outside it. Chosen over a
  second branch-and-bound run with the peak excluded because the B&B kernel has no exclusion
  and a small exhaustive window costs a few ms, only for matches that passed the score;
- estimate: a match that moves the node at least ``margin_exclusion`` from where the pose graph
  places it must beat that estimate on the points both poses put on observed cells
  (``matching/observed.py``). A scan that sees past the mapped part of a submap scores higher
  slid back onto mapped ground, and can do so with a clear margin, the estimate being the
  separated peak its new ground scores low (the regular search only: the wide search starts its
  node matches from a coarse match, not from the estimate);
- information: Olson's covariance of that window's score distribution (unpenalized; covered
  by the curvature at the peak, flat directions get the whole window), in the submap grid
  frame — the caller floors it and turns it into the node's frame.

Precomputation grids are built once per finished submap and kept as uint8 (value × 255), which
bounds their memory (level d is padded by 2^d − 1 cells on the low side so that the search is
exact across the submap's borders; level 0 is the matcher's only uncompressed copy of the
values); scores are reported in [0, 1].
"""
from __future__ import annotations

import math
import time
import zlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from slam2d.geometry import between
from slam2d.grid import _kernels as _grid_kernels
from slam2d.grid.probability_grid import field_kernel, quantize
from slam2d.matching import _kernels
from slam2d.matching.observed import observed_scores
from slam2d.matching.real_time import _covariance, unmatched_covariance
from slam2d.matching.refine import refine
from slam2d.matching.search import MatchGrid, PrecomputationStack, SearchParameters, branch_and_bound, exhaustive
from slam2d.range_data import adaptive_voxel_filter, voxel_filter


@dataclass
class LoopMatch:
    pose: np.ndarray      # refined pose of the node in the submap's grid frame
    relative: np.ndarray  # submap_pose⁻¹ ∘ node pose
    score: float          # branch-and-bound lattice score
    seconds: float
    rescore: float = float("nan")       # mean probability at the refined pose
    margin: float = float("nan")        # peak minus the best separated local maximum nearby
    heading_margin: float = float("nan")  # the refined heading's best score minus the best at other headings
    covariance: np.ndarray | None = None  # (x, y, θ) in the submap grid's axes
    reason: str | None = None           # why verification rejected it (None: accepted)


class StackCache:
    """The precomputation stacks of the most recently searched finished submaps.

    A stack costs several bytes per cell and is needed only while nodes are matched against
    its submap. Stacks are kept, most recently used first, up to ``max_bytes`` in all; beyond
    it the least recently searched go, and an evicted stack is rebuilt, identically, from the
    submap's uint8 grid when it is searched again. Memory is then bounded whatever the map's
    size, and a map that fits the budget never rebuilds a stack. The budget gives way only to
    ``min_stacks``: one sampled node is matched against several submaps in turn, and the node
    after it against nearly the same ones, so a cache holding fewer stacks than that working set
    rebuilds every one of them at every node (large submaps, a long-range laser in open halls);
    the stacks one node needs are kept whatever their size. A matcher that scores the
    likelihood field refines on the submap's probabilities: once a match needs them they are kept
    unpacked beside its stack, counted in the budget and evicted with it. The buffer of the stack
    evicted last is kept until the next build, which writes into it when the levels fill at least
    half of it (``PrecomputationStack``'s ``buffer``): a build then faults in no fresh memory.
    """

    def __init__(self, max_bytes: int, min_stacks: int = 1):
        self.max_bytes = max_bytes
        self.min_stacks = max(1, int(min_stacks))
        self._stacks: OrderedDict[int, PrecomputationStack] = OrderedDict()
        self._probabilities: dict[int, np.ndarray] = {}
        self._spare: np.ndarray | None = None  # the largest evicted stack's buffer, until a build reuses it
        self.builds = 0

    def get(self, matcher: "SubmapMatcher") -> PrecomputationStack:
        key = matcher.submap.index
        st = self._stacks.get(key)
        if st is not None:
            self._stacks.move_to_end(key)
            return st
        spare, self._spare = self._spare, None
        st = PrecomputationStack(matcher.source_grid(), matcher.depth, buffer=spare)
        self.builds += 1
        self._stacks[key] = st
        while len(self._stacks) > self.min_stacks and self.nbytes > self.max_bytes:
            old, gone = self._stacks.popitem(last=False)
            self._probabilities.pop(old, None)
            if self._spare is None or gone.buffer.nbytes > self._spare.nbytes:
                self._spare = gone.buffer  # the next build writes into it: no fresh memory to fault in
        return st

    def probabilities(self, matcher: "SubmapMatcher") -> np.ndarray:
        """The submap's probabilities (uint8, × 255), unpacked on the first match that refines against
        them and kept beside its stack from then on."""
        key = matcher.submap.index
        self.get(matcher)
        p = self._probabilities.get(key)
        if p is None:
            p = matcher.submap.grid.prob
            if key in self._stacks:
                self._probabilities[key] = p
        return p

    def holds(self, key: int) -> bool:
        """Whether submap ``key``'s stack is cached (its next search builds none)."""
        return key in self._stacks

    @property
    def nbytes(self) -> int:
        return sum(st.nbytes for st in self._stacks.values()) + sum(p.nbytes for p in self._probabilities.values())

    def clear(self) -> None:
        """Drop every stack (a later search rebuilds its own)."""
        self._stacks.clear()
        self._probabilities.clear()
        self._spare = None


class SubmapMatcher:
    """Branch-and-bound matcher for one finished submap."""

    def __init__(self, submap, depth: int, cache: StackCache | None = None, field_sigma: float | None = None):
        """``field_sigma``: score against the submap's likelihood field of this σ [m] (module docstring),
        made here and kept zlib-compressed; None: against its probabilities."""
        g = submap.grid
        self.submap = submap
        self.depth = depth
        self._field = None
        if field_sigma:
            f = likelihood_field(g, field_sigma)
            self._field = (zlib.compress(f.tobytes(), 1), f.shape)
        self.cache = StackCache(0) if cache is None else cache  # alone: keeps its one stack
        self.center_local = _known_centre(g)

    @property
    def scores_field(self) -> bool:
        """Whether matches are scored against the likelihood field (else the probabilities)."""
        return self._field is not None

    def source_grid(self) -> MatchGrid:
        """The values scored, as uint8 (× 255): the likelihood field (unpacked), or the submap's
        probabilities read from the submap (unpacked if packed)."""
        g = self.submap.grid
        if self._field is not None:
            z, shape = self._field
            f = np.frombuffer(zlib.decompress(z), dtype=np.uint8).reshape(shape).copy()
            return MatchGrid(f, g.origin, g.resolution, 0.0)
        p = g.prob
        q = p if p.dtype == np.uint8 else quantize(p)  # a finished submap's grid is uint8 already
        return MatchGrid(q, g.origin, g.resolution, float(round(g.unknown_probability * 255)))

    @property
    def grid(self) -> MatchGrid:
        """The uint8 grid: level 0 of the submap's precomputation stack, the only copy of the values
        the matcher holds (the stack is rebuilt if the cache has let it go)."""
        return self.stack.grid

    def self_score(self, points_and_poses) -> float:
        """Mean value of the scored grid under the submap's own nodes' points at their own poses (grid
        frame): the score a perfect match reaches in this submap, which depends on how often its
        cells were observed. NaN without nodes."""
        return _self_score(self.prob, points_and_poses)

    @property
    def stack(self) -> PrecomputationStack:
        return self.cache.get(self)

    @property
    def prob(self) -> MatchGrid:
        """The uint8 grid read as the values in [0, 1] it holds, for verification and scoring
        (``MatchGrid.scale``: no float copy of the submap is made)."""
        g = self.grid
        unknown = 0.0 if self._field is not None else self.submap.grid.unknown_probability
        return MatchGrid(g.values, g.origin, g.resolution, unknown, 1.0 / 255.0)

    def refinement_grid(self, scored: MatchGrid) -> MatchGrid:
        """The probabilities the refinement climbs: ``scored`` itself when that holds them, else the
        submap's own (kept unpacked beside its stack, ``StackCache.probabilities``)."""
        if self._field is None:
            return scored
        g = self.submap.grid
        return MatchGrid(self.cache.probabilities(self), g.origin, g.resolution, g.unknown_probability, 1.0 / 255.0)

    def match(self, points, initial, linear_window, angular_window, min_score, refine_weights,
              min_margin=0.0, margin_window=(0.6, 0.035), margin_exclusion=(0.2, 0.0175),
              estimate: bool = False) -> LoopMatch | None:
        """None when branch-and-bound finds nothing above ``min_score``; else the refined match,
        with ``reason`` set when verification rejects it. ``estimate``: ``initial`` is where the
        pose graph places the node now, and verification holds the match against it."""
        t0 = time.perf_counter()
        params = SearchParameters.make(linear_window, angular_window, self.grid.resolution, points)
        cells = self.grid.cells(points, initial, params.angles)
        found = branch_and_bound(self.stack, cells, params.linear_cells, min_score * 255.0)
        if found is None:
            return None
        a, dx, dy, score = found
        res = self.grid.resolution
        pose = np.array([initial[0] + dx * res, initial[1] + dy * res, initial[2] + params.angles[a]])
        prob = self.prob
        pose, _ = refine(self.refinement_grid(prob), pose, points, *refine_weights)
        out = LoopMatch(pose, between(self.submap.local_pose, pose), score / 255.0, 0.0)
        self.verify(out, points, min_score, min_margin, margin_window, margin_exclusion, params.angular_step, prob,
                    np.asarray(initial, dtype=float) if estimate else None)
        out.seconds = time.perf_counter() - t0
        return out

    def verify(self, m: LoopMatch, points, min_score, min_margin, window, exclusion, step, prob=None,
               estimate=None) -> LoopMatch:
        """Fill rescore, margin and covariance from an exhaustive window around the refined pose.

        ``estimate``: the node's pose in the grid frame by the current pose graph. A match that
        moves the node at least the exclusion radius from it must also score higher than it on the
        points both poses put on observed cells of the submap (``matching/observed.py``): a scan
        that sees past the submap's mapped part scores higher slid back onto mapped ground, and
        there the separated peak the margin would compare with is the estimate itself, which its
        new ground scores low.

        Rescore and margin judge the scored grid (``prob``: the field or the probabilities); the
        covariance of an accepted match comes from the probabilities' window, whose surface the
        refinement climbed to place it (a rejected match keeps the scored window's, for the record).
        """
        res = self.grid.resolution
        prob = self.prob if prob is None else prob
        n_ang = max(2, int(np.ceil(window[1] / step)))
        w = max(2, int(np.ceil(window[0] / res)))
        angles = step * np.arange(-n_ang, n_ang + 1, dtype=np.float64)
        cells = prob.cells(points, m.pose, angles)
        scores = exhaustive(prob, cells, w)
        m.rescore = float(scores[n_ang, w, w])
        ex_lin, ex_ang = int(np.ceil(exclusion[0] / res)), int(np.ceil(exclusion[1] / step))
        m.margin = separated_margin(scores, ex_lin, ex_ang)
        m.heading_margin = heading_margin(scores, ex_ang)
        # the margin is the window's best pose's; the constraint is the refined pose (the window's
        # centre), so that must be the peak, or the margin speaks of another pose
        a, iy, ix = np.unravel_index(int(np.argmax(scores)), scores.shape)
        off_peak = abs(a - n_ang) > ex_ang or max(abs(iy - w), abs(ix - w)) > ex_lin
        if m.rescore < min_score:
            m.reason = f"refined pose scores {m.rescore:.3f} < {min_score}"
        elif off_peak:
            dxy = float(np.hypot(iy - w, ix - w)) * res
            m.reason = (f"ambiguous: a pose {dxy:.2f} m, {np.degrees(abs(a - n_ang) * step):.1f}° from the refined one "
                        f"scores {float(scores[a, iy, ix]):.3f} > {m.rescore:.3f}")
        elif m.margin < min_margin:
            m.reason = f"ambiguous: margin {m.margin:.3f} < {min_margin} to a separated peak"
        elif estimate is not None and (moved := float(np.hypot(*(m.pose[:2] - estimate[:2])))) >= exclusion[0]:
            common = observed_scores(self.submap.grid, prob, [m.pose, estimate], points)
            if common is not None and common[1] >= common[0]:
                m.reason = (f"the estimate {moved:.2f} m away scores {common[1]:.3f} >= {common[0]:.3f} "
                            f"on the points both put on observed cells")
        if m.reason is None and self._field is not None:
            estimated = self.refinement_grid(prob)
            scores = exhaustive(estimated, estimated.cells(points, m.pose, angles), w)
        params = SearchParameters(angles, w, step, res)
        m.covariance = _covariance(scores, params, len(points), unmatched_covariance(window[0], window[1]))
        return m


def _self_score(grid: MatchGrid, points_and_poses) -> float:
    scores = []
    for pts, pose in points_and_poses:
        if len(pts):
            cells = grid.cells(pts, np.asarray(pose, dtype=float), np.zeros(1))
            scores.append(float(exhaustive(grid, cells, 0)[0, 0, 0]))
    return float(np.mean(scores)) if scores else float("nan")


def probability_self_score(submap, points_and_poses) -> float:
    """``SubmapMatcher.self_score`` on the submap's probabilities, read from its grid (no matcher, no
    stack): how often its cells were observed, which decides ``loop_closure.score_grid: auto``."""
    g = submap.grid
    p = g.prob
    grid = MatchGrid(p, g.origin, g.resolution, g.unknown_probability, 1.0 / 255.0) if p.dtype == np.uint8 else \
        MatchGrid(p, g.origin, g.resolution, g.unknown_probability)
    return _self_score(grid, points_and_poses)


def _known_centre(g) -> np.ndarray:
    """Mean centre of a grid's known cells, in its frame (its origin when it has none), from the
    counts per row and per column (exact integer sums: the mean of ``np.argwhere`` to the last bit)."""
    k = g.known
    n = int(np.count_nonzero(k))
    if n == 0:
        return g.origin
    rows = np.count_nonzero(k, axis=1) @ np.arange(k.shape[0], dtype=np.int64)
    cols = np.count_nonzero(k, axis=0) @ np.arange(k.shape[1], dtype=np.int64)
    return g.origin + (np.array([cols, rows], dtype=float) / n + 0.5) * g.resolution


def likelihood_field(grid, sigma: float) -> np.ndarray:
    """A finished grid's likelihood field as uint8 (× 255): per cell, exp(−d²/2σ²) of the distance d
    between its centre and the nearest cell likelier occupied than free, zero beyond 3σ (rounded up
    to whole cells) — local SLAM's field (``ProbabilityGrid``), stamped by the same kernel."""
    p = grid.prob
    half = 127 if p.dtype == np.uint8 else 0.5  # uint8 127 is 0.498, 128 is 0.502
    bits = grid.known_bits()
    radius = max(1, int(math.ceil(3.0 * sigma / grid.resolution)))
    # stamped at uint8: quantizing is monotone, so the largest quantized kernel value over the
    # occupied cells near a cell is the quantized largest value, and no float field is made
    return _grid_kernels.occupied_field(p, bits, p.dtype.type(half), quantize(field_kernel(sigma, grid.resolution, radius)),
                                        radius)


def separated_margin(scores: np.ndarray, lin: int, ang: int) -> float:
    """Best score minus the best local maximum (3 × 3 × 3) farther than ``lin`` cells or ``ang``
    angular steps from the best; the best score itself when there is none."""
    a, iy, ix = np.unravel_index(int(np.argmax(scores)), scores.shape)
    best = float(scores[a, iy, ix])
    other = float(_kernels.best_separated_peak(scores, int(a), int(iy), int(ix), int(lin), int(ang)))
    return best if other == -math.inf else best - other


def heading_margin(scores: np.ndarray, ang: int) -> float:
    """How clearly a verification window (angles × y × x, centred on the refined pose) fixes the
    heading alone: the best score at headings within ``ang`` angular steps of the centre, anywhere in
    the window, minus the best at every other heading. A corridor scores alike along itself, so its
    margin is small, but only poses at the refined heading do: this stays large. NaN when the window
    holds no other heading."""
    best = scores.reshape(scores.shape[0], -1).max(axis=1)
    near = np.abs(np.arange(len(best)) - len(best) // 2) <= ang
    return float(best[near].max() - best[~near].max()) if (~near).any() else float("nan")


def loop_points(hits: np.ndarray, voxel: float, min_points: int = 0, max_length: float = 0.0) -> np.ndarray:
    """A node's points for loop-closure matching: voxel-filtered at ``voxel``, then thinned by the
    adaptive voxel filter to about ``min_points`` (0: not)."""
    return adaptive_voxel_filter(voxel_filter(np.asarray(hits, dtype=float), voxel), min_points, max_length)


__all__ = ["SubmapMatcher", "LoopMatch", "heading_margin", "loop_points", "separated_margin"]
