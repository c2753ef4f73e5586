"""Numba kernels of the per-scan range data (Cartographer's ``RangeData`` and ``VoxelFilter``),
of the scan's surface tangents (``frontend.degenerate_direction``) and of the health report's
free-space test.

Plain-numpy oracles live in ``tests/test_range_data.py`` (the adaptive voxel filter's is the Python
bisection kept there), ``tests/test_frontend.py`` (tangents),
``tests/test_health.py`` (``pick_neighbours``) and, for ``free_space_counts``,
``slam2d.health._violation`` (compared in ``tests/test_health.py``).

Kernels that run for a few microseconds per scan keep the interpreter lock (no ``nogil``): released,
it goes to global SLAM's worker thread whenever that one waits for it, and local SLAM then waits up
to the switch interval (``backend/background.py``) to get it back after microseconds of work.
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


@njit(cache=True)
def scan_to_range_data(ranges, valid, no_return, angle_min, angle_increment, min_range, max_range, miss_length,
                       ox, oy, oth, hits, misses, surface_gap):
    """Hits and free-space ray ends of one scan in the tracking frame (laser mount ``ox, oy, oth``).

    Valid readings within [min_range, max_range] are hits; valid readings beyond max_range
    become misses cut at max_range; no-return beams become misses of ``miss_length`` (none
    when it is 0), cut at the nearer of the two returns that flank them (the nearest valid
    reading on either side, in beam order) where those two lie at most ``surface_gap`` apart:
    both beams beside it met one surface, so this beam met it too and got no echo (a dark or
    glossy patch, glass); free space beyond it would mark what lies behind that surface free. Writes
    into ``hits`` / ``misses`` (capacity = beam count each) and returns (number of hits,
    number of misses, number of far misses); misses come far ones first, then no-returns,
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
    far = nm
    if miss_length > 0.0:
        ends = np.empty(n)  # each no-return ray's length
        # the nearest valid reading before each beam (its index, or -1): a no-return's left flank
        left = np.empty(n, dtype=np.int64)
        last = -1
        for i in range(n):
            left[i] = last
            if valid[i] and not no_return[i] and float(ranges[i]) >= min_range:
                last = i
        right = -1
        for i in range(n - 1, -1, -1):
            if valid[i] and not no_return[i] and float(ranges[i]) >= min_range:
                right = i
                continue
            if not no_return[i]:
                continue
            length = miss_length
            a = left[i]
            if a >= 0 and right >= 0:
                ra = float(ranges[a])
                rb = float(ranges[right])
                ta = angle_min + angle_increment * a
                tb = angle_min + angle_increment * right
                gap = math.hypot(ra * math.cos(ta) - rb * math.cos(tb), ra * math.sin(ta) - rb * math.sin(tb))
                if gap <= surface_gap:  # one surface on both sides: the beam met it too
                    length = min(length, ra, rb)
            ends[i] = length
        for i in range(n):
            if no_return[i]:
                _put(misses, nm, ends[i], angle_min + angle_increment * i, ox, oy, c0, s0)
                nm += 1
    return nh, nm, far


@njit(cache=True)
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
def adaptive_voxel_indices(points, min_points, max_length):
    """``voxel_filter_indices`` at the coarsest cell up to ``max_length`` that keeps ``min_points``
    points: the cell is halved until enough remain, then bisected to within 10 % (the bisection of
    Cartographer's adaptive voxel filter; ``range_data.adaptive_voxel_filter`` is its Python oracle in
    the tests). The caller handles clouds of at most ``min_points`` points."""
    result = voxel_filter_indices(points, max_length)
    if result.shape[0] >= min_points:
        return result
    high = max_length
    while high > 0.01 * max_length:
        low = 0.5 * high
        result = voxel_filter_indices(points, low)
        if result.shape[0] >= min_points:
            while high / low > 1.1:
                mid = 0.5 * (low + high)
                cand = voxel_filter_indices(points, mid)
                if cand.shape[0] >= min_points:
                    low = mid
                    result = cand
                else:
                    high = mid
            return result
        high = low
    return result


@njit(cache=True, nogil=True)
def scan_tangents(points, neighbours, min_baseline, max_gap):
    """Unit tangent of each point from its k-th neighbours on either side in beam order, for the
    first k of ``neighbours`` whose baseline lies strictly between ``min_baseline`` and ``max_gap``;
    (tangents (n, 2), has-one mask (n,)). Same floating-point operations as the numpy version."""
    n = points.shape[0]
    tangent = np.zeros((n, 2))
    have = np.zeros(n, dtype=np.bool_)
    for k in neighbours:
        if 2 * k >= n:
            break
        for i in range(k, n - k):
            if have[i]:
                continue
            dx = points[i + k, 0] - points[i - k, 0]
            dy = points[i + k, 1] - points[i - k, 1]
            length = np.hypot(dx, dy)
            if min_baseline < length < max_gap:
                tangent[i, 0] = dx / length
                tangent[i, 1] = dy / length
                have[i] = True
    return tangent, have


