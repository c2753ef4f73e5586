"""Numba kernels of the per-scan range data (Cartographer's ``RangeData`` and ``VoxelFilter``).

Plain-numpy oracles of both live in ``tests/test_range_data.py``.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _put(out, k, length, angle, ox, oy, c0, s0):
    """out[k] = the point ``length`` along beam ``angle`` of the laser, in the tracking frame."""
    px = length * math.cos(angle)
    py = length * math.sin(angle)
    out[k, 0] = ox + c0 * px - s0 * py
    out[k, 1] = oy + s0 * px + c0 * py


@njit(cache=True, nogil=True)
def scan_to_range_data(ranges, valid, no_return, angle_min, angle_increment, min_range, max_range, miss_length,
                       ox, oy, oth, hits, misses):
    """Hits and free-space ray ends of one scan in the tracking frame (laser mount ``ox, oy, oth``).

    Valid readings within [min_range, max_range] are hits; valid readings beyond max_range
    become misses cut at max_range; no-return beams become misses of ``miss_length`` (none
    when it is 0). Writes into ``hits`` / ``misses`` (capacity = beam count each) and
    returns (number of hits, number of misses); misses come far ones first, then no-returns,
    each in beam order.
    """
    n = ranges.shape[0]
    c0 = math.cos(oth)
    s0 = math.sin(oth)
    nh = 0
    nm = 0
    for i in range(n):
        r = float(ranges[i])
        if valid[i] and min_range <= r <= max_range:
            _put(hits, nh, r, angle_min + angle_increment * i, ox, oy, c0, s0)
            nh += 1
    for i in range(n):
        r = float(ranges[i])
        if valid[i] and r >= min_range and r > max_range:
            _put(misses, nm, max_range, angle_min + angle_increment * i, ox, oy, c0, s0)
            nm += 1
    if miss_length > 0.0:
        for i in range(n):
            if no_return[i]:
                _put(misses, nm, miss_length, angle_min + angle_increment * i, ox, oy, c0, s0)
                nm += 1
    return nh, nm


@njit(cache=True, nogil=True)
def voxel_filter_indices(points, size):
    """Indices of the first point (in input order) of every occupied ``size`` × ``size`` cell, increasing."""
    n = points.shape[0]
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        kx = np.int64(math.floor(points[i, 0] / size))
        ky = np.int64(math.floor(points[i, 1] / size))
        keys[i] = (kx << 32) ^ (ky & 0xFFFFFFFF)
    order = np.argsort(keys, kind="mergesort")  # stable: the first point of a cell comes first
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for j in range(n):
        if j == 0 or keys[order[j]] != keys[order[j - 1]]:
            keep[m] = order[j]
            m += 1
    return np.sort(keep[:m])


@njit(cache=True, nogil=True)
def classify_readings(ranges, no_return_value, valid, no_return):
    """Per beam: ``no_return`` = +inf or at/above ``no_return_value`` (NaN: none); ``valid`` = a
    positive finite reading that is not a no-return. Returns (index of the first negative
    reading or −1, True when every reading is NaN)."""
    n = ranges.shape[0]
    first_negative = -1
    all_nan = True
    for i in range(n):
        r = ranges[i]
        nan = r != r
        if not nan:
            all_nan = False
        if r < 0.0 and first_negative < 0:
            first_negative = i
        nr = r == math.inf or (no_return_value == no_return_value and r >= no_return_value)
        no_return[i] = nr
        valid[i] = (not nan) and (not nr) and r > 0.0
    return first_negative, all_nan


@njit(cache=True, nogil=True)
def finite_max_count(ranges):
    """(largest finite reading, how many readings equal it); (−inf, 0) when none is finite."""
    top = -math.inf
    count = 0
    for i in range(ranges.shape[0]):
        r = ranges[i]
        if r == r and r != math.inf and r != -math.inf:
            if r > top:
                top = r
                count = 1
            elif r == top:
                count += 1
    return top, count
