"""Numba kernels of the scan matchers. Each one has a plain-numpy oracle in ``tests/test_matching_kernels.py``.

Grid arrays are ``values[row, col]`` (row = y); ``origin`` is the lower-left corner of cell
(0, 0); a point falls in cell ``floor((p - origin) / resolution)``. Cells outside the array
read as ``unknown``.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
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


@njit(cache=True)
def score_window(values, cells, w, unknown):
    """Mean grid value for every angle and integer offset in [-w, w]²: scores[a, dy + w, dx + w]."""
    rows, cols = values.shape
    a_n, n = cells.shape[0], cells.shape[1]
    k = 2 * w + 1
    out = np.zeros((a_n, k, k), dtype=np.float32)
    for a in range(a_n):
        acc = out[a]
        for i in range(n):
            c0 = cells[a, i, 0] - w
            r0 = cells[a, i, 1] - w
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
                    else:
                        acc[dy, dx] += values[r, c]
        for dy in range(k):
            for dx in range(k):
                acc[dy, dx] /= n
    return out


@njit(cache=True)
def score_candidates(values, cells, cands, unknown):
    """Mean grid value for candidates (K, 3) = [angle index, dx, dy] (integer cells)."""
    rows, cols = values.shape
    n = cells.shape[1]
    k_n = cands.shape[0]
    out = np.empty(k_n, dtype=np.float32)
    for k in range(k_n):
        a = cands[k, 0]
        dx = cands[k, 1]
        dy = cands[k, 2]
        s = 0.0
        for i in range(n):
            c = cells[a, i, 0] + dx
            r = cells[a, i, 1] + dy
            if r < 0 or r >= rows or c < 0 or c >= cols:
                s += unknown
            else:
                s += values[r, c]
        out[k] = s / n
    return out


@njit(cache=True)
def _cubic_weights(t, w, dw):
    t2 = t * t
    t3 = t2 * t
    w[0] = 0.5 * (-t3 + 2.0 * t2 - t)
    w[1] = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0)
    w[2] = 0.5 * (-3.0 * t3 + 4.0 * t2 + t)
    w[3] = 0.5 * (t3 - t2)
    dw[0] = 0.5 * (-3.0 * t2 + 4.0 * t - 1.0)
    dw[1] = 0.5 * (9.0 * t2 - 10.0 * t)
    dw[2] = 0.5 * (-9.0 * t2 + 8.0 * t + 1.0)
    dw[3] = 0.5 * (3.0 * t2 - 2.0 * t)


@njit(cache=True)
def bicubic(values, u, v, unknown, out):
    """Catmull-Rom bicubic value and gradient at continuous cell coordinates (u = x, v = y; cell centres at +0.5).

    Writes (value, d/du, d/dv) into ``out``.
    """
    rows, cols = values.shape
    uu = u - 0.5
    vv = v - 0.5
    i0 = int(math.floor(uu))
    j0 = int(math.floor(vv))
    wx = np.empty(4)
    dwx = np.empty(4)
    wy = np.empty(4)
    dwy = np.empty(4)
    _cubic_weights(uu - i0, wx, dwx)
    _cubic_weights(vv - j0, wy, dwy)
    f = 0.0
    fu = 0.0
    fv = 0.0
    for jj in range(4):
        r = j0 - 1 + jj
        for ii in range(4):
            c = i0 - 1 + ii
            if r < 0 or r >= rows or c < 0 or c >= cols:
                val = unknown
            else:
                val = values[r, c]
            f += wy[jj] * wx[ii] * val
            fu += wy[jj] * dwx[ii] * val
            fv += dwy[jj] * wx[ii] * val
    out[0] = f
    out[1] = fu
    out[2] = fv


@njit(cache=True)
def refine_pose(values, ox, oy, res, unknown, points, x0, y0, t0, w_occ, w_t, w_r, max_iter):
    """Levenberg-Marquardt on Σ (w_occ/√N · (1 − P(T p)))² + w_t²|t − t0|² + w_r²(θ − θ0)².

    Cartographer's Ceres scan matcher cost on a bicubic-interpolated probability grid.
    Returns (x, y, theta, final cost, iterations).
    """
    n = points.shape[0]
    scale = w_occ / math.sqrt(max(n, 1))
    x, y, t = x0, y0, t0
    lam = 1e-3
    buf = np.empty(3)

    def cost_at(x, y, t):
        c = math.cos(t)
        s = math.sin(t)
        tot = 0.0
        for i in range(n):
            px = x + c * points[i, 0] - s * points[i, 1]
            py = y + s * points[i, 0] + c * points[i, 1]
            bicubic(values, (px - ox) / res, (py - oy) / res, unknown, buf)
            r = scale * (1.0 - buf[0])
            tot += r * r
        tot += (w_t * (x - x0)) ** 2 + (w_t * (y - y0)) ** 2 + (w_r * (t - t0)) ** 2
        return tot

    cost = cost_at(x, y, t)
    it = 0
    step = 1.0
    for it in range(max_iter):
        c = math.cos(t)
        s = math.sin(t)
        h = np.zeros((3, 3))
        g = np.zeros(3)
        for i in range(n):
            px0 = points[i, 0]
            py0 = points[i, 1]
            px = x + c * px0 - s * py0
            py = y + s * px0 + c * py0
            bicubic(values, (px - ox) / res, (py - oy) / res, unknown, buf)
            r = scale * (1.0 - buf[0])
            gx = -scale * buf[1] / res
            gy = -scale * buf[2] / res
            gt = gx * (-s * px0 - c * py0) + gy * (c * px0 - s * py0)
            jac = (gx, gy, gt)
            for a in range(3):
                g[a] += jac[a] * r
                for b in range(3):
                    h[a, b] += jac[a] * jac[b]
        h[0, 0] += w_t * w_t
        h[1, 1] += w_t * w_t
        h[2, 2] += w_r * w_r
        g[0] += w_t * w_t * (x - x0)
        g[1] += w_t * w_t * (y - y0)
        g[2] += w_r * w_r * (t - t0)
        improved = False
        for _ in range(10):
            hd = h.copy()
            for a in range(3):
                hd[a, a] += lam * (h[a, a] + 1e-9)
            d = np.linalg.solve(hd, -g)
            nx, ny, nt = x + d[0], y + d[1], t + d[2]
            nc = cost_at(nx, ny, nt)
            if nc < cost:
                x, y, t = nx, ny, nt
                step = abs(d[0]) + abs(d[1]) + abs(d[2])
                cost = nc
                lam = max(lam * 0.3, 1e-7)
                improved = True
                break
            lam *= 10.0
        if not improved or step < 1e-7:
            break
    return x, y, t, cost, it + 1