@njit(cache=True)
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


@njit(cache=True)
def tangent_moments(points, neighbours, min_baseline, max_gap):
    """(how many points have a tangent, Σ tx², Σ tx·ty, Σ ty²) over the tangents of ``scan_tangents``:
    the point-to-line information of a scan, summed in beam order."""
    tangent, have = scan_tangents(points, neighbours, min_baseline, max_gap)
    n = 0
    sxx = 0.0
    sxy = 0.0
    syy = 0.0
    for i in range(points.shape[0]):
        if have[i]:
            n += 1
            sxx += tangent[i, 0] * tangent[i, 0]
            sxy += tangent[i, 0] * tangent[i, 1]
            syy += tangent[i, 1] * tangent[i, 1]
    return n, sxx, sxy, syy


@njit(cache=True, nogil=True)
def survey_band(ranges, threshold):
    """One batch of the no-return survey: its finite readings at or above ``threshold``, in order."""
    n = 0
    for i in range(ranges.shape[0]):
        r = ranges[i]
        if r >= threshold and r != math.inf and r != -math.inf:
            n += 1
    band = np.empty(n, dtype=ranges.dtype)
    n = 0
    for i in range(ranges.shape[0]):
        r = ranges[i]
        if r >= threshold and r != math.inf and r != -math.inf:
            band[n] = r
            n += 1
    return band


@njit(cache=True, nogil=True)
def pick_neighbours(origins, path, radius, same_span, per_pass):
    """The health report's neighbours: for every node i, its ``per_pass`` nearest other nodes within
    ``radius`` (inclusive) whose path distance to it is below ``same_span`` (same pass), then its
    ``per_pass`` nearest of the others within ``radius`` (other passes); nearest first, equal
    distances in index order. Rows (i, j, 1 if other pass) in that order, i ascending. Candidates
    come from a hash of square cells of side ``radius`` (the 3 × 3 cells around a node's own), sorted
    by cell, so no list of every node's neighbours is ever built; the oracle in the tests takes them
    from scipy's k-d tree."""
    n = origins.shape[0]
    out = np.empty((n * 2 * per_pass, 3), dtype=np.int64)
    if n == 0:
        return out
    cx = np.empty(n, dtype=np.int64)
    cy = np.empty(n, dtype=np.int64)
    for i in range(n):
        cx[i] = int(math.floor(origins[i, 0] / radius))
        cy[i] = int(math.floor(origins[i, 1] / radius))
    x0, y0 = cx.min() - 1, cy.min() - 1
    span = cy.max() - y0 + 2  # rows of the key; the 3 × 3 block of any node stays inside
    keys = (cx - x0) * span + (cy - y0)
    order = np.argsort(keys, kind="mergesort")
    sorted_keys = keys[order]
    r2 = radius * radius
    m = 0
    bd = np.empty((2, per_pass))
    bj = np.empty((2, per_pass), dtype=np.int64)
    cnt = np.zeros(2, dtype=np.int64)
    for i in range(n):
        cnt[0] = 0
        cnt[1] = 0
        for ddx in range(-1, 2):
            for ddy in range(-1, 2):
                k = keys[i] + ddx * span + ddy
                lo = np.searchsorted(sorted_keys, k, side="left")
                hi = np.searchsorted(sorted_keys, k, side="right")
                for p in range(lo, hi):
                    j = order[p]
                    if j == i:
                        continue
                    dx, dy = origins[j, 0] - origins[i, 0], origins[j, 1] - origins[i, 1]
                    if dx * dx + dy * dy > r2:
                        continue
                    d = np.hypot(dx, dy)
                    o = 0 if abs(path[j] - path[i]) < same_span else 1
                    c = cnt[o]
                    if c == per_pass and not (d < bd[o, c - 1] or (d == bd[o, c - 1] and j < bj[o, c - 1])):
                        continue
                    kk = c if c < per_pass else per_pass - 1  # the slot it takes before shifting
                    while kk > 0 and (bd[o, kk - 1] > d or (bd[o, kk - 1] == d and bj[o, kk - 1] > j)):
                        if kk < per_pass:
                            bd[o, kk] = bd[o, kk - 1]
                            bj[o, kk] = bj[o, kk - 1]
                        kk -= 1
                    bd[o, kk] = d
                    bj[o, kk] = j
                    if c < per_pass:
                        cnt[o] = c + 1
        for o in range(2):
            for kk in range(cnt[o]):
                out[m, 0] = i
                out[m, 1] = bj[o, kk]
                out[m, 2] = o
                m += 1
    return out[:m]


