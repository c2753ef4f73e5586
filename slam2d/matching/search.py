"""Search lattice shared by the real-time and the branch-and-bound matcher.

Cartographer's ``correlative_scan_matcher_2d``: the angular step follows from the scan's
farthest point, δθ = arccos(1 − r²/(2·d_max²)) (Hess et al. 2016, Sec. V-A, eq. 7), so
that the farthest point moves by at most one cell; the translation lattice is the grid's
cells. Candidates are (angle index, dx, dy) in integer cells around the predicted pose.

Branch-and-bound (Hess et al. 2016, Sec. V-B/C): precomputation grids hold the maximum of
the 2^d × 2^d cells starting at each cell, so a candidate at depth d bounds the score of
every one of its descendants; children are scored, sorted best first and visited depth
first; a subtree whose bound is not above the best score so far is cut. The result equals
the exhaustive search over the same lattice.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam2d.matching import _kernels


def angular_step(resolution: float, max_range: float) -> float:
    """δθ = arccos(1 − r²/(2 d²)) (Hess et al. 2016, eq. 7)."""
    d = max(max_range, resolution)
    return math.acos(1.0 - resolution * resolution / (2.0 * d * d))


@dataclass
class SearchParameters:
    angles: np.ndarray  # (A,) offsets from the predicted heading [rad]
    linear_cells: int   # translation window half-width in cells
    angular_step: float
    resolution: float

    @classmethod
    def make(cls, linear_window: float, angular_window: float, resolution: float, points: np.ndarray,
             min_angular_step: float = 0.0):
        d_max = float(np.sqrt((points ** 2).sum(axis=1)).max()) if len(points) else resolution
        step = max(angular_step(resolution, d_max), min_angular_step)
        n = int(math.ceil(angular_window / step))
        angles = step * np.arange(-n, n + 1, dtype=np.float64)
        return cls(angles, int(math.ceil(linear_window / resolution)), step, resolution)


@dataclass
class MatchGrid:
    """Values to score against (e.g. probabilities), with the frame of cell (0, 0)."""

    values: np.ndarray  # float32 [row, col]
    origin: np.ndarray  # lower-left corner of cell (0, 0)
    resolution: float
    unknown: float

    def cells(self, points, pose, angles) -> np.ndarray:
        return _kernels.rotated_cells(np.ascontiguousarray(points, dtype=np.float64), float(pose[0]), float(pose[1]),
                                      float(pose[2]), np.ascontiguousarray(angles, dtype=np.float64),
                                      float(self.origin[0]), float(self.origin[1]), 1.0 / self.resolution)


class PrecomputationStack:
    """Max-pooled grids of widths 1, 2, 4, …, 2^depth (Hess et al. 2016, Sec. V-C), one 3-D array
    in the grid's dtype (uint8 for finished submaps)."""

    def __init__(self, grid: MatchGrid, depth: int):
        self.grid = grid
        self.depth = depth
        self.array = np.empty((depth + 1,) + grid.values.shape, dtype=grid.values.dtype)
        self.array[0] = grid.values
        for d in range(1, depth + 1):
            self.array[d] = sliding_max(grid.values, 1 << d, grid.unknown)

    @property
    def nbytes(self) -> int:
        return self.array.nbytes


def sliding_max(values: np.ndarray, width: int, fill: float) -> np.ndarray:
    """out[r, c] = max(values[r:r+width, c:c+width]) (cells beyond the array count as ``fill``)."""
    from scipy.ndimage import maximum_filter  # global SLAM only: local runs skip its import time

    return maximum_filter(values, size=width, origin=-(width // 2), mode="constant", cval=fill).astype(np.float32)


@dataclass
class DeltaPenalty:
    """Cartographer's real-time matcher penalty: score · exp(−(w_t·|Δt| + w_r·|Δθ|)²).

    Where the scan cannot tell poses apart (a corridor seen without its ends), it picks
    the one closest to the prediction instead of whichever the search order met first.
    """

    translation_weight: float = 0.0
    rotation_weight: float = 0.0


def exhaustive(grid: MatchGrid, cells: np.ndarray, linear_cells: int, penalty: DeltaPenalty | None = None,
               angles: np.ndarray | None = None) -> np.ndarray:
    """All scores, (A, 2w+1, 2w+1) indexed [angle, dy + w, dx + w] (times the penalty when given)."""
    scores = _kernels.score_window(grid.values, cells, linear_cells, np.float32(grid.unknown))
    if penalty is not None:
        _kernels.apply_delta_penalty(scores, np.ascontiguousarray(angles, dtype=np.float64),
                                     float(penalty.translation_weight), float(penalty.rotation_weight),
                                     float(grid.resolution))
    return scores


def branch_and_bound(stack: PrecomputationStack, cells: np.ndarray, linear_cells: int, min_score: float,
                     penalty: DeltaPenalty | None = None, angles: np.ndarray | None = None):
    """Best (angle index, dx, dy, score) with score > min_score, or None. Exact over the lattice.

    With a penalty, a block's bound is its max-pooled score times the largest penalty
    factor in the block, which still bounds every descendant. The search runs in a numba
    kernel (explicit stack, children best first).
    """
    w_t = penalty.translation_weight if penalty is not None else 0.0
    w_r = penalty.rotation_weight if penalty is not None else 0.0
    ang = np.zeros(cells.shape[0]) if angles is None else np.ascontiguousarray(angles, dtype=np.float64)
    a, x, y, s = _kernels.branch_and_bound(stack.array, cells, ang, int(linear_cells), float(min_score),
                                           float(stack.grid.unknown), float(w_t), float(w_r), float(stack.grid.resolution))
    if a < 0:
        return None
    return int(a), int(x), int(y), float(s)
