"""Loop search after a long stretch without loop closure (Hess et al. 2016, Sec. V-C, with the
search window of Olson 2009's multi-resolution matcher sized by the drift model).

The regular search (``global_slam.GlobalSlam._search``) looks around the current estimate
as far as the drift bound of ``drift.py`` reaches, up to ``linear_search_window`` /
``angular_search_window_deg``. The bound grows with the stretch of local SLAM linking two
places through the pose graph (loop closures are shortcuts) and with every step local SLAM
could not trust on it, and can exceed that window: a robot back at its start after a long
tour with no loop on the way, a corridor walked again from its other end, a pose recovered
after a fast turn. Then the single-scan search misses the revisit, and a single scan in a
corridor is too ambiguous over a window of many metres.

So, when a submap is finished and an older submap near it is farther than the regular window
can reach, the finished submap's whole content (its occupied cells) is matched against the
older one with the drift-sized window: coarse first, on grids max-pooled to a few cells per
metre, where branch-and-bound searches every rotation and offset of the window exactly. A
never-observed cell scores 0.5 there (no evidence either way), so partial overlap of two
submaps does not favour poses that pile the content onto mapped cells, while content laid on
observed free space scores low. The coarse pose is only a start: two of the submap's nodes
are then matched from it by the regular, verified single-scan search, and both must pass
verification and agree on where the submap lies (within ``consistency_translation`` /
``consistency_rotation_deg``) before either becomes a loop constraint.
"""
from __future__ import annotations

import math

import numpy as np

from slam2d.geometry import between, compose
from slam2d.matching.search import MatchGrid, PrecomputationStack, SearchParameters, branch_and_bound
from slam2d.range_data import adaptive_voxel_filter, voxel_filter

#: cells of the regular grid pooled into one coarse cell, per side
COARSE_FACTOR = 4
#: what a never-observed cell scores in the coarse search (probability × 255: no evidence)
NEUTRAL = 128


def coarse_grid(grid) -> MatchGrid:
    """A finished submap's probabilities (uint8) max-pooled over ``COARSE_FACTOR`` cells a side, never
    observed cells at ``NEUTRAL``."""
    f = COARSE_FACTOR
    q = np.where(grid.known > 0, grid.prob, np.uint8(NEUTRAL)).astype(np.uint8)
    rows, cols = q.shape
    pr, pc = -rows % f, -cols % f
    q = np.pad(q, ((0, pr), (0, pc)), constant_values=NEUTRAL)
    pooled = q.reshape(q.shape[0] // f, f, q.shape[1] // f, f).max(axis=(1, 3))
    return MatchGrid(np.ascontiguousarray(pooled), grid.origin.copy(), grid.resolution * f, float(NEUTRAL))


def submap_content(grid, min_points: int = 0, max_length: float = 0.0) -> np.ndarray:
    """Centres (local frame) of a finished submap's cells more likely occupied than not (hit more often
    than the misses cancel), thinned to one per 2 × 2 coarse cells, then by the adaptive voxel filter
    to about ``min_points`` (cells up to ``max_length``; 0: not), the budget of a node's loop-closure
    points: the search costs time in proportion to the points, and a submap's walls sampled as
    densely as one scan's still place it (measured against the sparse logs' ground truth, the
    coarse pose lands within the regular window as often as with every 2 × 2 cells' point)."""
    rows, cols = np.nonzero((grid.known > 0) & (grid.prob > NEUTRAL))
    pts = grid.origin + (np.stack([cols, rows], axis=1) + 0.5) * grid.resolution
    return adaptive_voxel_filter(voxel_filter(pts, 2 * grid.resolution * COARSE_FACTOR), min_points, max_length)


def coarse_match(content: np.ndarray, centre: np.ndarray, initial, target: MatchGrid, linear_window: float,
                 angular_window: float):
    """The best pose (in ``target``'s frame) of the frame at ``centre`` (x, y in the content's frame)
    within the windows around ``initial``, and its score in [0, 1]; rotations are about ``centre``.
    None when no placement scores above ``NEUTRAL`` (the content lies on free or unobserved cells)."""
    pts = content - centre[:2]
    params = SearchParameters.make(linear_window, angular_window, target.resolution, pts)
    depth = max(1, int(math.ceil(math.log2(2 * params.linear_cells + 1))))
    stack = PrecomputationStack(target, depth)
    cells = target.cells(pts, initial, params.angles)
    # only placements with more evidence for than against (above the never-observed value) are of
    # interest, so branch-and-bound may cut every subtree that cannot beat it
    found = branch_and_bound(stack, cells, params.linear_cells, float(NEUTRAL))
    if found is None:
        return None
    a, dx, dy, score = found
    pose = np.array([initial[0] + dx * target.resolution, initial[1] + dy * target.resolution,
                     initial[2] + params.angles[a]])
    return pose, score / 255.0


def frame_offset(x1, x2, centre) -> tuple[float, float]:
    """How far apart two transforms of one frame put the point ``centre`` (m) and its heading (rad)."""
    c = np.array([centre[0], centre[1], 0.0])
    d = between(compose(x1, c), compose(x2, c))
    return float(math.hypot(d[0], d[1])), abs(float(d[2]))


__all__ = ["coarse_grid", "submap_content", "coarse_match", "frame_offset"]