@njit(cache=True, nogil=True)
def free_space_counts(hits, hit_start, origins, bearings, ranges, beam_start, steps, pairs, resolution, range_share):
    """For every pair (a, b): (hits of node a lying in node b's free space, hits of a inside b's field
    of view). Node a's hits are ``hits[hit_start[a]:hit_start[a + 1]]`` (map frame); node b's beams
    are its sorted ``bearings`` and ``ranges`` from ``origins[b]`` in ``[beam_start[b], beam_start[b + 1])``,
    ``steps[b]`` their median bearing step. A hit is seen when the two beams either side of its
    bearing are at most 3 steps apart, and violates when it lies more than
    ``2 · resolution + range_share · range`` in front of the nearer of their returns."""
    out = np.zeros((pairs.shape[0], 2), dtype=np.int64)
    two_pi = 2.0 * math.pi
    for p in range(pairs.shape[0]):
        a, b = pairs[p, 0], pairs[p, 1]
        s0, s1 = beam_start[b], beam_start[b + 1]
        nb = s1 - s0
        if nb < 3:
            continue
        ox, oy = origins[b, 0], origins[b, 1]
        bad = 0
        seen = 0
        for h in range(hit_start[a], hit_start[a + 1]):
            dx, dy = hits[h, 0] - ox, hits[h, 1] - oy
            qb = math.atan2(dy, dx)
            qr = math.hypot(dx, dy)
            idx = np.searchsorted(bearings[s0:s1], qb)
            lo = (idx - 1) % nb
            hi = idx % nb
            span = bearings[s0 + hi] - bearings[s0 + lo]
            span -= two_pi * math.floor(span / two_pi)
            if span <= 3.0 * steps[b]:
                seen += 1
                free = min(ranges[s0 + lo], ranges[s0 + hi])
                if qr < free - (2.0 * resolution + range_share * qr):
                    bad += 1
        out[p, 0] = bad
        out[p, 1] = seen
    return out


@njit(cache=True, nogil=True)
def world_beams(poses, origins, hits, hit_start, misses, miss_start):
    """Every node's rays in the map frame, for the health report's free-space test. Node k, at
    ``poses[k]``, has its sensor at ``origins[k]`` and its hits and misses at
    ``hits[hit_start[k]:hit_start[k + 1]]`` and ``misses[miss_start[k]:miss_start[k + 1]]`` (tracking
    frame). Returns the sensors and hits in the map frame, and per node its beams: bearings sorted
    (stably) and ranges from the sensor to every ray end (hits, then misses), from
    ``beam_start[k]``, with the median bearing step (inf for fewer than 3 beams).
    ``health._node_world`` and ``health._beams`` are its oracle."""
    n = poses.shape[0]
    o_w = np.empty((n, 2))
    h_w = np.empty((hits.shape[0], 2))
    beam_start = np.zeros(n + 1, dtype=np.int64)
    for k in range(n):
        beam_start[k + 1] = beam_start[k] + (hit_start[k + 1] - hit_start[k]) + (miss_start[k + 1] - miss_start[k])
    bearings = np.empty(beam_start[n])
    ranges = np.empty(beam_start[n])
    steps = np.full(n, np.inf)
    for k in range(n):
        px, py = poses[k, 0], poses[k, 1]
        c, s = math.cos(poses[k, 2]), math.sin(poses[k, 2])
        ox = px + c * origins[k, 0] - s * origins[k, 1]
        oy = py + s * origins[k, 0] + c * origins[k, 1]
        o_w[k, 0] = ox
        o_w[k, 1] = oy
        h0, h1 = hit_start[k], hit_start[k + 1]
        m0, m1 = miss_start[k], miss_start[k + 1]
        m = (h1 - h0) + (m1 - m0)
        b = np.empty(m)
        r = np.empty(m)
        for i in range(m):
            if i < h1 - h0:
                x, y = hits[h0 + i, 0], hits[h0 + i, 1]
            else:
                x, y = misses[m0 + i - (h1 - h0), 0], misses[m0 + i - (h1 - h0), 1]
            wx = px + c * x - s * y
            wy = py + s * x + c * y
            if i < h1 - h0:
                h_w[h0 + i, 0] = wx
                h_w[h0 + i, 1] = wy
            b[i] = math.atan2(wy - oy, wx - ox)
            r[i] = math.hypot(wx - ox, wy - oy)
        order = np.argsort(b, kind="mergesort")
        s0 = beam_start[k]
        for i in range(m):
            bearings[s0 + i] = b[order[i]]
            ranges[s0 + i] = r[order[i]]
        if m > 2:
            steps[k] = np.median(np.diff(bearings[s0:s0 + m]))
    return o_w, h_w, bearings, ranges, beam_start, steps
