"""Search lattice shared by the real-time and the branch-and-bound matcher.

Cartographer's ``correlative_scan_matcher_2d``: the angular step follows from the scan's
farthest point, δθ = arccos(1 − r²/(2·d_max²)) (Hess et al. 2016, Sec. V-A, eq. 7), so
that the farthest point moves by at most one cell; the translation lattice is the grid's
cells. Candidates are (angle index, dx, dy) in integer cells around the predicted pose.

Branch-and-bound (Hess et al. 2016, Sec. V-B/C): precomputation grids hold the maximum of
the 2^d × 2^d cells starting at each cell — also at the cells left of and below the grid
whose blocks still reach into it (Cartographer pads each level by 2^d − 1 cells on the low
side) — so a candidate at depth d bounds the score of every one of its descendants, near
the borders too; children are scored, sorted best first and visited depth first; a subtree
whose bound is not above the best score so far is cut. The result equals the exhaustive
search over the same lattice: the same best score (poses differ only between exact ties),
tested on random grids and on finished submaps with windows across their borders.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
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
    #: exhaustive scoring and refinement read a cell as float32(value) × float32(scale): 1/255 reads a
    #: uint8 grid as its ``dequantize``d probabilities, without the float copy (branch-and-bound ignores it)
    scale: float = 1.0
    #: refinement only: cells whose entry here is 0 or less (e.g. an active grid's stamps: never
    #: updated) are never-observed and read by ``_kernels._unobserved``'s rule (a surface's free side
    #: just behind it, else ``unknown``); None: every cell holds its value (the scorers ignore it)
    known: np.ndarray | None = None

    def cells(self, points, pose, angles) -> np.ndarray:
        return _kernels.rotated_cells(np.ascontiguousarray(points, dtype=np.float64), float(pose[0]), float(pose[1]),
                                      float(pose[2]), np.ascontiguousarray(angles, dtype=np.float64),
                                      float(self.origin[0]), float(self.origin[1]), 1.0 / self.resolution)


def quantized_up(grid: MatchGrid) -> MatchGrid:
    """A grid of values in [0, 1] as uint8 of ``ceil(v × 255)``: its scores, divided by 255, bound the
    float grid's from above by less than 1/255, so branch-and-bound over it prunes only what the
    float grid would, with a quarter of the memory to pool."""
    return MatchGrid(_kernels.quantize_up(np.asarray(grid.values)), grid.origin, grid.resolution,
                     float(min(255, math.ceil(grid.unknown * 255.0))))


class PrecomputationStack:
    """Max-pooled grids of widths 1, 2, 4, …, 2^depth (Hess et al. 2016, Sec. V-C) in the grid's dtype
    (uint8 for finished submaps), stored one after the other in one flat array.

    Level d holds, for every block of 2^d × 2^d cells that overlaps the grid, the maximum over
    the block (cells outside the grid count as ``unknown``); the block starting at grid cell
    (r, c) is ``level(d)[r + offsets[d], c + offsets[d]]``. As in Cartographer's
    ``PrecomputationGrid2D``, level d is padded on the low side by ``offsets[d]`` = 2^d − 1 rows
    and columns, so blocks that start left of or below the grid but still cover it read their
    true maximum; blocks that start beyond the padded level lie wholly outside and score
    ``unknown``. Level 0 is the grid itself: ``self.grid`` reads it, so a caller may drop its own
    copy of the values.
    """

    def __init__(self, grid: MatchGrid, depth: int, cell_offset: tuple[int, int] = (0, 0),
                 buffer: np.ndarray | None = None):
        """``cell_offset`` (col, row): ``grid`` is a crop (``search_region``) whose cell (0, 0) is that
        cell of the grid the searches compute their cells in; ``branch_and_bound`` shifts them.
        ``buffer``: a 1-D uint8 array (e.g. an evicted stack's ``buffer``) the levels are written into,
        instead of new memory, when they fill at least half of it."""
        values = grid.values
        rows, cols = values.shape
        self.depth = depth
        self.cell_offset = (int(cell_offset[0]), int(cell_offset[1]))
        self.linear_cells: int | None = None  # a crop serves windows up to this half-width only
        self.shape = (rows, cols)
        self.offsets = tuple((1 << d) - 1 for d in range(depth + 1))
        sizes = [(rows + p) * (cols + p) for p in self.offsets]
        self.starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        n = int(self.starts[-1])
        size = n * values.dtype.itemsize
        if buffer is None or not size <= buffer.nbytes <= 2 * size:
            buffer = np.empty(size, dtype=np.uint8)
        self.buffer = buffer
        self.data = buffer[:size].view(values.dtype)
        self.level(0)[:, :] = values
        fill = _upper_fill(grid.unknown, values.dtype)
        # one scratch for the row pass of every level: the last level's is the largest
        scratch = np.empty((rows + self.offsets[-1]) * (cols + self.offsets[-1]), dtype=values.dtype)
        for d in range(1, depth + 1):
            _double_block(self.level(d - 1), 1 << (d - 1), fill, self.level(d), scratch)
        self.grid = MatchGrid(self.level(0), grid.origin, grid.resolution, grid.unknown)

    def level(self, d: int) -> np.ndarray:
        """Level d as a 2-D view, (rows + offsets[d], cols + offsets[d])."""
        rows, cols = self.shape
        p = self.offsets[d]
        return self.data[self.starts[d]:self.starts[d + 1]].reshape(rows + p, cols + p)

    @property
    def nbytes(self) -> int:
        """Bytes held: the whole buffer, also where the levels fill only part of it."""
        return self.buffer.nbytes


def search_region(shape: tuple[int, int], origin, resolution: float, poses, reach: float, linear_cells: int,
                  depth: int) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1), half-open: the cells of a grid of ``shape`` that branch-and-bound
    with ``depth`` levels and a window of ``linear_cells`` around any of ``poses`` can read, for
    points at most ``reach`` metres from the pose; None when that is the whole grid.

    A point's cell lies within ceil(reach / resolution) + 1 cells of its pose's cell whatever the
    rotation (one more for rounding); candidates move it by −w … w cells and a block of level d
    starting there covers 2^d − 1 more. A stack built on these cells alone (``PrecomputationStack``
    with ``cell_offset``) therefore holds every value such a search reads, and the search returns
    what it returns on the whole grid (tested).
    """
    rows, cols = shape
    r = int(math.ceil(reach / resolution)) + 2
    lo_extra, hi_extra = r + linear_cells, r + linear_cells + (1 << depth) - 1
    c = np.floor((np.asarray(poses, dtype=float).reshape(-1, 3)[:, :2] - np.asarray(origin)[:2]) / resolution)
    c0, r0 = int(c[:, 0].min()) - lo_extra, int(c[:, 1].min()) - lo_extra
    c1, r1 = int(c[:, 0].max()) + hi_extra + 1, int(c[:, 1].max()) + hi_extra + 1
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, cols), min(r1, rows)
    if r0 == 0 and c0 == 0 and r1 == rows and c1 == cols:
        return None
    # a region wholly off the grid reads only ``unknown``: one cell of the grid, never read, stands for it
    r0, c0 = min(r0, rows - 1), min(c0, cols - 1)
    return r0, max(r1, r0 + 1), c0, max(c1, c0 + 1)


