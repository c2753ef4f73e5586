"""Loop-closure constraints (Hess et al. 2016, Sec. V): a node's scan is matched against a finished
submap by branch-and-bound correlative search over precomputed max-pooled grids, scored as
the mean probability under the scan's points; matches above ``min_score`` are refined below
cell size and then verified before they become constraints. How high a right match scores
depends on how often the submap's cells were observed, so the caller lowers ``min_score`` for
a submap whose own nodes score low at their own poses (``self_score``):

- re-score: the mean probability at the refined pose (the float grid, nearest cell) must
  still reach ``min_score`` (the lattice score alone can be a lucky cell);
- ambiguity: an exhaustive search on the lattice around the refined pose (``margin_window``)
  finds the best *separated* local maximum (outside ``margin_exclusion`` of the peak); the
  peak must beat it by ``min_margin`` (a corridor's slide, repeated doors), and the peak must be
  the refined pose itself (within ``margin_exclusion``): a branch-and-bound best on the edge of
  its window can refine onto the slope of a better pose just outside it. Chosen over a
  second branch-and-bound run with the peak excluded because the B&B kernel has no exclusion
  and a small exhaustive window costs a few ms, only for matches that passed the score;
- information: Olson's covariance of that window's score distribution (unpenalized; covered
  by the curvature at the peak, flat directions get the whole window), in the submap grid
  frame — the caller floors it and turns it into the node's frame.

Precomputation grids are built once per finished submap and kept as uint8 (probability ×
255), which bounds their memory (level d is padded by 2^d − 1 cells on the low side so that
the search is exact across the submap's borders; level 0 is the matcher's only copy of the
values); scores are reported in [0, 1].
"""
from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from slam2d.geometry import between
from slam2d.grid.probability_grid import quantize
from slam2d.matching import _kernels
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
    covariance: np.ndarray | None = None  # (x, y, θ) in the submap grid's axes
    reason: str | None = None           # why verification rejected it (None: accepted)


class StackCache:
    """The precomputation stacks of the most recently searched finished submaps.

    A stack costs several bytes per cell and is needed only while nodes are matched against
    its submap. Stacks are kept, most recently used first, up to ``max_bytes`` in all; beyond
    it the least recently searched go, and an evicted stack is rebuilt, identically, from the
    submap's uint8 grid when it is searched again. Memory is then bounded whatever the map's
    size, and a map that fits the budget never rebuilds a stack.
    """

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._stacks: OrderedDict[int, PrecomputationStack] = OrderedDict()
        self.builds = 0

    def get(self, matcher: "SubmapMatcher") -> PrecomputationStack:
        key = matcher.submap.index
        st = self._stacks.get(key)
        if st is not None:
            self._stacks.move_to_end(key)
            return st
        st = PrecomputationStack(matcher.source_grid(), matcher.depth)
        self.builds += 1
        self._stacks[key] = st
        while len(self._stacks) > 1 and self.nbytes > self.max_bytes:
            self._stacks.popitem(last=False)
        return st

    def holds(self, key: int) -> bool:
        """Whether submap ``key``'s stack is cached (its next search builds none)."""
        return key in self._stacks

    @property
    def nbytes(self) -> int:
        return sum(st.nbytes for st in self._stacks.values())

    def clear(self) -> None:
        """Drop every stack (a later search rebuilds its own)."""
        self._stacks.clear()


class SubmapMatcher:
    """Branch-and-bound matcher for one finished submap."""

    def __init__(self, submap, depth: int, cache: StackCache | None = None):
        g = submap.grid
        self.submap = submap
        self.depth = depth
        self.cache = StackCache(0) if cache is None else cache  # alone: keeps its one stack
        known = np.argwhere(g.known > 0)
        self.center_local = (g.origin + (known.mean(axis=0)[::-1] + 0.5) * g.resolution) if len(known) else g.origin

    def source_grid(self) -> MatchGrid:
        """The submap's probabilities as uint8 (× 255), read from the submap (unpacked if packed)."""
        g = self.submap.grid
        p = g.prob
        q = p if p.dtype == np.uint8 else quantize(p)  # a finished submap's grid is uint8 already
        return MatchGrid(q, g.origin, g.resolution, float(round(g.unknown_probability * 255)))

    @property
    def grid(self) -> MatchGrid:
        """The uint8 grid: level 0 of the submap's precomputation stack, the only copy of the values
        the matcher holds (the stack is rebuilt if the cache has let it go)."""
        return self.stack.grid

    def self_score(self, points_and_poses) -> float:
        """Mean probability under the submap's own nodes' points at their own poses (grid frame):
        the score a perfect match reaches in this submap, which depends on how often its cells
        were observed. NaN without nodes."""
        scores = []
        prob = self.prob
        for pts, pose in points_and_poses:
            if len(pts):
                cells = prob.cells(pts, np.asarray(pose, dtype=float), np.zeros(1))
                scores.append(float(exhaustive(prob, cells, 0)[0, 0, 0]))
        return float(np.mean(scores)) if scores else float("nan")

    @property
    def stack(self) -> PrecomputationStack:
        return self.cache.get(self)

    @property
    def prob(self) -> MatchGrid:
        """The uint8 grid read as the probabilities ``dequantize`` gives, for refinement and
        verification (``MatchGrid.scale``: no float copy of the submap is made)."""
        g = self.grid
        return MatchGrid(g.values, g.origin, g.resolution, self.submap.grid.unknown_probability, 1.0 / 255.0)

    def match(self, points, initial, linear_window, angular_window, min_score, refine_weights,
              min_margin=0.0, margin_window=(0.6, 0.035), margin_exclusion=(0.2, 0.0175)) -> LoopMatch | None:
        """None when branch-and-bound finds nothing above ``min_score``; else the refined match,
        with ``reason`` set when verification rejects it."""
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
        pose, _ = refine(prob, pose, points, *refine_weights)
        out = LoopMatch(pose, between(self.submap.local_pose, pose), score / 255.0, 0.0)
        self.verify(out, points, min_score, min_margin, margin_window, margin_exclusion, params.angular_step, prob)
        out.seconds = time.perf_counter() - t0
        return out

    def verify(self, m: LoopMatch, points, min_score, min_margin, window, exclusion, step, prob=None) -> LoopMatch:
        """Fill rescore, margin and covariance from an exhaustive window around the refined pose."""
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
        params = SearchParameters(angles, w, step, res)
        m.covariance = _covariance(scores, params, len(points), unmatched_covariance(window[0], window[1]))
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
        return m


def separated_margin(scores: np.ndarray, lin: int, ang: int) -> float:
    """Best score minus the best local maximum (3 × 3 × 3) farther than ``lin`` cells or ``ang``
    angular steps from the best; the best score itself when there is none."""
    a, iy, ix = np.unravel_index(int(np.argmax(scores)), scores.shape)
    best = float(scores[a, iy, ix])
    other = float(_kernels.best_separated_peak(scores, int(a), int(iy), int(ix), int(lin), int(ang)))
    return best if other == -math.inf else best - other


def loop_points(hits: np.ndarray, voxel: float, min_points: int = 0, max_length: float = 0.0) -> np.ndarray:
    """A node's points for loop-closure matching: voxel-filtered at ``voxel``, then thinned by the
    adaptive voxel filter to about ``min_points`` (0: not)."""
    return adaptive_voxel_filter(voxel_filter(np.asarray(hits, dtype=float), voxel), min_points, max_length)


__all__ = ["SubmapMatcher", "LoopMatch", "loop_points", "separated_margin"]
