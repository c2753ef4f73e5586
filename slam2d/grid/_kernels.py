"""Numba kernels of the grid: range insertion by exact ray traversal (Amanatides & Woo 1987).

Each kernel has a plain-numpy oracle in ``tests/test_grid_kernels.py``.
Cells are addressed as ``[row, col] = [y index, x index]`` from the grid's lower-left corner.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _apply(logodds, known, stamp, r, c, scan_id, delta, lo_min, lo_max):
    if stamp[r, c] == scan_id:
        return
    stamp[r, c] = scan_id
    v = logodds[r, c] + delta
    if v < lo_min:
        v = lo_min
    elif v > lo_max:
        v = lo_max
    logodds[r, c] = v
    known[r, c] = 1


@njit(cache=True)
def insert_rays(logodds, known, stamp, scan_id, ox, oy, ends, is_hit, hit_delta, miss_delta, lo_min, lo_max):
    """Insert rays from (ox, oy) to ``ends`` (M, 2), all in cell units (continuous, lower-left origin).

    Endpoints with ``is_hit`` get one hit update per scan even when several rays end in the
    same cell; every cell a ray crosses before its end gets one miss update unless it was
    already updated by this scan (hits are applied first, as in Cartographer). Rays whose
    ``is_hit`` is False mark free space along the whole ray, the end cell included.
    """
    rows, cols = logodds.shape
    m = ends.shape[0]
    for i in range(m):
        if is_hit[i]:
            c = int(math.floor(ends[i, 0]))
            r = int(math.floor(ends[i, 1]))
            if 0 <= r < rows and 0 <= c < cols:
                _apply(logodds, known, stamp, r, c, scan_id, hit_delta, lo_min, lo_max)
    for i in range(m):
        ex = ends[i, 0]
        ey = ends[i, 1]
        cx = int(math.floor(ox))
        cy = int(math.floor(oy))
        tx = int(math.floor(ex))
        ty = int(math.floor(ey))
        dx = ex - ox
        dy = ey - oy
        step_x = 1 if dx > 0 else -1
        step_y = 1 if dy > 0 else -1
        inf = 1e30
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
        n_steps = abs(tx - cx) + abs(ty - cy)
        for _ in range(n_steps + 1):
            if cx == tx and cy == ty:
                if not is_hit[i] and 0 <= cy < rows and 0 <= cx < cols:
                    _apply(logodds, known, stamp, cy, cx, scan_id, miss_delta, lo_min, lo_max)
                break
            if 0 <= cy < rows and 0 <= cx < cols:
                _apply(logodds, known, stamp, cy, cx, scan_id, miss_delta, lo_min, lo_max)
            if t_max_x < t_max_y:
                t_max_x += t_delta_x
                cx += step_x
            else:
                t_max_y += t_delta_y
                cy += step_y


@njit(cache=True)
def logodds_to_probability(logodds, known, unknown_value, out):
    rows, cols = logodds.shape
    for r in range(rows):
        for c in range(cols):
            if known[r, c]:
                out[r, c] = 1.0 / (1.0 + math.exp(-logodds[r, c]))
            else:
                out[r, c] = unknown_value
    return out