def _double_block(prev: np.ndarray, h: int, fill, out: np.ndarray, scratch: np.ndarray) -> None:
    """Level d from level d − 1 (blocks of width h = 2^(d−1)): a block of width 2h starting at a
    cell is the max of the four width-h blocks starting at it, h to its right, h above and both.
    With the low-side padding (level d − 1 is offset by h − 1, level d by 2h − 1) that is
    ``out[i, j] = max(prev[i − h, j − h], prev[i − h, j], prev[i, j − h], prev[i, j])``, blocks
    beyond ``prev`` counting as ``fill``: the maximum of two shifted views along the rows, then
    along the columns, instead of a sliding window of width 2^d over the grid. ``scratch``: a 1-D
    array of prev's dtype, at least out's rows × prev's columns long, for the row pass."""
    half = scratch[:out.shape[0] * prev.shape[1]].reshape(out.shape[0], prev.shape[1])
    _shifted_max(prev, h, fill, half, 0)
    _shifted_max(half, h, fill, out, 1)


def _shifted_max(a: np.ndarray, h: int, fill, out: np.ndarray, axis: int) -> None:
    """``out[i] = max(a[i − h], a[i])`` along ``axis`` (out is h longer there), entries beyond ``a``
    counting as ``fill``."""
    n = a.shape[axis]

    def at(x, lo, hi):
        return x[lo:hi] if axis == 0 else x[:, lo:hi]

    if n > h:
        np.maximum(at(a, 0, n - h), at(a, h, n), out=at(out, h, n))
        np.maximum(at(a, 0, h), fill, out=at(out, 0, h))
        np.maximum(at(a, n - h, n), fill, out=at(out, n, n + h))
    else:  # every entry meets the fill on one side
        out[...] = fill
        np.maximum(at(out, 0, n), a, out=at(out, 0, n))
        np.maximum(at(out, h, h + n), a, out=at(out, h, h + n))


