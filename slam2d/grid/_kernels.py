"""Numba kernels of the grid: range insertion by exact ray traversal (Amanatides & Woo 1987).

Each kernel has a plain-numpy oracle in ``tests/test_grid_kernels.py``.
Cells are addressed as ``[row, col] = [y index, x index]`` from the grid's lower-left corner.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, inline="always")
def _apply(logodds, prob, stamp, r, c, scan_id, delta, lo_min, lo_max):
    if stamp[r, c] == scan_id:
        return False
    stamp[r, c] = scan_id  # a cell is known once any scan updated it (stamp > 0)
    old = logodds[r, c]
    v = old + delta
    if v < lo_min:
        v = lo_min
    elif v > lo_max:
        v = lo_max
    if np.float32(v) == old:  # clamped (compared as stored: the clamp is a float64 the float32 cell rounds)
        return False
    logodds[r, c] = v
    prob[r, c] = 1.0 / (1.0 + math.exp(-v))
    return (old > 0.0) != (v > 0.0)


@njit(cache=True, nogil=True)
def insert_rays(logodds, prob, stamp, scan_id, ox, oy, ends, is_hit, hit_delta, miss_delta, lo_min, lo_max,
                flips, n_flips, row_lo, row_hi, row_offset):
    """Insert rays from (ox, oy) to ``ends`` (M, 2), all in cell units (continuous, lower-left origin).

    Endpoints with ``is_hit`` get one hit update per scan even when several rays end in the
    same cell; ``prob`` mirrors each updated cell as a probability. Every cell a ray crosses before its end gets one miss update unless it was
    already updated by this scan (hits are applied first, as in Cartographer). Cells that
    cross between occupied (log-odds > 0) and not are written to ``flips`` (their count to
    ``n_flips[0]``, which may exceed the buffer: then the caller recomputes what depends on it). Rays whose
    ``is_hit`` is False mark free space along the whole ray, the end cell included.
    Cells outside the grid, or outside rows [row_lo, row_hi) (``row_hi`` < 0: no upper limit), are
    skipped. ``row_offset``: the arrays hold only rows [row_offset, row_offset + their rows) of a
    larger grid whose cell units ``ends`` and the origin are in (a map built one band of rows at a
    time); a ray that crosses none of those rows is not traced. A whole grid is (0, -1, 0). The three
    have no defaults on purpose: called from Python with them left out, numba compiled the kernel
    with them as constants, and that version traced rays about half as fast.
    """
    n_rows, cols = logodds.shape
    r_lo = max(row_lo, row_offset)
    r_hi = row_offset + n_rows if row_hi < 0 else min(row_hi, row_offset + n_rows)
    m = ends.shape[0]
    nf = 0
    cap = flips.shape[0]
    for i in range(m):
        if is_hit[i]:
            c = int(math.floor(ends[i, 0]))
            r = int(math.floor(ends[i, 1]))
            if r_lo <= r < r_hi and 0 <= c < cols:
                if _apply(logodds, prob, stamp, r - row_offset, c, scan_id, hit_delta, lo_min, lo_max):
                    if nf < cap:
                        flips[nf, 0] = r
                        flips[nf, 1] = c
                    nf += 1
    cx0 = int(math.floor(ox))
    cy0 = int(math.floor(oy))
    inf = 1e30
    for i in range(m):
        ex = ends[i, 0]
        ey = ends[i, 1]
        cx = cx0
        cy = cy0
        tx = int(math.floor(ex))
        ty = int(math.floor(ey))
        if (ty < r_lo and cy0 < r_lo) or (ty >= r_hi and cy0 >= r_hi):
            continue  # the ray's cells lie in rows from cy0 to ty: none of them in this band
        dx = ex - ox
        dy = ey - oy
        step_x = 1 if dx > 0 else -1
        step_y = 1 if dy > 0 else -1
        if dx != 0.0:
            t_max_x = ((cx + (1 if dx > 0 else 0)) - ox) / dx
            t_delta_x = abs(1.0 / dx)
        else:
            t_max_x = inf
            t_delta_x = inf
        if dy != 0.0:
            t_max_y = ((cy + (1 if dy > 0 else 0)) - oy) / dy
            t_delta_y = abs(1.0 / dy)
        else:
            t_max_y = inf
            t_delta_y = inf
        # the cells before the end cell: a grid traversal visits exactly |Δcol| + |Δrow| of them
        n_steps = abs(tx - cx) + abs(ty - cy)
        for _ in range(n_steps):
            # ``_apply`` written out: calling it here (inline="always") made insertion 1.6x slower
            ry = cy - row_offset
            if r_lo <= cy < r_hi and 0 <= cx < cols and stamp[ry, cx] != scan_id:
                stamp[ry, cx] = scan_id  # a cell is known once any scan updated it
                old = logodds[ry, cx]
                v = old + miss_delta
                if v < lo_min:
                    v = lo_min
                elif v > lo_max:
                    v = lo_max
                if np.float32(v) != old:  # most misses land on cells already at the clamp (compared as stored)
                    logodds[ry, cx] = v
                    prob[ry, cx] = 1.0 / (1.0 + math.exp(-v))
                    if (old > 0.0) != (v > 0.0):
                        if nf < cap:
                            flips[nf, 0] = cy
                            flips[nf, 1] = cx
                        nf += 1
            if t_max_x < t_max_y:
                t_max_x += t_delta_x
                cx += step_x
            else:
                t_max_y += t_delta_y
                cy += step_y
        if not is_hit[i] and r_lo <= ty < r_hi and 0 <= tx < cols:
            if _apply(logodds, prob, stamp, ty - row_offset, tx, scan_id, miss_delta, lo_min, lo_max):
                if nf < cap:
                    flips[nf, 0] = ty
                    flips[nf, 1] = tx
                nf += 1
    n_flips[0] = nf


@njit(cache=True, nogil=True)
def logodds_to_probability(logodds, known, unknown_value, out):
    rows, cols = logodds.shape
    for r in range(rows):
        for c in range(cols):
            if known[r, c]:
                out[r, c] = 1.0 / (1.0 + math.exp(-logodds[r, c]))
            else:
                out[r, c] = unknown_value
    return out


@njit(cache=True, nogil=True)
def stamp_field(field, logodds, flips, n, kernel, radius):
    """Update a likelihood field after occupancy flips, exactly.

    ``field[q] = max over occupied cells o with |q − o| ≤ radius of kernel[o − q]``. A cell
    that became occupied raises its neighbourhood to the kernel; around a cell that stopped
    being occupied every cell is recomputed from the occupied cells near it.
    """
    rows, cols = field.shape
    for k in range(n):
        r = flips[k, 0]
        c = flips[k, 1]
        if logodds[r, c] > 0.0:
            for dr in range(-radius, radius + 1):
                rr = r + dr
                if rr < 0 or rr >= rows:
                    continue
                for dc in range(-radius, radius + 1):
                    cc = c + dc
                    if cc < 0 or cc >= cols:
                        continue
                    v = kernel[dr + radius, dc + radius]
                    if v > field[rr, cc]:
                        field[rr, cc] = v
    # around a cell that stopped being occupied, every cell within the radius is recomputed:
    # marked dirty (value − 2), then every occupied cell within the radius of it stamps the
    # kernel onto the dirty cells, and the marks are lifted
    for k in range(n):
        r = flips[k, 0]
        c = flips[k, 1]
        if logodds[r, c] > 0.0:
            continue
        for rr in range(max(r - radius, 0), min(r + radius + 1, rows)):
            for cc in range(max(c - radius, 0), min(c + radius + 1, cols)):
                if field[rr, cc] >= -0.5:
                    field[rr, cc] = -2.0
    reach = 2 * radius
    for k in range(n):
        r = flips[k, 0]
        c = flips[k, 1]
        if logodds[r, c] > 0.0:
            continue
        for orow in range(max(r - reach, 0), min(r + reach + 1, rows)):
            for ocol in range(max(c - reach, 0), min(c + reach + 1, cols)):
                if logodds[orow, ocol] <= 0.0:
                    continue
                for rr in range(max(orow - radius, 0), min(orow + radius + 1, rows)):
                    for cc in range(max(ocol - radius, 0), min(ocol + radius + 1, cols)):
                        f = field[rr, cc]
                        if f < -0.5:
                            v = kernel[rr - orow + radius, cc - ocol + radius] - 2.0
                            if v > f:
                                field[rr, cc] = v
    for k in range(n):
        r = flips[k, 0]
        c = flips[k, 1]
        if logodds[r, c] > 0.0:
            continue
        for rr in range(max(r - radius, 0), min(r + radius + 1, rows)):
            for cc in range(max(c - radius, 0), min(c + radius + 1, cols)):
                if field[rr, cc] < -0.5:
                    field[rr, cc] += 2.0


@njit(cache=True, nogil=True)
def _insert_and_stamp(logodds, prob, stamp, scan_id, ox, oy, ends, is_hit, hit_delta, miss_delta, lo_min, lo_max,
                      flips, n_flips, field, kernel, radius, with_field):
    # the whole grid as constants here: unlike a call from Python, this path timed the same with the
    # band passed at run time (intel's insertion 3.7 s either way)
    insert_rays(logodds, prob, stamp, scan_id, ox, oy, ends, is_hit, hit_delta, miss_delta, lo_min, lo_max, flips, n_flips,
                0, -1, 0)
    if with_field and n_flips[0] <= flips.shape[0]:
        stamp_field(field, logodds, flips, n_flips[0], kernel, radius)


@njit(cache=True, nogil=True, parallel=True)
def insert_rays_pair(lo_a, prob_a, stamp_a, id_a, ox_a, oy_a, ends_a, flips_a, n_flips_a, field_a,
                     lo_b, prob_b, stamp_b, id_b, ox_b, oy_b, ends_b, flips_b, n_flips_b, field_b,
                     is_hit, hit_delta, miss_delta, lo_min, lo_max, kernel, radius, with_field):
    """``insert_rays`` (then ``stamp_field`` when ``with_field``) into two grids at once, one per
    thread: the two active submaps take every scan. A grid whose flips overflowed its buffer
    is left for the caller to recompute its field. (Each thread's work sits in its own
    function so that numba's parallel loop cannot hoist the flip count above the insertion.)"""
    for g in prange(2):
        if g == 0:
            _insert_and_stamp(lo_a, prob_a, stamp_a, id_a, ox_a, oy_a, ends_a, is_hit, hit_delta, miss_delta, lo_min,
                              lo_max, flips_a, n_flips_a, field_a, kernel, radius, with_field)
        else:
            _insert_and_stamp(lo_b, prob_b, stamp_b, id_b, ox_b, oy_b, ends_b, is_hit, hit_delta, miss_delta, lo_min,
                              lo_max, flips_b, n_flips_b, field_b, kernel, radius, with_field)


@njit(cache=True, nogil=True, parallel=True)
def insert_scans_striped(logodds, prob, stamp, first_id, origins, ends, starts, n_hits, hit_delta, miss_delta,
                         lo_min, lo_max, n_stripes, row_offset):
    """Insert many scans, in order, into one grid: scan s has rays from ``origins[s]`` to
    ``ends[starts[s]:starts[s+1]]``, its first ``n_hits[s]`` ends being hits, and scan id
    ``first_id + s``. The rows are cut into ``n_stripes`` bands, one per thread; every thread
    traces every ray that reaches its rows but updates only those, so each cell sees the same
    updates in the same order as with ``insert_rays`` one scan at a time (the result is
    identical). ``row_offset``: the arrays are rows [row_offset, …) of a larger grid (``insert_rays``)."""
    rows = logodds.shape[0]
    n_scans = origins.shape[0]
    for k in prange(n_stripes):
        r0 = row_offset + rows * k // n_stripes
        r1 = row_offset + rows * (k + 1) // n_stripes
        no_flips = np.empty((0, 2), dtype=np.int32)
        count = np.zeros(1, dtype=np.int64)
        for sc in range(n_scans):
            a = starts[sc]
            b = starts[sc + 1]
            is_hit = np.zeros(b - a, dtype=np.bool_)
            is_hit[:n_hits[sc]] = True
            insert_rays(logodds, prob, stamp, first_id + sc, origins[sc, 0], origins[sc, 1], ends[a:b], is_hit,
                        hit_delta, miss_delta, lo_min, lo_max, no_flips, count, r0, r1, row_offset)


@njit(cache=True, nogil=True)
def stamped_bounds(stamp):
    """(r0, r1, c0, c1): slice bounds of the cells whose stamp is above 0 (observed); (0, 0, 0, 0)
    when there are none."""
    rows, cols = stamp.shape
    r0, r1, c0, c1 = rows, 0, cols, 0
    for r in range(rows):
        first = -1
        for c in range(cols):
            if stamp[r, c] > 0:
                first = c
                break
        if first < 0:
            continue
        last = first
        for c in range(cols - 1, first, -1):
            if stamp[r, c] > 0:
                last = c
                break
        r0 = min(r0, r)
        r1 = r + 1
        c0 = min(c0, first)
        c1 = max(c1, last + 1)
    if r1 == 0:
        return 0, 0, 0, 0
    return r0, r1, c0, c1


@njit(cache=True, nogil=True)
def frozen_cells(prob, stamp, r0, r1, c0, c1):
    """A finished grid's cells [r0:r1, c0:c1] in one pass: the probabilities as uint8 (p × 255,
    rounded half to even, clipped: ``probability_grid.quantize``) and the known mask (stamp above
    0) packed 8 cells a byte, first cell in the high bit (``np.packbits(…, axis=1)``)."""
    rows = r1 - r0
    cols = c1 - c0
    q = np.empty((rows, cols), dtype=np.uint8)
    bits = np.zeros((rows, (cols + 7) // 8), dtype=np.uint8)
    scale = np.float32(255.0)
    for r in range(rows):
        for c in range(cols):
            v = np.rint(prob[r0 + r, c0 + c] * scale)
            q[r, c] = np.uint8(min(max(v, 0.0), 255.0))
            if stamp[r0 + r, c0 + c] > 0:
                bits[r, c >> 3] |= np.uint8(128 >> (c & 7))
    return q, bits


@njit(cache=True, nogil=True)
def occupied_field(prob, known_bits, half, kernel, radius):
    """A likelihood field from scratch, at the kernel's dtype: ``out[q]`` = max over the occupied
    cells o (known, ``prob`` above ``half``) with |q − o| ≤ radius of ``kernel[o − q]``, else 0.
    ``known_bits``: the known mask packed as ``frozen_cells`` packs it."""
    rows, cols = prob.shape
    out = np.zeros((rows, cols), dtype=kernel.dtype)
    for r in range(rows):
        for c in range(cols):
            if prob[r, c] <= half or not (known_bits[r, c >> 3] >> (7 - (c & 7))) & 1:
                continue
            for rr in range(max(r - radius, 0), min(r + radius + 1, rows)):
                for cc in range(max(c - radius, 0), min(c + radius + 1, cols)):
                    v = kernel[rr - r + radius, cc - c + radius]
                    if v > out[rr, cc]:
                        out[rr, cc] = v
    return out
