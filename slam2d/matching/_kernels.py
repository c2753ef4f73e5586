"""Numba kernels of the scan matchers. Each one has a plain-numpy oracle in ``tests/test_matching_kernels.py``.

Grid arrays are ``values[row, col]`` (row = y); ``origin`` is the lower-left corner of cell
(0, 0); a point falls in cell ``floor((p - origin) / resolution)``. Cells outside the array
read as ``unknown``.

``apply_delta_penalty``, microseconds per scan, keeps the interpreter lock (``slam2d/_kernels.py`` says why).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

#: ``known`` for a grid whose every cell was observed (``_bicubic``)
ALL_KNOWN = np.zeros((0, 0), dtype=np.int32)


@njit(cache=True, nogil=True)
def quantize_up(values):
    """``values`` in [0, 1] (any float array, 2-D) as uint8 of ``ceil(v × 255)``, clipped to 0…255."""
    rows, cols = values.shape
    out = np.empty((rows, cols), dtype=np.uint8)
    for r in range(rows):
        for c in range(cols):
            q = math.ceil(values[r, c] * 255.0)
            out[r, c] = 0 if q < 0.0 else (255 if q > 255.0 else np.uint8(q))
    return out


@njit(cache=True, nogil=True)
def rotated_cells(points, x, y, theta0, angles, ox, oy, inv_res):
    """Cells (A, N, 2) as [col, row] of ``points`` (N, 2) rotated by theta0 + angles[a] and moved to (x, y)."""
    a_n = angles.shape[0]
    n = points.shape[0]
    out = np.empty((a_n, n, 2), dtype=np.int32)
    for a in range(a_n):
        c = math.cos(theta0 + angles[a])
        s = math.sin(theta0 + angles[a])
        for i in range(n):
            px = x + c * points[i, 0] - s * points[i, 1]
            py = y + s * points[i, 0] + c * points[i, 1]
            out[a, i, 0] = int(math.floor((px - ox) * inv_res))
            out[a, i, 1] = int(math.floor((py - oy) * inv_res))
    return out


@njit(cache=True, nogil=True)
def score_window(values, cells, w, unknown, scale=1.0):
    """Mean grid value for every angle and integer offset in [-w, w]²: scores[a, dy + w, dx + w].

    ``scale`` ≠ 1: a cell's value is ``float32(values[r, c]) × float32(scale)``, exactly what the
    grid ``dequantize``d would hold (uint8 probabilities are scored without a float copy)."""
    rows, cols = values.shape
    a_n, n = cells.shape[0], cells.shape[1]
    k = 2 * w + 1
    scaled = scale != 1.0
    s32 = np.float32(scale)
    out = np.zeros((a_n, k, k), dtype=np.float32)
    for a in range(a_n):
        acc = out[a]
        for i in range(n):
            c0 = cells[a, i, 0] - w
            r0 = cells[a, i, 1] - w
            if r0 >= 0 and c0 >= 0 and r0 + k <= rows and c0 + k <= cols:
                for dy in range(k):  # the whole window lies inside: branch-free rows
                    row = values[r0 + dy]
                    arow = acc[dy]
                    if scaled:
                        for dx in range(k):
                            arow[dx] += np.float32(row[c0 + dx]) * s32
                    else:
                        for dx in range(k):
                            arow[dx] += row[c0 + dx]
                continue
            for dy in range(k):
                r = r0 + dy
                if r < 0 or r >= rows:
                    for dx in range(k):
                        acc[dy, dx] += unknown
                    continue
                for dx in range(k):
                    c = c0 + dx
                    if c < 0 or c >= cols:
                        acc[dy, dx] += unknown
                    elif scaled:
                        acc[dy, dx] += np.float32(values[r, c]) * s32
                    else:
                        acc[dy, dx] += values[r, c]
        for dy in range(k):
            for dx in range(k):
                acc[dy, dx] /= n
    return out


@njit(cache=True, nogil=True, inline="always")
def _level_score(level, cells, a, dx, dy, unknown):
    rows, cols = level.shape
    n = cells.shape[1]
    s = 0.0
    for i in range(n):
        c = cells[a, i, 0] + dx
        r = cells[a, i, 1] + dy
        if r < 0 or r >= rows or c < 0 or c >= cols:
            s += unknown
        else:
            s += level[r, c]
    return s / n


@njit(cache=True, nogil=True, inline="always")
def _block_score(data, start, rows, cols, pad, cells, a, dx, dy, unknown):
    """Mean over the points of the max-pooled value of their block at (dx, dy), one precomputation level.

    The level is ``data[start:]`` as (rows + pad) × (cols + pad), padded by ``pad`` on the low
    side: a block starting at grid cell (r, c) is element (r + pad, c + pad); blocks starting
    outside that range lie wholly outside the grid and score ``unknown``.
    """
    h = rows + pad
    wd = cols + pad
    n = cells.shape[1]
    s = 0.0
    for i in range(n):
        c = cells[a, i, 0] + dx + pad
        r = cells[a, i, 1] + dy + pad
        if r < 0 or r >= h or c < 0 or c >= wd:
            s += unknown
        else:
            s += data[start + r * wd + c]
    return s / n


@njit(cache=True, nogil=True)
def score_candidates(values, cells, cands, unknown):
    """Mean grid value for candidates (K, 3) = [angle index, dx, dy] (integer cells)."""
    k_n = cands.shape[0]
    out = np.empty(k_n, dtype=np.float32)
    for k in range(k_n):
        out[k] = _level_score(values, cells, cands[k, 0], cands[k, 1], cands[k, 2], unknown)
    return out


@njit(cache=True, nogil=True, inline="always")
def _w(t):
    t2 = t * t
    t3 = t2 * t
    return (0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
            0.5 * (-3.0 * t3 + 4.0 * t2 + t), 0.5 * (t3 - t2))


@njit(cache=True, nogil=True, inline="always")
def _dw(t):
    t2 = t * t
    return (0.5 * (-3.0 * t2 + 4.0 * t - 1.0), 0.5 * (9.0 * t2 - 10.0 * t),
            0.5 * (-9.0 * t2 + 8.0 * t + 1.0), 0.5 * (3.0 * t2 - 2.0 * t))


@njit(cache=True, nogil=True, inline="always")
def _unobserved(values, known, r, c, rows, cols, unknown):
    """What a never-observed cell (r, c) reads as: the mean of the observed cells likelier free than
    occupied that lie two cells away along a row or column, beyond an observed cell likelier
    occupied (the free side of a surface the cell lies just behind, mirrored across it); else
    ``unknown``."""
    acc = 0.0
    n = 0
    for d in range(4):
        dr = 1 if d == 0 else -1 if d == 1 else 0
        dc = 1 if d == 2 else -1 if d == 3 else 0
        r2 = r + 2 * dr
        c2 = c + 2 * dc
        if 0 <= r2 < rows and 0 <= c2 < cols:
            r1 = r + dr
            c1 = c + dc
            if known[r1, c1] > 0 and values[r1, c1] > 0.5 and known[r2, c2] > 0 and values[r2, c2] < 0.5:
                acc += values[r2, c2]
                n += 1
    return acc / n if n else unknown


@njit(cache=True, nogil=True)
def _bicubic(values, u, v, unknown, scale, known):
    """Value and gradient. A cell outside the grid reads as ``unknown``; so does one whose ``known``
    entry is 0 or less (when ``known`` has the grid's shape; an empty ``known``: every cell is
    observed), unless it lies just behind a surface: then as that surface's free side
    (``_unobserved``). Masked grids hold probabilities (scale 1)."""
    rows, cols = values.shape
    masked = known.shape[0] == rows and known.shape[1] == cols
    scaled = scale != 1.0
    s32 = np.float32(scale)
    uu = u - 0.5
    vv = v - 0.5
    i0 = int(math.floor(uu))
    j0 = int(math.floor(vv))
    tx = uu - i0
    ty = vv - j0
    wx = _w(tx)
    dwx = _dw(tx)
    wy = _w(ty)
    dwy = _dw(ty)
    f = 0.0
    fu = 0.0
    fv = 0.0
    inside = i0 >= 1 and j0 >= 1 and i0 + 2 < cols and j0 + 2 < rows
    if inside and not masked and not scaled:
        # the common case, without a branch per cell: the same sums in the same order
        wx0, wx1, wx2, wx3 = wx
        dx0, dx1, dx2, dx3 = dwx
        for jj in range(4):
            row = values[j0 - 1 + jj]
            v0 = row[i0 - 1]
            v1 = row[i0]
            v2 = row[i0 + 1]
            v3 = row[i0 + 2]
            rf = 0.0 + wx0 * v0 + wx1 * v1 + wx2 * v2 + wx3 * v3
            rdu = 0.0 + dx0 * v0 + dx1 * v1 + dx2 * v2 + dx3 * v3
            f += wy[jj] * rf
            fu += wy[jj] * rdu
            fv += dwy[jj] * rf
        return f, fu, fv
    for jj in range(4):
        r = j0 - 1 + jj
        rf = 0.0
        rdu = 0.0
        for ii in range(4):
            c = i0 - 1 + ii
            if inside or (0 <= r < rows and 0 <= c < cols):
                if masked and known[r, c] <= 0:
                    val = _unobserved(values, known, r, c, rows, cols, unknown)
                else:
                    val = np.float32(values[r, c]) * s32 if scaled else values[r, c]
            else:
                val = unknown
            rf += wx[ii] * val
            rdu += dwx[ii] * val
        f += wy[jj] * rf
        fu += wy[jj] * rdu
        fv += dwy[jj] * rf
    return f, fu, fv


@njit(cache=True, nogil=True)
def bicubic(values, u, v, unknown, out, known):
    """Catmull-Rom bicubic value and gradient at continuous cell coordinates (u = x, v = y; cell centres at +0.5).

    Writes (value, d/du, d/dv) into ``out``.
    """
    f, fu, fv = _bicubic(values, u, v, unknown, 1.0, known)
    out[0] = f
    out[1] = fu
    out[2] = fv


@njit(cache=True, nogil=True)
def _normal_equations(values, ox, oy, res, unknown, points, x, y, t, x0, y0, t0, scale, w_t, w_r, h, g,
                      value_scale, known):
    """Cost at (x, y, t), and the Gauss-Newton Hessian ``h`` and gradient ``g`` there (one pass over the points)."""
    c = math.cos(t)
    s = math.sin(t)
    h[:, :] = 0.0
    g[:] = 0.0
    tot = 0.0
    for i in range(points.shape[0]):
        px0 = points[i, 0]
        py0 = points[i, 1]
        px = x + c * px0 - s * py0
        py = y + s * px0 + c * py0
        f, fu, fv = _bicubic(values, (px - ox) / res, (py - oy) / res, unknown, value_scale, known)
        r = scale * (1.0 - f)
        tot += r * r
        j0 = -scale * fu / res
        j1 = -scale * fv / res
        j2 = j0 * (-s * px0 - c * py0) + j1 * (c * px0 - s * py0)
        g[0] += j0 * r
        g[1] += j1 * r
        g[2] += j2 * r
        h[0, 0] += j0 * j0
        h[0, 1] += j0 * j1
        h[0, 2] += j0 * j2
        h[1, 1] += j1 * j1
        h[1, 2] += j1 * j2
        h[2, 2] += j2 * j2
    h[1, 0] = h[0, 1]
    h[2, 0] = h[0, 2]
    h[2, 1] = h[1, 2]
    h[0, 0] += w_t * w_t
    h[1, 1] += w_t * w_t
    h[2, 2] += w_r * w_r
    g[0] += w_t * w_t * (x - x0)
    g[1] += w_t * w_t * (y - y0)
    g[2] += w_r * w_r * (t - t0)
    return tot + (w_t * (x - x0)) ** 2 + (w_t * (y - y0)) ** 2 + (w_r * (t - t0)) ** 2


#: refinement stops when a step lowers the cost by less than this fraction (Ceres' function_tolerance)
FUNCTION_TOLERANCE = 1e-6


@njit(cache=True, nogil=True)
def refine_pose(values, ox, oy, res, unknown, points, x0, y0, t0, w_occ, w_t, w_r, max_iter, value_scale, known):
    """Levenberg-Marquardt on Σ (w_occ/√N · (1 − P(T p)))² + w_t²|t − t0|² + w_r²(θ − θ0)².

    Cartographer's Ceres scan matcher cost on a bicubic-interpolated probability grid. Each
    iteration is one pass over the points: the trial pose's cost comes with its normal
    equations, which the next step uses when the trial is accepted. Stops on Ceres' default
    rules (relative cost decrease below 1e-6, or a negligible step) or after ``max_iter``
    trials. Returns (x, y, theta, final cost, iterations). ``known``: cells whose entry is 0 or less
    read as ``unknown`` (``_bicubic``).
    """
    n = points.shape[0]
    scale = w_occ / math.sqrt(max(n, 1))
    x, y, t = x0, y0, t0
    lam = 1e-3
    h = np.zeros((3, 3))
    g = np.zeros(3)
    hn = np.zeros((3, 3))
    gn = np.zeros(3)
    hd = np.zeros((3, 3))
    cost = _normal_equations(values, ox, oy, res, unknown, points, x, y, t, x0, y0, t0, scale, w_t, w_r, h, g,
                             value_scale, known)
    it = 0
    for it in range(max_iter):
        hd[:, :] = h
        for a in range(3):
            hd[a, a] += lam * (h[a, a] + 1e-9)
        d = np.linalg.solve(hd, -g)
        nx, ny, nt = x + d[0], y + d[1], t + d[2]
        nc = _normal_equations(values, ox, oy, res, unknown, points, nx, ny, nt, x0, y0, t0, scale, w_t, w_r, hn, gn,
                               value_scale, known)
        if nc < cost:
            decrease = cost - nc
            x, y, t = nx, ny, nt
            cost = nc
            h[:, :] = hn
            g[:] = gn
            lam = max(lam * 0.3, 1e-7)
            if abs(d[0]) + abs(d[1]) + abs(d[2]) < 1e-6 or decrease <= FUNCTION_TOLERANCE * (cost + decrease):
                break
        else:
            lam *= 10.0
            if lam > 1e6:
                break
    return x, y, t, cost, it + 1


@njit(cache=True, nogil=True, inline="always")
def _penalty(w_t, w_r, res, angle, x, y, width):
    if w_t == 0.0 and w_r == 0.0:
        return 1.0
    hx = x + width - 1
    hy = y + width - 1
    nx = x if x > 0 else (hx if hx < 0 else 0)
    ny = y if y > 0 else (hy if hy < 0 else 0)
    d = math.sqrt(float(nx * nx + ny * ny)) * res
    v = w_t * d + w_r * abs(angle)
    return math.exp(-v * v)


@njit(cache=True, nogil=True)
def _top_candidates(data, starts, rows, cols, cells, angles, w, unknown, w_t, w_r, res):
    """The coarsest level's candidates (K, 3) = (angle, dx, dy), their bounds, and the order in which
    branch-and-bound visits them: ``order[r]`` is the r-th, best bound first."""
    depth = starts.shape[0] - 2
    top = 1 << depth
    n_off = (2 * w) // top + 1
    a_n = cells.shape[0]
    k0 = a_n * n_off * n_off
    cand = np.empty((k0, 3), dtype=np.int64)
    sc = np.empty(k0)
    k = 0
    for a in range(a_n):
        for ix in range(n_off):
            for iy in range(n_off):
                x = -w + ix * top
                y = -w + iy * top
                cand[k, 0] = a
                cand[k, 1] = x
                cand[k, 2] = y
                sc[k] = _block_score(data, starts[depth], rows, cols, top - 1, cells, a, x, y, unknown) * _penalty(
                    w_t, w_r, res, angles[a], x, y, top)
                k += 1
    # the order of the original stack (pushed in ascending order, popped from the top)
    return cand, sc, np.argsort(sc)[::-1]


@njit(cache=True, nogil=True)
def _subtree(data, starts, rows, cols, cells, angles, w, unknown, w_t, w_r, res, a, x, y, s, best, found):
    """Depth-first search of one coarsest-level candidate (a, x, y) with bound ``s``: children best
    first, a subtree whose bound is not above ``best`` cut. A leaf scoring above ``best`` becomes
    the best; returns the best score and writes its (a, dx, dy) into ``found``."""
    depth = starts.shape[0] - 2
    cap = 4 * (depth + 1) + 4
    st_x = np.empty(cap, dtype=np.int64)
    st_y = np.empty(cap, dtype=np.int64)
    st_d = np.empty(cap, dtype=np.int64)
    st_s = np.empty(cap)
    st_x[0], st_y[0], st_d[0], st_s[0] = x, y, depth, s
    sp = 1
    ks = np.empty(4)
    kx = np.empty(4, dtype=np.int64)
    ky = np.empty(4, dtype=np.int64)
    while sp > 0:
        sp -= 1
        s = st_s[sp]
        if s <= best:
            continue
        d = st_d[sp]
        x = st_x[sp]
        y = st_y[sp]
        if d == 0:
            best = s
            found[0], found[1], found[2] = a, x, y
            continue
        half = 1 << (d - 1)
        m = 0
        for i in range(2):
            for j in range(2):
                cx = x + i * half
                cy = y + j * half
                if cx <= w and cy <= w:
                    kx[m] = cx
                    ky[m] = cy
                    ks[m] = _block_score(data, starts[d - 1], rows, cols, half - 1, cells, a, cx, cy, unknown) * _penalty(
                        w_t, w_r, res, angles[a], cx, cy, half)
                    m += 1
        # push ascending so the best child is popped first
        for _ in range(m):
            lo = 0
            for q in range(1, m):
                if ks[q] < ks[lo]:
                    lo = q
            if ks[lo] > best:
                st_x[sp] = kx[lo]
                st_y[sp] = ky[lo]
                st_d[sp] = d - 1
                st_s[sp] = ks[lo]
                sp += 1
            ks[lo] = np.inf
    return best


@njit(cache=True, nogil=True)
def branch_and_bound(data, starts, rows, cols, cells, angles, w, min_score, unknown, w_t, w_r, res):
    """Depth-first branch-and-bound (Hess et al. 2016, Algorithm 3) with an explicit stack.

    Level d of the precomputation stack (``search.PrecomputationStack``: ``data[starts[d]:]``,
    padded by 2^d − 1 on the low side) holds the max-pooled grid of width 2^d; candidates are
    (angle, dx, dy) with dx, dy in [-w, w]; the coarsest ones are visited best bound first, each
    one's subtree wholly before the next (children best first), and a subtree whose bound is not
    above the best score so far is cut. Returns (angle index, dx, dy, score) or score < 0.
    """
    cand, sc, order = _top_candidates(data, starts, rows, cols, cells, angles, w, unknown, w_t, w_r, res)
    best = min_score
    found = np.array([-1, 0, 0], dtype=np.int64)
    for r in range(order.shape[0]):
        i = order[r]
        if sc[i] > best:
            best = _subtree(data, starts, rows, cols, cells, angles, w, unknown, w_t, w_r, res,
                            cand[i, 0], cand[i, 1], cand[i, 2], sc[i], best, found)
    return found[0], found[1], found[2], best


#: coarsest-level candidates are dealt to this many shares (by rank, in turn) in the parallel search;
#: a constant, so that the result does not depend on the thread count
BNB_SHARES = 8


@njit(cache=True, nogil=True, parallel=True)
def branch_and_bound_shared(data, starts, rows, cols, cells, angles, w, min_score, unknown, w_t, w_r, res):
    """``branch_and_bound``'s result, searched by numba's threads: the coarsest candidates, in
    visiting order, are dealt to ``BNB_SHARES`` shares, each searched as ``branch_and_bound``
    searches all of them (its own best for cutting). A share's best is the first leaf of the top
    score in its own order; the sequential search returns the first leaf of the top score in the
    whole order (a leaf replaces the best only when it scores above it, and a cut subtree holds
    none that does). So the share with the highest score, the earliest-ranked first among equal
    scores, holds exactly the sequential result."""
    cand, sc, order = _top_candidates(data, starts, rows, cols, cells, angles, w, unknown, w_t, w_r, res)
    n = BNB_SHARES
    bests = np.full(n, min_score)
    ranks = np.full(n, order.shape[0], dtype=np.int64)
    founds = np.full((n, 3), -1, dtype=np.int64)
    for c in prange(n):
        best = min_score
        found = np.array([-1, 0, 0], dtype=np.int64)
        for r in range(c, order.shape[0], n):
            i = order[r]
            if sc[i] > best:
                b = _subtree(data, starts, rows, cols, cells, angles, w, unknown, w_t, w_r, res,
                             cand[i, 0], cand[i, 1], cand[i, 2], sc[i], best, found)
                if b > best:
                    best = b
                    ranks[c] = r
        bests[c] = best
        founds[c, 0], founds[c, 1], founds[c, 2] = found[0], found[1], found[2]
    pick = 0
    for c in range(1, n):
        if bests[c] > bests[pick] or (bests[c] == bests[pick] and ranks[c] < ranks[pick]):
            pick = c
    return founds[pick, 0], founds[pick, 1], founds[pick, 2], bests[pick]


@njit(cache=True, nogil=True)
def score_covariance(scores, offsets, angles, n_points, out):
    """Covariance of (x, y, θ) over a score volume ``scores[angle, y, x]`` (Olson 2009, Sec. IV).

    Candidate weights are exp(N·(s − s_best)) (exponent clipped at −50); ``offsets`` are the
    metric x/y offsets of the lattice columns/rows. Writes the 3×3 moment matrix into ``out``
    (no floor added).
    """
    na, ny, nx = scores.shape
    best = -1e300
    for a in range(na):
        for iy in range(ny):
            for ix in range(nx):
                if scores[a, iy, ix] > best:
                    best = scores[a, iy, ix]
    s0 = 0.0
    sx = 0.0
    sy = 0.0
    st = 0.0
    sxx = 0.0
    syy = 0.0
    stt = 0.0
    sxy = 0.0
    sxt = 0.0
    syt = 0.0
    for a in range(na):
        th = angles[a]
        for iy in range(ny):
            y = offsets[iy]
            for ix in range(nx):
                e = n_points * (float(scores[a, iy, ix]) - best)
                if e < -50.0:
                    e = -50.0
                w = math.exp(e)
                x = offsets[ix]
                s0 += w
                sx += w * x
                sy += w * y
                st += w * th
                sxx += w * x * x
                syy += w * y * y
                stt += w * th * th
                sxy += w * x * y
                sxt += w * x * th
                syt += w * y * th
    mx = sx / s0
    my = sy / s0
    mt = st / s0
    out[0, 0] = sxx / s0 - mx * mx
    out[1, 1] = syy / s0 - my * my
    out[2, 2] = stt / s0 - mt * mt
    out[0, 1] = out[1, 0] = sxy / s0 - mx * my
    out[0, 2] = out[2, 0] = sxt / s0 - mx * mt
    out[1, 2] = out[2, 1] = syt / s0 - my * mt


@njit(cache=True)
def apply_delta_penalty(scores, angles, w_t, w_r, res):
    """Multiply ``scores[a, dy + w, dx + w]`` in place by the delta penalty exp(−(w_t·d + w_r·|Δθ|)²),
    d = |(dx, dy)|·res (the same factor ``branch_and_bound`` applies to single candidates)."""
    if w_t == 0.0 and w_r == 0.0:
        return
    a_n, k, _ = scores.shape
    w = (k - 1) // 2
    for a in range(a_n):
        for iy in range(k):
            for ix in range(k):
                scores[a, iy, ix] *= _penalty(w_t, w_r, res, angles[a], ix - w, iy - w, 1)


@njit(cache=True, nogil=True)
def apply_translation_prior(scores, res, sigma, n_points):
    """Multiply ``scores[a, dy + w, dx + w]`` in place by exp(−d² / (2σ²N)), d = |(dx, dy)|·res: a
    Gaussian prior on the translation from the prediction, in the units of a mean score over N
    points (``real_time.RealTimeCorrelativeScanMatcher.match``)."""
    a_n, k, _ = scores.shape
    w = (k - 1) // 2
    for iy in range(k):
        dy = (iy - w) * res
        for ix in range(k):
            dx = (ix - w) * res
            f = math.exp(-((dx * dx + dy * dy) / (sigma * sigma)) / (2.0 * n_points))
            for a in range(a_n):
                scores[a, iy, ix] *= f


@njit(cache=True, nogil=True)
def best_separated_peak(scores, a, iy, ix, lin, ang):
    """The highest positive local maximum of ``scores`` (≥ every neighbour of its 3 × 3 × 3
    neighbourhood inside the array) outside the box of ``ang`` angle steps and ``lin`` cells around
    (a, iy, ix); -inf when there is none. ``loop_closure.separated_margin``'s peaks, which its oracle
    in the tests finds with ``scipy.ndimage.maximum_filter`` (mode "nearest")."""
    na, ny, nx = scores.shape
    best = -np.inf
    for i in range(na):
        out_a = i < a - ang or i > a + ang
        for j in range(ny):
            out_y = j < iy - lin or j > iy + lin
            for k in range(nx):
                if not (out_a or out_y or k < ix - lin or k > ix + lin):
                    continue
                v = scores[i, j, k]
                if v <= 0 or v <= best:
                    continue
                peak = True
                for di in range(max(i - 1, 0), min(i + 2, na)):
                    for dj in range(max(j - 1, 0), min(j + 2, ny)):
                        for dk in range(max(k - 1, 0), min(k + 2, nx)):
                            if scores[di, dj, dk] > v:
                                peak = False
                if peak:
                    best = v
    return best


@njit(cache=True, nogil=True)
def laplace_cover(scores, n_points, res, angular_step, prior_sigmas, cov):
    """Raise ``cov`` (3×3, x/y/θ, in place) to cover the curvature (Laplace) covariance of the
    log-likelihood N·s at the best lattice pose of ``scores[angle, y, x]`` (lattice steps ``res``,
    ``res``, ``angular_step``): ``real_time._covariance``'s second half, whose numpy oracle (a
    least-squares quadratic through the 3 × 3 × 3 neighbourhood, then two eigen-decompositions) is
    in the tests.

    The neighbourhood is moved inside the volume at its edges. On that 3-level factorial design
    the least-squares quadratic has closed-form curvatures: the mean second difference along
    each axis, and Σ f·i·j / 12 for each cross term. Directions whose information (in units of
    the prior's sigmas) is below 1 get the prior's variance; then ``cov`` becomes the smallest
    A^½ W max(M, 1) Wᵀ A^½ that is ⪰ A = cov and ⪰ the Laplace covariance (M, W: its
    eigen-decomposition whitened by A). Volumes thinner than 3 along an axis are left as they are.
    """
    na, ny, nx = scores.shape
    if na < 3 or ny < 3 or nx < 3:
        return
    best = -np.inf
    a0 = 0
    y0 = 0
    x0 = 0
    for a in range(na):
        for iy in range(ny):
            for ix in range(nx):
                if scores[a, iy, ix] > best:
                    best = scores[a, iy, ix]
                    a0 = a
                    y0 = iy
                    x0 = ix
    ca = min(max(a0, 1), na - 2)
    cy = min(max(y0, 1), ny - 2)
    cx = min(max(x0, 1), nx - 2)
    sa = np.zeros(3)
    sy = np.zeros(3)
    sx = np.zeros(3)
    sxy = 0.0
    sxt = 0.0
    syt = 0.0
    for da in range(-1, 2):
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                f = n_points * float(scores[ca + da, cy + dy, cx + dx])
                sa[da + 1] += f
                sy[dy + 1] += f
                sx[dx + 1] += f
                sxy += f * dx * dy
                sxt += f * dx * da
                syt += f * dy * da
    info = np.empty((3, 3))
    info[0, 0] = -(sx[0] + sx[2] - 2.0 * sx[1]) / (9.0 * res * res)
    info[1, 1] = -(sy[0] + sy[2] - 2.0 * sy[1]) / (9.0 * res * res)
    info[2, 2] = -(sa[0] + sa[2] - 2.0 * sa[1]) / (9.0 * angular_step * angular_step)
    info[0, 1] = info[1, 0] = -sxy / (12.0 * res * res)
    info[0, 2] = info[2, 0] = -sxt / (12.0 * res * angular_step)
    info[1, 2] = info[2, 1] = -syt / (12.0 * res * angular_step)
    for i in range(3):
        for j in range(3):
            info[i, j] *= prior_sigmas[i] * prior_sigmas[j]
    lam, vec = np.linalg.eigh(info)
    lap = np.zeros((3, 3))
    for k in range(3):
        inv_l = 1.0 / max(lam[k], 1.0)
        for i in range(3):
            for j in range(3):
                lap[i, j] += vec[i, k] * inv_l * vec[j, k]
    for i in range(3):
        for j in range(3):
            lap[i, j] *= prior_sigmas[i] * prior_sigmas[j]
    # the cover of cov and lap
    sym = 0.5 * (cov + cov.T)
    la, va = np.linalg.eigh(sym)
    half = np.empty((3, 3))
    for k in range(3):
        r = math.sqrt(max(la[k], 1e-300))
        for i in range(3):
            half[i, k] = va[i, k] * r
    inv_half = np.linalg.inv(half)
    w = inv_half @ lap @ inv_half.T
    mu, wv = np.linalg.eigh(0.5 * (w + w.T))
    mid = np.zeros((3, 3))
    for k in range(3):
        m = max(mu[k], 1.0)
        for i in range(3):
            for j in range(3):
                mid[i, j] += wv[i, k] * m * wv[j, k]
    res_cov = half @ mid @ half.T
    for i in range(3):
        for j in range(3):
            cov[i, j] = 0.5 * (res_cov[i, j] + res_cov[j, i])