def _upper_fill(unknown: float, dtype) -> np.generic:
    """``unknown`` in ``dtype``, rounded up where it is not representable (the levels stay upper bounds)."""
    dtype = np.dtype(dtype)
    if np.issubdtype(dtype, np.integer):
        v = math.ceil(unknown)
        if not np.iinfo(dtype).min <= v <= np.iinfo(dtype).max:
            raise ValueError(f"unknown value {unknown} does not fit the grid's {dtype}")
        return dtype.type(v)
    v = dtype.type(unknown)
    return v if float(v) >= unknown else np.nextafter(v, dtype.type(np.inf))


def sliding_max(values: np.ndarray, width: int, fill: float, out: np.ndarray | None = None) -> np.ndarray:
    """out[r, c] = max(values[r:r+width, c:c+width]) (cells beyond the array count as ``fill``), in values' dtype."""
    from scipy.ndimage import maximum_filter  # global SLAM only: local runs skip its import time

    return maximum_filter(values, size=width, origin=-(width // 2), mode="constant", cval=fill, output=out)


@dataclass
class DeltaPenalty:
    """Cartographer's real-time matcher penalty: score · exp(−(w_t·|Δt| + w_r·|Δθ|)²).

    Where the scan cannot tell poses apart (a corridor seen without its ends), it picks
    the one closest to the prediction instead of whichever the search order met first.
    """

    translation_weight: float = 0.0
    rotation_weight: float = 0.0

    def _of(self, distance: float, angle: float) -> float:
        v = self.translation_weight * distance + self.rotation_weight * abs(angle)
        return math.exp(-v * v)

    def factor(self, pose, predicted) -> float:
        """The factor of ``pose`` in a search around ``predicted``."""
        return self._of(math.hypot(pose[0] - predicted[0], pose[1] - predicted[1]),
                        math.remainder(pose[2] - predicted[2], 2 * math.pi))

    def smallest_factor(self, params: SearchParameters) -> float:
        """The factor at the lattice's far corner (its largest offset and angle, as the kernels
        measure them): no candidate of ``params`` is penalized more."""
        return self._of(math.sqrt(2.0) * params.linear_cells * params.resolution, float(np.abs(params.angles).max()))


def exhaustive(grid: MatchGrid, cells: np.ndarray, linear_cells: int, penalty: DeltaPenalty | None = None,
               angles: np.ndarray | None = None) -> np.ndarray:
    """All scores, (A, 2w+1, 2w+1) indexed [angle, dy + w, dx + w] (times the penalty when given)."""
    scores = _kernels.score_window(grid.values, cells, linear_cells, np.float32(grid.unknown), float(grid.scale))
    if penalty is not None:
        _kernels.apply_delta_penalty(scores, np.ascontiguousarray(angles, dtype=np.float64),
                                     float(penalty.translation_weight), float(penalty.rotation_weight),
                                     float(grid.resolution))
    return scores


def branch_and_bound(stack: PrecomputationStack, cells: np.ndarray, linear_cells: int, min_score: float,
                     penalty: DeltaPenalty | None = None, angles: np.ndarray | None = None):
    """Best (angle index, dx, dy, score) with score > min_score, or None. Exact over the lattice.

    Exact means the exhaustive search's best score (scores are sums of non-negative grid
    values; this kernel sums in float64, ``exhaustive`` in float32); among exactly tied poses
    either may be returned. With a penalty, a block's bound is its max-pooled score times the
    largest penalty factor in the block (at the block's point nearest the prediction), which
    still bounds every descendant. The search runs in a numba kernel (explicit stack,
    children best first).
    """
    w_t = penalty.translation_weight if penalty is not None else 0.0
    w_r = penalty.rotation_weight if penalty is not None else 0.0
    ang = np.zeros(cells.shape[0]) if angles is None else np.ascontiguousarray(angles, dtype=np.float64)
    rows, cols = stack.shape
    if stack.cell_offset != (0, 0):
        cells = cells - np.array(stack.cell_offset, dtype=cells.dtype)
    # on more than one numba thread the coarsest candidates are shared among them; the result is the same
    kernel = _kernels.branch_and_bound_shared if numba.get_num_threads() > 1 else _kernels.branch_and_bound
    a, x, y, s = kernel(stack.data, stack.starts, rows, cols, cells, ang, int(linear_cells), float(min_score),
                        float(stack.grid.unknown), float(w_t), float(w_r), float(stack.grid.resolution))
    if a < 0:
        return None
    return int(a), int(x), int(y), float(s)
