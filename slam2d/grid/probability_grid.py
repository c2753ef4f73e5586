"""Log-odds probability grid with map limits that grow as the robot explores.

Cartographer's ``ProbabilityGrid`` + ``ProbabilityGridRangeDataInserter2D`` (Hess et al.
2016, Sec. IV): hits and misses update cells in log-odds, clamped; unknown cells are kept
apart from free ones by a ``known`` mask.
"""
from __future__ import annotations

import math
import zlib

import numba
import numpy as np

from slam2d.grid import _kernels


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def field_kernel(sigma: float, resolution: float, radius: int) -> np.ndarray:
    """exp(−d²/2σ²) over a (2R+1)² window of cell-centre distances d, zero beyond R cells."""
    k = np.arange(-radius, radius + 1) * resolution
    d = np.hypot(k[None, :], k[:, None])
    out = np.exp(-0.5 * (d / sigma) ** 2)
    out[d > radius * resolution + 1e-9] = 0.0
    return out.astype(np.float32)


class ProbabilityGrid:
    """Cells ``[row, col]``; cell (0, 0)'s lower-left corner is at ``origin`` (x, y) in the grid's frame."""

    GROW_MARGIN = 64  # cells added beyond the requested bounds when the grid grows (at least)

    def __init__(self, resolution: float, hit_probability=0.55, miss_probability=0.49,
                 min_probability=0.12, max_probability=0.97, origin=(0.0, 0.0), shape=(0, 0),
                 unknown_probability: float | None = None, field_sigma: float | None = None):
        self.resolution = float(resolution)
        self.hit_delta = logit(hit_probability)
        self.miss_delta = logit(miss_probability)
        self.lo_min = logit(min_probability)
        self.lo_max = logit(max_probability)
        self.min_probability = min_probability
        # what matching reads for never-observed cells (Cartographer: the minimum probability)
        self.unknown_probability = min_probability if unknown_probability is None else unknown_probability
        self.origin = np.array(origin, dtype=float)
        self.logodds = np.zeros(shape, dtype=np.float32)
        self._packed = None  # a finished grid's probabilities compressed (``pack``), with their shape
        self.prob = np.full(shape, self.unknown_probability, dtype=np.float32)
        self.stamp = np.zeros(shape, dtype=np.int32)
        self._known_bits = None  # frozen grids keep a known mask instead of stamps, 1 bit a cell (np.packbits by row)
        self.scan_id = 0
        # likelihood field: Gaussian of the distance to the nearest occupied cell, cut at 3 sigma
        self.field_sigma = field_sigma
        self.field = np.zeros(shape if field_sigma else (0, 0), dtype=np.float32)
        if field_sigma:
            self.field_radius = max(1, int(math.ceil(3.0 * field_sigma / self.resolution)))
            self.field_kernel = field_kernel(field_sigma, self.resolution, self.field_radius)

    @classmethod
    def from_config(cls, grid_cfg, resolution=None, field_sigma=None):
        return cls(resolution or grid_cfg.resolution, grid_cfg.hit_probability, grid_cfg.miss_probability,
                   grid_cfg.min_probability, grid_cfg.max_probability, field_sigma=field_sigma)

    def _arrays(self):
        out = [("logodds", np.float32, 0), ("stamp", np.int32, 0),
               ("prob", np.float32, self.unknown_probability)]
        if self.field_sigma:
            out.append(("field", np.float32, 0))
        return out

    @property
    def prob(self) -> np.ndarray:
        """Probabilities [row, col] (float32; uint8 as p × 255 once frozen). A packed grid unpacks a
        fresh copy on every read."""
        p = self._prob
        if p is None:
            z, shape = self._packed
            p = np.frombuffer(zlib.decompress(z), dtype=np.uint8).reshape(shape).copy()
        return p

    @prob.setter
    def prob(self, value: np.ndarray):
        self._prob = value
        self._packed = None

    def pack(self) -> None:
        """Keep a frozen grid's probabilities compressed (zlib): a finished submap is read only when a
        loop search builds its precomputation stack, which then holds the values while it is cached
        (``loop_closure.StackCache``); mostly-unknown uint8 grids compress several times over."""
        p = self._prob
        if p is None or p.dtype != np.uint8:
            return
        # set before ``_prob`` goes, so a reader on another thread always finds one of the two
        self._packed = (zlib.compress(p.tobytes(), 1), p.shape)
        self._prob = None

    @property
    def packed_bytes(self) -> int | None:
        """Size of the compressed probabilities (None: not packed)."""
        return None if self._packed is None else len(self._packed[0])

    @property
    def shape(self):
        return self._packed[1] if self._prob is None else self._prob.shape

    @property
    def known(self) -> np.ndarray:
        """1 where some scan updated the cell (observed), else 0."""
        if self._known_bits is not None:
            return self._known_rows(0, self.shape[0])
        return (self.stamp > 0).view(np.uint8)

    def known_bits(self) -> np.ndarray:
        """The known mask packed 8 cells a byte along each row, first cell in the high bit
        (``np.packbits(known, axis=1)``): what a frozen grid keeps."""
        if self._known_bits is not None:
            return self._known_bits
        return np.packbits(self.stamp > 0, axis=1)

    def _known_rows(self, r0: int, r1: int) -> np.ndarray:
        """``known[r0:r1]`` of a frozen grid, unpacked from its bit mask."""
        return np.unpackbits(self._known_bits[r0:r1], axis=1, count=self.shape[1])

    def observed_at(self, cells: np.ndarray) -> np.ndarray:
        """For cells (N, 2) as [col, row]: True where the cell lies in the grid and was observed."""
        rows, cols = self.shape
        c, r = cells[:, 0], cells[:, 1]
        inside = (c >= 0) & (r >= 0) & (c < cols) & (r < rows)
        out = np.zeros(len(cells), dtype=bool)
        if self._known_bits is not None:
            ri, ci = r[inside], c[inside]
            out[inside] = ((self._known_bits[ri, ci >> 3] >> (7 - (ci & 7))) & 1) > 0
        else:
            out[inside] = self.stamp[r[inside], c[inside]] > 0
        return out

    def freeze(self, r0, r1, c0, c1):
        """Crop to [r0:r1, c0:c1] and drop the insertion buffers (no more inserts)."""
        # matching and export read probabilities only: the log-odds go, and the probabilities are kept
        # as uint8 (p × 255, what branch-and-bound scores anyway) beside a 1-bit known mask, both made
        # in one pass without full-size temporaries
        if self._known_bits is not None:
            raise ValueError("the grid is frozen already")
        q, bits = _kernels.frozen_cells(self.prob, self.stamp, r0, r1, c0, c1)
        self.logodds = np.zeros((0, 0), dtype=np.float32)
        self.prob = q
        # a frozen grid is read, never matched by local SLAM again: its likelihood field goes
        self.field_sigma = None
        self.field = np.zeros((0, 0), dtype=np.float32)
        self.origin = self._cell_origin(c0, r0)
        self._known_bits = bits
        self.stamp = np.zeros((0, 0), dtype=np.int32)

    def release(self):
        """Drop every cell (the grid keeps its frame and rules; it is empty afterwards)."""
        empty = np.zeros((0, 0), dtype=np.float32)
        self.logodds, self.prob, self.field = empty, empty.copy(), empty.copy()
        self.stamp = np.zeros((0, 0), dtype=np.int32)
        self._known_bits = np.zeros((0, 0), dtype=np.uint8)
        self.field_sigma = None

    def ensure_contains(self, xmin, ymin, xmax, ymax):
        """Grow the grid (keeping its content and cell alignment) so the box fits."""
        res = self.resolution
        rows, cols = self.shape
        if rows and cols:
            c0 = math.floor((xmin - self.origin[0]) / res)
            r0 = math.floor((ymin - self.origin[1]) / res)
            c1 = math.floor((xmax - self.origin[0]) / res)
            r1 = math.floor((ymax - self.origin[1]) / res)
            if c0 >= 0 and r0 >= 0 and c1 < cols and r1 < rows:
                return
            # a side that grows gains a quarter of the grid's size beyond the box as well: a long-range
            # laser carried along a corridor would otherwise copy the whole grid every few scans
            mc, mr = max(self.GROW_MARGIN, cols // 4), max(self.GROW_MARGIN, rows // 4)
            add_left = mc - c0 if c0 < 0 else 0
            add_bottom = mr - r0 if r0 < 0 else 0
            add_right = c1 - cols + 1 + mc if c1 >= cols else 0
            add_top = r1 - rows + 1 + mr if r1 >= rows else 0
            new_shape = (rows + add_bottom + add_top, cols + add_left + add_right)
            for name, dtype, fill in self._arrays():
                setattr(self, name, _grown(getattr(self, name), new_shape, add_bottom, add_left, fill))
            self.origin = self._cell_origin(-add_left, -add_bottom)
        else:
            self.origin, shape = self._frame_for(xmin, ymin, xmax, ymax)
            for name, dtype, fill in self._arrays():
                setattr(self, name, np.full(shape, fill, dtype=dtype))

    def _cell_origin(self, dc: int, dr: int) -> np.ndarray:
        """The origin moved by (dc, dr) cells, as a whole number of cells times the resolution: a grid's
        frame is then the same floats however it grew, and so is every point's cell."""
        k = np.round(self.origin / self.resolution) + np.array([dc, dr])
        return k * self.resolution

    def _frame_for(self, xmin, ymin, xmax, ymax):
        """(origin, shape) of an empty grid's first extent around the box (``GROW_MARGIN`` beyond it)."""
        res, m = self.resolution, self.GROW_MARGIN
        origin = np.array([math.floor(xmin / res) - m, math.floor(ymin / res) - m], dtype=float) * res
        shape = (int(math.floor(ymax / res) - math.floor(ymin / res)) + 2 * m + 1,
                 int(math.floor(xmax / res) - math.floor(xmin / res)) + 2 * m + 1)
        return origin, shape

    def insert(self, origin_xy, hits: np.ndarray, misses: np.ndarray | None = None):
        """Insert one scan: rays from ``origin_xy`` to hit points (N, 2) and to free-space ray ends (M, 2), grid frame."""
        insert_scan([self], origin_xy, hits, misses)

    def insert_scans(self, scans: list, threads: int | None = None):
        """Insert many scans ``(origin (2,), hits (N, 2), misses (M, 2))`` in order, grid frame.

        The grid's rows are split among threads (``insert_scans_striped``); the result is
        identical to inserting the scans one at a time. A likelihood field is computed afresh
        from the occupied cells (one at a time keeps it up cell by cell: the same values but in
        the last bits of cells recomputed after a cell stopped being occupied).
        """
        batch = _ScanBatch(scans)
        if batch.empty:
            return
        self.ensure_contains(*batch.lo, *batch.hi)
        first = self.scan_id + 1
        self.scan_id += batch.count
        n = threads or numba.get_num_threads()
        o, e = batch.to_cells(self.origin, self.resolution)
        _kernels.insert_scans_striped(self.logodds, self.prob, self.stamp, first, o, e, batch.starts, batch.n_hits,
                                      self.hit_delta, self.miss_delta, self.lo_min, self.lo_max, max(1, int(n)), 0)
        if self.field_sigma:  # afresh: the kernel laid around every occupied cell (``stamp_field``'s rule)
            self.field = _kernels.occupied_field(self.logodds, self.known_bits(), np.float32(0.0), self.field_kernel,
                                                 self.field_radius)

    def build_finished(self, scans: list, threads: int | None = None, band_cells: int = 1 << 22):
        """Insert many scans, in order, into this empty grid and finish it: what is kept is the
        probability of every cell (float32, unknown cells at ``unknown_probability``, exactly what
        ``insert_scans`` leaves in ``prob``) and the known mask (1 bit a cell), and no more scans
        can be inserted. The log-odds and stamps exist for one band of rows (about ``band_cells``
        cells) at a time, and only the scans whose rays reach a band are traced for it; every cell
        sees the same updates in the same order as with ``insert_scans``, so the result is identical."""
        if self.shape != (0, 0) or self.scan_id:
            raise ValueError("build_finished needs an empty grid")
        self.field_sigma = None
        self.field = np.zeros((0, 0), dtype=np.float32)
        batch = _ScanBatch(scans)
        if batch.empty:
            return
        self.origin, shape = self._frame_for(*batch.lo, *batch.hi)
        rows, cols = shape
        prob = np.full(shape, self.unknown_probability, dtype=np.float32)
        known = np.zeros(shape, dtype=np.uint8)
        o, e = batch.to_cells(self.origin, self.resolution)
        # each scan's rows, from its origin and ray ends (a ray's cells lie between them)
        row_of = np.floor(e[:, 1]).astype(np.int64)
        first_row = np.minimum(np.minimum.reduceat(row_of, batch.starts[:-1]), np.floor(o[:, 1]).astype(np.int64))
        last_row = np.maximum(np.maximum.reduceat(row_of, batch.starts[:-1]), np.floor(o[:, 1]).astype(np.int64))
        band = max(1, band_cells // max(cols, 1))
        n = max(1, int(threads or numba.get_num_threads()))
        for a in range(0, rows, band):
            b = min(rows, a + band)
            sel = np.flatnonzero((last_row >= a) & (first_row < b))
            if sel.size == 0:
                continue
            sizes = batch.starts[sel + 1] - batch.starts[sel]
            starts = np.zeros(sel.size + 1, dtype=np.int64)
            starts[1:] = np.cumsum(sizes)
            ray = np.repeat(batch.starts[sel] - starts[:-1], sizes) + np.arange(starts[-1])
            logodds = np.zeros((b - a, cols), dtype=np.float32)
            stamp = np.zeros((b - a, cols), dtype=np.int32)
            _kernels.insert_scans_striped(logodds, prob[a:b], stamp, 1, np.ascontiguousarray(o[sel]),
                                          np.ascontiguousarray(e[ray]), starts, batch.n_hits[sel], self.hit_delta,
                                          self.miss_delta, self.lo_min, self.lo_max, n, a)
            known[a:b] = stamp > 0
        self.prob, self._known_bits = prob, np.packbits(known, axis=1)
        self.logodds = np.zeros((0, 0), dtype=np.float32)
        self.stamp = np.zeros((0, 0), dtype=np.int32)
        self.scan_id = batch.count

    def _prepare(self, ends: np.ndarray, origin: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        """Grow to fit, advance the scan id; (ray ends in cells, origin in cells, flips buffer, flip count)."""
        self.ensure_contains(lo[0], lo[1], hi[0], hi[1])
        self.scan_id += 1
        cells = np.ascontiguousarray((ends - self.origin) / self.resolution)
        o = (origin - self.origin) / self.resolution
        return cells, o, np.empty((4 * len(ends) + 256, 2), dtype=np.int32), np.zeros(1, dtype=np.int64)

    def _field_after(self, flips, n_flips, stamped: bool):
        if not self.field_sigma:
            return
        n = int(n_flips[0])
        if n > len(flips):
            self.field = self.compute_field()
        elif not stamped:
            _kernels.stamp_field(self.field, self.logodds, flips, n, self.field_kernel, self.field_radius)

    def compute_field(self) -> np.ndarray:
        """The likelihood field from scratch (exact Euclidean distance transform)."""
        occ = self.logodds > 0
        if not occ.any():
            return np.zeros(self.shape, dtype=np.float32)
        from scipy.ndimage import distance_transform_edt  # rare (a fallback): not worth its import time

        d = distance_transform_edt(~occ) * self.resolution
        f = np.exp(-0.5 * (d / self.field_sigma) ** 2)
        f[d > self.field_radius * self.resolution + 1e-9] = 0.0
        return f.astype(np.float32)

    def probability(self, unknown_value: float = 0.5) -> np.ndarray:
        return self.probability_rows(0, self.shape[0], unknown_value)

    def probability_rows(self, r0: int, r1: int, unknown_value: float = 0.5) -> np.ndarray:
        """``probability()[r0:r1]`` without converting the whole grid (a large map is exported in bands)."""
        if self._known_bits is not None:  # frozen: ``prob`` holds every known cell's probability (× 255 when uint8)
            p = self.prob[r0:r1]
            return np.where(self._known_rows(r0, r1) > 0, dequantize(p) if p.dtype == np.uint8 else p,
                            np.float32(unknown_value)).astype(np.float32)
        out = np.empty(self.logodds[r0:r1].shape, dtype=np.float32)
        if out.size:
            known = (self.stamp[r0:r1] > 0).view(np.uint8)
            _kernels.logodds_to_probability(self.logodds[r0:r1], known, np.float32(unknown_value), out)
        return out

    def known_bounds(self):
        """(r0, r1, c0, c1) slice bounds of the known cells, or None."""
        if self._known_bits is None:
            b = _kernels.stamped_bounds(self.stamp)
            return None if b[1] == 0 else tuple(int(v) for v in b)
        rows = np.flatnonzero(self.known.any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero(self.known.any(axis=0))
        return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


class _ScanBatch:
    """Scans ``(origin, hits, misses)`` as flat arrays: every ray end (a scan's hits first), where
    each scan starts, its hit count, and the box holding every origin and end."""

    def __init__(self, scans):
        scans = [(np.asarray(o, dtype=float), h, m) for o, h, m in scans if len(h) + len(m) > 0]
        self.count = len(scans)
        self.empty = not scans
        if self.empty:
            return
        self.ends = np.concatenate([np.concatenate([h, m]) if len(m) else h for _, h, m in scans]).astype(np.float64)
        self.origins = np.array([o for o, _, _ in scans], dtype=np.float64)
        self.lo = np.minimum(self.ends.min(axis=0), self.origins.min(axis=0))
        self.hi = np.maximum(self.ends.max(axis=0), self.origins.max(axis=0))
        self.starts = np.zeros(len(scans) + 1, dtype=np.int64)
        self.starts[1:] = np.cumsum([len(h) + len(m) for _, h, m in scans])
        self.n_hits = np.array([len(h) for _, h, _ in scans], dtype=np.int64)

    def to_cells(self, origin, resolution):
        """(origins, ends) converted, in place, to cell units of a grid with this origin and resolution."""
        for a in (self.origins, self.ends):
            a -= origin
            a /= resolution
        return self.origins, self.ends


def _grown(old: np.ndarray, shape: tuple[int, int], r0: int, c0: int, fill) -> np.ndarray:
    """``old`` placed at rows ``r0``…, columns ``c0``… of a new array of ``shape``, ``fill`` elsewhere.
    Every element is written once: a zero fill is left to the zeroed pages the allocator maps, any
    other goes only where ``old`` does not."""
    rows, cols = old.shape
    if fill == 0:
        new = np.zeros(shape, dtype=old.dtype)
    else:
        new = np.empty(shape, dtype=old.dtype)
        new[:r0] = fill
        new[r0 + rows:] = fill
        new[r0:r0 + rows, :c0] = fill
        new[r0:r0 + rows, c0 + cols:] = fill
    new[r0:r0 + rows, c0:c0 + cols] = old
    return new


def quantize(prob: np.ndarray) -> np.ndarray:
    """Probabilities as uint8 (p × 255, rounded)."""
    return np.ascontiguousarray(np.clip(np.round(np.asarray(prob, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8))


def dequantize(q: np.ndarray) -> np.ndarray:
    """uint8 probabilities back to float32 in [0, 1]."""
    return q.astype(np.float32) * np.float32(1.0 / 255.0)


def insert_scan(grids: list[ProbabilityGrid], origin_xy, hits: np.ndarray, misses: np.ndarray | None = None):
    """Insert one scan (grid frame, shared by ``grids``) into each grid; two grids with the same
    update rules (the active submaps) are updated in parallel, one per thread."""
    ends = hits if misses is None or len(misses) == 0 else np.concatenate([hits, misses])
    if len(ends) == 0:
        return
    origin = np.asarray(origin_xy, dtype=float)
    lo = np.minimum(ends.min(axis=0), origin)
    hi = np.maximum(ends.max(axis=0), origin)
    is_hit = np.zeros(len(ends), dtype=np.bool_)
    is_hit[: len(hits)] = True
    prepared = [g._prepare(ends, origin, lo, hi) for g in grids]
    if len(grids) == 2 and _same_rules(*grids):
        a, b = grids
        (ca, oa, fa, na), (cb, ob, fb, nb) = prepared
        with_field = bool(a.field_sigma)
        _kernels.insert_rays_pair(a.logodds, a.prob, a.stamp, a.scan_id, float(oa[0]), float(oa[1]), ca, fa, na, a.field,
                                  b.logodds, b.prob, b.stamp, b.scan_id, float(ob[0]), float(ob[1]), cb, fb, nb, b.field,
                                  is_hit, a.hit_delta, a.miss_delta, a.lo_min, a.lo_max,
                                  a.field_kernel if with_field else _NO_KERNEL, a.field_radius if with_field else 0,
                                  with_field)
        a._field_after(fa, na, stamped=True)
        b._field_after(fb, nb, stamped=True)
        return
    for g, (cells, o, flips, n_flips) in zip(grids, prepared):
        _kernels.insert_rays(g.logodds, g.prob, g.stamp, g.scan_id, float(o[0]), float(o[1]), cells, is_hit,
                             g.hit_delta, g.miss_delta, g.lo_min, g.lo_max, flips, n_flips, 0, -1, 0)
        g._field_after(flips, n_flips, stamped=False)


_NO_KERNEL = np.zeros((1, 1), dtype=np.float32)


def _same_rules(a: ProbabilityGrid, b: ProbabilityGrid) -> bool:
    return (a.hit_delta == b.hit_delta and a.miss_delta == b.miss_delta and a.lo_min == b.lo_min
            and a.lo_max == b.lo_max and a.field_sigma == b.field_sigma and a.resolution == b.resolution)
