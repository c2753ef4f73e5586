"""Matching kernels against plain-numpy oracles; branch-and-bound against exhaustive search."""
import math

import numpy as np
import pytest

from slam2d.matching import _kernels
from slam2d.matching.search import (DeltaPenalty, MatchGrid, PrecomputationStack, SearchParameters, angular_step,
                                    branch_and_bound, exhaustive, sliding_max)


def test_rotated_cells_oracle():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (50, 2))
    angles = np.linspace(-0.2, 0.2, 7)
    got = _kernels.rotated_cells(pts, 1.3, -0.7, 0.4, angles, -10.0, -12.0, 20.0)
    for a, da in enumerate(angles):
        t = 0.4 + da
        R = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        w = pts @ R.T + [1.3, -0.7]
        want = np.floor((w - [-10.0, -12.0]) * 20.0).astype(int)
        np.testing.assert_array_equal(got[a], want)


def score_oracle(values, cells, w, unknown):
    rows, cols = values.shape
    out = np.zeros((cells.shape[0], 2 * w + 1, 2 * w + 1))
    for dy in range(-w, w + 1):
        for dx in range(-w, w + 1):
            c = cells[:, :, 0] + dx
            r = cells[:, :, 1] + dy
            inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
            v = np.where(inside, values[np.clip(r, 0, rows - 1), np.clip(c, 0, cols - 1)], unknown)
            out[:, dy + w, dx + w] = v.mean(axis=1)
    return out


def test_score_window_and_candidates_oracle():
    rng = np.random.default_rng(1)
    values = rng.random((40, 50)).astype(np.float32)
    cells = rng.integers(-3, 55, size=(4, 30, 2)).astype(np.int32)
    got = _kernels.score_window(values, cells, 3, np.float32(0.1))
    want = score_oracle(values, cells, 3, 0.1)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    cands = np.array([[a, dx, dy] for a in range(4) for dx in range(-3, 4) for dy in range(-3, 4)], np.int32)
    sc = _kernels.score_candidates(values, cells, cands, np.float32(0.1))
    np.testing.assert_allclose(sc, [want[a, dy + 3, dx + 3] for a, dx, dy in cands], rtol=1e-5)


@pytest.mark.parametrize("dtype,unknown", [(np.float32, 0.1), (np.uint8, 31.0)])
@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (23, 31)])
def test_precomputation_levels_oracle(dtype, unknown, shape):
    """Each level (built from the level below) holds, at [r + 2^d − 1, c + 2^d − 1], the max over the
    2^d × 2^d block starting at grid cell (r, c), cells outside the grid counting as ``unknown``."""
    rng = np.random.default_rng(shape[0])
    v = (rng.random(shape) * 255).astype(dtype) if dtype == np.uint8 else rng.random(shape).astype(dtype)
    st = PrecomputationStack(MatchGrid(v, np.zeros(2), 0.05, unknown), 5)
    rows, cols = shape
    for d in range(6):
        w, p = 1 << d, (1 << d) - 1
        big = np.full((rows + 2 * w, cols + 2 * w), dtype(unknown), dtype)
        big[w:w + rows, w:w + cols] = v
        lvl = st.level(d)
        assert lvl.shape == (rows + p, cols + p)
        for r in range(-p, rows):
            for c in range(-p, cols):
                assert lvl[r + p, c + p] == big[r + w:r + 2 * w, c + w:c + 2 * w].max(), (d, r, c)


@pytest.mark.parametrize("width", [1, 2, 4, 8, 16])
def test_sliding_max_oracle(width):
    rng = np.random.default_rng(width)
    v = rng.random((23, 31)).astype(np.float32)
    got = sliding_max(v, width, 0.05)
    pad = np.full((23 + width, 31 + width), 0.05, np.float32)
    pad[:23, :31] = v
    for r in range(23):
        for c in range(31):
            assert got[r, c] == pad[r:r + width, c:c + width].max()


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.uint8])
def test_precomputation_stack_oracle(dtype):
    """Level d holds the maximum of every 2^d block that overlaps the grid, in the grid's dtype:
    it is padded by 2^d − 1 on the low side; cells outside the grid count as unknown."""
    rng = np.random.default_rng(4)
    raw = rng.random((11, 17)) ** 2
    values = np.round(raw * 255).astype(np.uint8) if dtype == np.uint8 else raw.astype(dtype)
    unknown = 100.0 if dtype == np.uint8 else 0.375
    stack = PrecomputationStack(MatchGrid(values, np.zeros(2), 0.05, unknown), 4)
    np.testing.assert_array_equal(stack.grid.values, values)
    assert np.shares_memory(stack.grid.values, stack.data)  # level 0 is the stack's only copy
    assert stack.nbytes == sum((11 + p) * (17 + p) for p in stack.offsets) * values.itemsize
    for d in range(5):
        wd, p = 1 << d, stack.offsets[d]
        lev = stack.level(d)
        assert p == wd - 1 and lev.shape == (11 + p, 17 + p) and lev.dtype == values.dtype
        big = np.full((11 + 2 * wd, 17 + 2 * wd), unknown)
        big[wd:wd + 11, wd:wd + 17] = values
        for r in range(-p, 11):
            for c in range(-p, 17):
                assert lev[r + p, c + p] == big[r + wd:r + 2 * wd, c + wd:c + 2 * wd].max()
    # an unknown value the dtype cannot hold is rounded up, so the levels stay upper bounds
    zeros = PrecomputationStack(MatchGrid(np.zeros((3, 3), np.uint8), np.zeros(2), 0.05, 30.2), 1)
    assert zeros.level(1)[0, 0] == 31 and zeros.level(1)[1, 1] == 0


def bicubic_oracle(values, u, v, unknown):
    """Catmull-Rom as separable 1-D cubic convolution, plain numpy."""
    def w(t):
        t = abs(t)
        if t <= 1:
            return 1.5 * t ** 3 - 2.5 * t ** 2 + 1
        if t < 2:
            return -0.5 * t ** 3 + 2.5 * t ** 2 - 4 * t + 2
        return 0.0
    uu, vv = u - 0.5, v - 0.5
    i0, j0 = math.floor(uu), math.floor(vv)
    s = 0.0
    for j in range(j0 - 1, j0 + 3):
        for i in range(i0 - 1, i0 + 3):
            val = values[j, i] if 0 <= j < values.shape[0] and 0 <= i < values.shape[1] else unknown
            s += w(uu - i) * w(vv - j) * val
    return s


def test_bicubic_value_and_gradient():
    rng = np.random.default_rng(2)
    values = rng.random((12, 14))
    out = np.empty(3)
    for _ in range(50):
        u, v = rng.uniform(-1, 15), rng.uniform(-1, 13)
        _kernels.bicubic(values, u, v, 0.2, out, _kernels.ALL_KNOWN)
        assert out[0] == pytest.approx(bicubic_oracle(values, u, v, 0.2), abs=1e-9)
        h = 1e-6
        du = (bicubic_oracle(values, u + h, v, 0.2) - bicubic_oracle(values, u - h, v, 0.2)) / (2 * h)
        dv = (bicubic_oracle(values, u, v + h, 0.2) - bicubic_oracle(values, u, v - h, 0.2)) / (2 * h)
        assert out[1] == pytest.approx(du, abs=1e-5) and out[2] == pytest.approx(dv, abs=1e-5)


def test_bicubic_inside_the_grid_is_bit_identical_to_the_general_path():
    """A point whose 4 × 4 cells lie inside an unmasked, unscaled grid takes ``_bicubic``'s short path;
    a mask that marks every cell observed sends the same point through the per-cell path. Both
    must give the same bits (same sums in the same order), on float32 and float64 grids."""
    rng = np.random.default_rng(7)
    for dtype in (np.float32, np.float64):
        values = rng.random((12, 14)).astype(dtype)
        all_observed = np.ones(values.shape, dtype=np.int32)
        fast, general = np.empty(3), np.empty(3)
        for _ in range(200):
            u, v = rng.uniform(1.6, 12.4), rng.uniform(1.6, 10.4)  # every cell of the 4 × 4 inside
            _kernels.bicubic(values, u, v, 0.3, fast, _kernels.ALL_KNOWN)
            _kernels.bicubic(values, u, v, 0.3, general, all_observed)
            assert fast.tobytes() == general.tobytes()
            assert fast[0] == pytest.approx(bicubic_oracle(values, u, v, 0.3), abs=1e-6)


def unobserved_oracle(values, known, unknown):
    """``values`` with every never-observed cell replaced as ``_kernels._unobserved`` reads it: the
    mean of the observed free cells (< 0.5) two cells away along a row or column beyond an observed
    occupied one (> 0.5); ``unknown`` where there is none. Plain loops."""
    rows, cols = values.shape
    out = values.astype(np.float64)
    for r in range(rows):
        for c in range(cols):
            if known[r, c] > 0:
                continue
            found = []
            for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                r1, c1, r2, c2 = r + dr, c + dc, r + 2 * dr, c + 2 * dc
                if 0 <= r2 < rows and 0 <= c2 < cols and known[r1, c1] > 0 and values[r1, c1] > 0.5 \
                        and known[r2, c2] > 0 and values[r2, c2] < 0.5:
                    found.append(float(values[r2, c2]))
            out[r, c] = sum(found) / len(found) if found else unknown
    return out


def test_bicubic_reads_unobserved_cells_as_the_oracle_says():
    """With a ``known`` mask (an active grid's stamps), a never-updated cell reads as the free side of
    a surface it lies just behind, else as ``unknown``: the oracle on the grid with those cells
    replaced; values and gradients equal (to float rounding)."""
    rng = np.random.default_rng(4)
    values = rng.random((12, 14)).astype(np.float32)
    stamps = rng.integers(0, 3, values.shape).astype(np.int32)  # 0: never updated
    swapped = unobserved_oracle(values, stamps, 0.375)
    assert (swapped != np.where(stamps > 0, values, 0.375)).any()  # some cells are mirrored
    out, ref = np.empty(3), np.empty(3)
    for _ in range(50):
        u, v = rng.uniform(-1, 15), rng.uniform(-1, 13)
        _kernels.bicubic(values, u, v, 0.375, out, stamps)
        _kernels.bicubic(swapped, u, v, 0.375, ref, _kernels.ALL_KNOWN)
        assert out[0] == pytest.approx(bicubic_oracle(swapped, u, v, 0.375), abs=1e-6)
        np.testing.assert_allclose(out, ref, rtol=0, atol=1e-9)


def test_refinement_with_a_known_mask_equals_refinement_on_the_swapped_grid():
    from slam2d.matching.refine import refine

    rng = np.random.default_rng(6)
    values = rng.random((40, 40)).astype(np.float32)
    stamps = (rng.random(values.shape) > 0.4).astype(np.int32)
    swapped = unobserved_oracle(values, stamps, 0.4375)
    pts = rng.uniform(0.3, 1.7, (60, 2))
    masked = MatchGrid(values, np.zeros(2), 0.05, 0.4375, known=stamps)
    plain = MatchGrid(swapped, np.zeros(2), 0.05, 0.4375)
    for init in ([0.01, -0.02, 0.03], [0.0, 0.0, 0.0]):
        a, ca = refine(masked, np.array(init), pts, 1.0, 1.0, 1.0, 20)
        b, cb = refine(plain, np.array(init), pts, 1.0, 1.0, 1.0, 20)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
        assert ca == pytest.approx(cb, abs=1e-9)


def test_angular_step_rule():
    assert angular_step(0.05, 30.0) == pytest.approx(math.acos(1 - 0.05 ** 2 / (2 * 30.0 ** 2)))
    # the farthest point moves by about one cell per step
    assert 30.0 * angular_step(0.05, 30.0) == pytest.approx(0.05, rel=1e-3)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("depth", [1, 2, 3])
def test_branch_and_bound_equals_exhaustive(seed, depth):
    rng = np.random.default_rng(seed)
    values = (rng.random((80, 90)) ** 3).astype(np.float32)
    grid = MatchGrid(values, np.array([-2.0, -2.0]), 0.05, 0.1)
    pts = rng.uniform(-1.5, 1.5, (40, 2))
    params = SearchParameters.make(0.3, 0.05, 0.05, pts)
    cells = grid.cells(pts, (0.2, 0.1, 0.0), params.angles)
    pen = DeltaPenalty(0.5 * seed, 0.3 * seed)
    ex = exhaustive(grid, cells, params.linear_cells, pen, params.angles)
    stack = PrecomputationStack(grid, depth)
    found = branch_and_bound(stack, cells, params.linear_cells, 0.0, pen, params.angles)
    a, dx, dy, s = found
    w = params.linear_cells
    assert s == pytest.approx(float(ex.max()), rel=1e-6)
    assert ex[a, dy + w, dx + w] == pytest.approx(s, rel=1e-6)
    # above the best score nothing is found
    assert branch_and_bound(stack, cells, w, float(ex.max()) + 1e-6, pen, params.angles) is None


def covariance_oracle(scores, offs, th, n_points):
    weights = np.exp(np.clip(n_points * (scores.astype(np.float64) - scores.max()), -50.0, 0.0))
    tot = weights.sum()
    dx = offs[None, None, :]
    dy = offs[None, :, None]
    dt = th[:, None, None]
    comps = [c * np.ones_like(weights) for c in (dx, dy, dt)]
    means = [(weights * c).sum() / tot for c in comps]
    cov = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            cov[i, j] = (weights * (comps[i] - means[i]) * (comps[j] - means[j])).sum() / tot
    return cov


@pytest.mark.parametrize("seed", range(3))
def test_score_covariance_matches_oracle(seed):
    rng = np.random.default_rng(seed)
    scores = rng.uniform(0.5, 0.9, (7, 9, 9)).astype(np.float32)
    scores[3, 4, 6] = 0.95
    offs = np.arange(-4, 5) * 0.05
    th = np.linspace(-0.03, 0.03, 7)
    out = np.empty((3, 3))
    _kernels.score_covariance(scores, offs, th, 40.0, out)
    np.testing.assert_allclose(out, covariance_oracle(scores, offs, th, 40.0), rtol=1e-6, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(out) > 0)


def test_delta_penalty_matches_oracle():
    rng = np.random.default_rng(9)
    w, res = 4, 0.05
    angles = np.linspace(-0.1, 0.1, 5)
    scores = rng.uniform(0.2, 0.9, (5, 2 * w + 1, 2 * w + 1)).astype(np.float32)
    got = scores.copy()
    _kernels.apply_delta_penalty(got, angles, 0.7, 2.0, res)
    offs = np.arange(-w, w + 1) * res
    dist = np.hypot(offs[None, :], offs[:, None])
    factor = np.exp(-np.square(0.7 * dist[None] + 2.0 * np.abs(angles)[:, None, None]))
    np.testing.assert_allclose(got, scores * factor, rtol=1e-6)
    assert got[2, w, w] == scores[2, w, w]  # the predicted pose is not penalized


#: seeded random cases of the border property test below (all of them are checked)
BORDER_CASES = 3000


def _border_case(rng):
    """A small grid (float32 or uint8, random unknown value) and a search whose window crosses a border.

    Each axis puts the scan's cells near the low border, near the high border, or anywhere
    (partly or wholly outside the grid included).
    """
    rows, cols = (int(n) for n in rng.integers(3, 40, 2))
    depth = int(rng.integers(1, 6))
    w = int(rng.integers(0, 14))
    raw = rng.random((rows, cols)) ** 3
    if rng.random() < 0.5:
        values = np.round(raw * 255).astype(np.uint8)
        unknown = float(rng.integers(0, 256))
    else:
        values = raw.astype(np.float32)
        unknown = float(np.float32(rng.random()))
    a_n = int(rng.integers(1, 5))
    n = int(rng.integers(1, 25))
    spread = int(rng.integers(1, max(rows, cols) + 1))
    top = 1 << depth
    center = []
    for size in (cols, rows):
        kind = rng.integers(3)
        if kind == 0:
            center.append(int(rng.integers(-w - top - spread, top + 1)))
        elif kind == 1:
            center.append(int(rng.integers(size - top - 1, size + w + top + spread)))
        else:
            center.append(int(rng.integers(-w - spread, size + w + spread)))
    cells = (np.array(center) + rng.integers(-spread, spread + 1, (a_n, n, 2))).astype(np.int32)
    angles = np.sort(rng.uniform(-0.2, 0.2, a_n))
    pen = DeltaPenalty(rng.uniform(0, 3), rng.uniform(0, 5)) if rng.random() < 0.5 else None
    return MatchGrid(values, np.zeros(2), 0.05, unknown), depth, cells, w, angles, pen


def bnb_disagreement(grid, stack, cells, w, min_score, pen, angles):
    """None when branch-and-bound agrees with exhaustive search, else a description.

    Agreement: the same best score (bit for bit on uint8 grids without a penalty, else within
    float rounding, as the exhaustive kernel sums in float32 and the B&B kernel in float64),
    the returned pose scoring that best, and None exactly when nothing beats ``min_score``.
    """
    ex = exhaustive(grid, cells, w, pen, angles)
    best = float(ex.max())
    found = branch_and_bound(stack, cells, w, min_score, pen, angles)
    if best <= min_score:
        return None if found is None else f"found {found} though the best is {best} <= {min_score}"
    if found is None:
        return f"none found, exhaustive best {best}"
    a, dx, dy, s = found
    if not (0 <= a < cells.shape[0] and -w <= dx <= w and -w <= dy <= w):
        return f"{found} outside the lattice"
    exact = grid.values.dtype == np.uint8 and pen is None
    tol = 0.0 if exact else 1e-5 * best
    if abs(float(np.float32(s)) - best) > tol or abs(float(ex[a, dy + w, dx + w]) - best) > tol:
        return f"B&B {s} at {found[:3]} (exhaustive there {ex[a, dy + w, dx + w]}), exhaustive best {best}"
    return None


def test_branch_and_bound_is_exact_across_borders():
    """Property test, 3000 seeded random cases (``BORDER_CASES``): branch-and-bound finds the
    exhaustive search's best score on small float32 and uint8 grids, depths 1-5, with and
    without the delta penalty, a random unknown value (often above some cells), and search
    windows that cross the low and the high borders or lie partly or wholly outside."""
    rng = np.random.default_rng(12)
    bad = []
    crossed_low = 0
    for case in range(BORDER_CASES):
        grid, depth, cells, w, angles, pen = _border_case(rng)
        stack = PrecomputationStack(grid, depth)
        crossed_low += int(cells.min() - w < 0)
        min_score = 0.0
        if rng.random() < 0.3:  # a threshold below the best: the cut must not lose it
            min_score = float(rng.uniform(0, 0.99)) * float(exhaustive(grid, cells, w, pen, angles).max())
        why = bnb_disagreement(grid, stack, cells, w, min_score, pen, angles)
        if why:
            bad.append((case, why))
    assert crossed_low > BORDER_CASES // 2
    assert not bad, f"{len(bad)} of {BORDER_CASES} cases disagree, e.g. {bad[:3]}"


@pytest.mark.parametrize("res,window,ang_deg", [(0.05, 2.0, 45.0), (0.03, 2.0, 45.0), (0.07, 0.5, 7.3)])
def test_smallest_delta_penalty_is_the_lattice_corner(res, window, ang_deg):
    """``DeltaPenalty.smallest_factor`` equals the smallest factor the kernel applies anywhere on the
    lattice, also where rounding to whole cells and angular steps makes the lattice wider than asked."""
    pts = np.random.default_rng(3).normal(0, 8.0, (200, 2))
    params = SearchParameters.make(window, math.radians(ang_deg), res, pts)
    pen = DeltaPenalty(0.1, 0.1)
    k = 2 * params.linear_cells + 1
    ones = np.ones((len(params.angles), k, k), np.float32)
    _kernels.apply_delta_penalty(ones, np.ascontiguousarray(params.angles), 0.1, 0.1, res)
    assert pen.smallest_factor(params) == pytest.approx(float(ones.min()), rel=1e-6)
    assert pen.smallest_factor(params) <= float(ones.min()) * (1 + 1e-6)


def test_quantize_up_oracle():
    """uint8 of ceil(v × 255), clipped: never below the float value, less than 1/255 above it."""
    from slam2d.matching.search import quantized_up

    rng = np.random.default_rng(9)
    v = rng.random((37, 23)).astype(np.float32)
    v[0, :4] = [0.0, 1.0, 1.0 / 255.0, -0.25]
    v[1, :2] = [1.5, np.nextafter(np.float32(2.0 / 255.0), np.float32(1.0))]
    want = np.clip(np.ceil(v.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    got = _kernels.quantize_up(v)
    np.testing.assert_array_equal(got, want)
    inside = (v >= 0) & (v <= 1)
    assert np.all(got[inside] / 255.0 >= v[inside]) and np.all(got[inside] / 255.0 - v[inside] < 1 / 255.0)
    g = quantized_up(MatchGrid(v, np.zeros(2), 0.05, 0.3))
    assert g.values.dtype == np.uint8 and g.unknown == 77.0  # ceil(0.3 × 255) = ceil(76.5)


def test_quantized_branch_and_bound_bounds_the_float_score_from_above():
    """The real-time matcher over a uint8 stack picks the pose the quantized grid scores best and returns
    the float grid's score there: within 1/255 of the float grid's best; and a min_score the float
    best exceeds never prunes it away."""
    from slam2d.matching.real_time import RealTimeCorrelativeScanMatcher

    rng = np.random.default_rng(5)
    values = (rng.random((60, 60)) ** 3).astype(np.float32)
    grid = MatchGrid(values, np.zeros(2), 0.05, 0.0)
    pts = rng.uniform(0.6, 2.4, (40, 2))
    pred = np.array([0.1, -0.05, 0.02])
    exact = RealTimeCorrelativeScanMatcher(0.3, 0.1, 0, 0.1, 0.1).match(grid, pred, pts)
    quant = RealTimeCorrelativeScanMatcher(0.3, 0.1, 4, 0.1, 0.1, quantize=True)
    q = quant._match(grid, pred, pts, 0.0, 0.3, 0.1)
    assert exact.score - 1 / 255.0 < q.score <= exact.score + 1e-6
    assert quant._match(grid, pred, pts, exact.score - 1e-4, 0.3, 0.1) is not None


def _separated_margin_oracle(scores, lin, ang):
    """The separated margin with scipy: local maxima (≥ their 3 × 3 × 3 neighbourhood, edges
    replicated), positive, outside the box around the best."""
    from scipy.ndimage import maximum_filter

    a, iy, ix = np.unravel_index(int(np.argmax(scores)), scores.shape)
    best = float(scores[a, iy, ix])
    peaks = (scores >= maximum_filter(scores, size=3, mode="nearest")) & (scores > 0)
    peaks[max(a - ang, 0):a + ang + 1, max(iy - lin, 0):iy + lin + 1, max(ix - lin, 0):ix + lin + 1] = False
    return best if not peaks.any() else best - float(scores[peaks].max())


@pytest.mark.parametrize("seed", range(8))
def test_separated_margin_matches_oracle(seed):
    """Random cubes (float32 and float64), plateaus of equal values (ties count as peaks), zero and
    negative regions (never peaks), and cubes whose only peak is the best one."""
    from slam2d.backend.loop_closure import separated_margin

    rng = np.random.default_rng(seed)
    for trial in range(40):
        shape = tuple(int(v) for v in rng.integers(1, 12, 3))
        dtype = np.float32 if trial % 2 else np.float64
        s = rng.random(shape).astype(dtype)
        if trial % 5 == 1:
            s = np.round(s * 4).astype(dtype) / 4  # plateaus
        if trial % 5 == 2:
            s[s < 0.5] = 0.0
        if trial % 5 == 3:
            s -= 0.6
        if trial % 5 == 4:
            s = np.zeros(shape, dtype)
            s[tuple(int(rng.integers(0, n)) for n in shape)] = 1.0  # a single peak
        lin, ang = int(rng.integers(0, 4)), int(rng.integers(0, 4))
        assert separated_margin(s, lin, ang) == _separated_margin_oracle(s, lin, ang), (seed, trial)


def laplace_cover_oracle(scores, offs, angles, n_points, prior, cov):
    """The curvature cover in plain numpy: a least-squares quadratic through the 3 × 3 × 3
    neighbourhood of the best lattice pose (``np.linalg.lstsq`` on the absolute offsets), its
    information floored at the prior's, then the smallest covariance covering both."""
    a, iy, ix = np.unravel_index(int(np.argmax(scores)), scores.shape)
    idx = [int(np.clip(v, 1, n - 2)) for v, n in zip((a, iy, ix), scores.shape)]
    g = np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")
    ka, ky, kx = (i + d.ravel() for i, d in zip(idx, g))
    x, y, t = offs[kx], offs[ky], angles[ka]
    rows = np.stack([np.ones(27), x, y, t, 0.5 * x * x, 0.5 * y * y, 0.5 * t * t, x * y, x * t, y * t], axis=1)
    c = np.linalg.lstsq(rows, n_points * scores[ka, ky, kx].astype(np.float64), rcond=None)[0]
    info = -np.array([[c[4], c[7], c[8]], [c[7], c[5], c[9]], [c[8], c[9], c[6]]])
    sp = np.sqrt(np.diag(prior))
    lam, vec = np.linalg.eigh(info * np.outer(sp, sp))
    lap = (vec / np.maximum(lam, 1.0)) @ vec.T * np.outer(sp, sp)
    la, va = np.linalg.eigh(0.5 * (cov + cov.T))
    half = va * np.sqrt(np.maximum(la, 1e-300))
    inv_half = np.linalg.inv(half)
    mu, wv = np.linalg.eigh(inv_half @ lap @ inv_half.T)
    out = half @ (wv * np.maximum(mu, 1.0)) @ wv.T @ half.T
    return 0.5 * (out + out.T)


@pytest.mark.parametrize("seed", range(40))
def test_laplace_cover_matches_oracle(seed):
    """Peaks inside and on every face of the volume (the neighbourhood moved inside), sharp and
    flat ones (information above and below the prior's), windows of 3 cells and more."""
    rng = np.random.default_rng(100 + seed)
    na, w = int(rng.integers(3, 12)), int(rng.integers(1, 6))
    res, step = float(rng.choice([0.02, 0.05, 0.1])), float(rng.uniform(0.002, 0.03))
    offs = np.arange(-w, w + 1) * res
    angles = step * np.arange(-(na // 2), na - na // 2, dtype=np.float64)
    peak = np.array([rng.uniform(-1, na), rng.uniform(-1, 2 * w + 1), rng.uniform(-1, 2 * w + 1)])
    curv = rng.uniform(0.001, 0.2, 3) if seed % 3 else np.array([0.2, 1e-5, 0.05])  # seed % 3 == 0: a flat axis
    ga, gy, gx = np.meshgrid(np.arange(na), np.arange(2 * w + 1), np.arange(2 * w + 1), indexing="ij")
    scores = (0.9 - curv[0] * (ga - peak[0]) ** 2 - curv[1] * (gy - peak[1]) ** 2 - curv[2] * (gx - peak[2]) ** 2
              + 0.3 * curv[1] * (gx - peak[2]) * (gy - peak[1]) + rng.normal(0, 0.002, ga.shape)).astype(np.float32)
    n_points = float(rng.integers(20, 400))
    prior = np.diag([0.3 ** 2, 0.3 ** 2, math.radians(20) ** 2])
    cov = np.empty((3, 3))
    _kernels.score_covariance(scores, offs, angles, n_points, cov)
    cov[np.diag_indices(3)] += [res * res / 12, res * res / 12, step * step / 12]
    want = laplace_cover_oracle(scores, offs, angles, n_points, prior, cov)
    got = cov.copy()
    _kernels.laplace_cover(scores, n_points, res, step, np.sqrt(np.diag(prior)), got)
    np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-14 * np.abs(want).max())
    assert np.all(np.linalg.eigvalsh(got) >= np.linalg.eigvalsh(cov).min() * (1 - 1e-9))


def test_laplace_cover_leaves_thin_volumes_alone():
    cov = np.diag([1e-4, 1e-4, 1e-5])
    got = cov.copy()
    _kernels.laplace_cover(np.ones((2, 5, 5), np.float32), 50.0, 0.05, 0.01, np.array([0.3, 0.3, 0.3]), got)
    np.testing.assert_array_equal(got, cov)


def test_cropped_stack_searches_as_the_whole_grid():
    """``stack_for(grid, around=poses, reach=r)`` pools only ``search_region``: 400 seeded random
    cases (float and uint8 stacks, depths 1-5, with the delta penalty, a score floor, one to three
    start poses inside the grid, across its borders or off it) give the same pose and score, bit
    for bit, as the stack of the whole grid, from every start pose."""
    from slam2d.matching.real_time import RealTimeCorrelativeScanMatcher
    from slam2d.matching.search import search_region

    rng = np.random.default_rng(21)
    cropped = off_grid = found = 0
    for case in range(400):
        rows, cols = (int(v) for v in rng.integers(8, 200, 2))
        res = float(rng.choice([0.05, 0.1]))
        values = (rng.random((rows, cols)) ** 2).astype(np.float32)
        grid = MatchGrid(values, rng.uniform(-3, 3, 2), res, float(rng.choice([0.0, 0.1, 0.5])))
        m = RealTimeCorrelativeScanMatcher(float(rng.uniform(0.1, 1.0)), float(rng.uniform(0.05, 0.6)),
                                           int(rng.integers(1, 6)), 0.1, 0.1, quantize=bool(rng.random() < 0.5))
        pts = rng.normal(0, rng.uniform(0.1, 1.2), (int(rng.integers(3, 40)), 2))
        reach = float(np.sqrt((pts ** 2).sum(axis=1)).max())
        lo, hi = grid.origin - 6.0, grid.origin + res * np.array([cols, rows]) + 6.0
        starts = [np.r_[rng.uniform(lo, hi), rng.uniform(-math.pi, math.pi)] for _ in range(int(rng.integers(1, 4)))]
        region = search_region(values.shape, grid.origin, res, starts, reach,
                               int(math.ceil(m.linear_window / res)), m.branch_depth)
        cropped += region is not None
        off_grid += region is not None and (region[1] - region[0]) * (region[3] - region[2]) == 1
        whole, part = m.stack_for(grid), m.stack_for(grid, around=starts, reach=reach)
        floor = float(rng.choice([0.0, 0.2]))
        for s in starts:
            a = m._match(grid, s, pts, floor, m.linear_window, m.angular_window, stack=whole)
            b = m._match(grid, s, pts, floor, m.linear_window, m.angular_window, stack=part)
            assert (a is None) == (b is None), (case, a, b)
            if a is not None:
                found += 1
                assert a.score == b.score and np.array_equal(a.pose, b.pose) and a.on_edge == b.on_edge, (case, a, b)
    assert cropped > 200 and off_grid > 10 and found > 200, (cropped, off_grid, found)


def test_shared_branch_and_bound_equals_the_sequential_one():
    """``branch_and_bound_shared`` (coarsest candidates dealt to ``BNB_SHARES`` shares, searched on
    numba's threads) returns the sequential kernel's (angle, dx, dy, score) exactly: 600 seeded random
    cases, half on uint8 grids of four values (many exactly tied poses, where the search order
    decides), with and without the delta penalty and a score floor, cells across the borders."""
    rng = np.random.default_rng(3)
    ties = 0
    for case in range(600):
        rows, cols = (int(v) for v in rng.integers(10, 90, 2))
        if rng.random() < 0.5:
            v = rng.choice(np.array([0, 64, 128, 255], np.uint8), size=(rows, cols))
            unknown = 128.0
        else:
            v = (rng.random((rows, cols)) ** 2).astype(np.float32)
            unknown = float(rng.choice([0.0, 0.3]))
        st = PrecomputationStack(MatchGrid(v, np.zeros(2), 0.05, unknown), int(rng.integers(1, 6)))
        a_n, n = int(rng.integers(1, 9)), int(rng.integers(3, 30))
        cells = rng.integers(-10, max(rows, cols) + 10, (a_n, n, 2)).astype(np.int32)
        w_t, w_r = (0.1, 0.1) if rng.random() < 0.5 else (0.0, 0.0)
        floor = float(rng.choice([0.0, 0.3 * (255 if v.dtype == np.uint8 else 1)]))
        args = (st.data, st.starts, rows, cols, cells, np.linspace(-0.2, 0.2, a_n), int(rng.integers(1, 20)),
                floor, unknown, w_t, w_r, 0.05)
        seq = _kernels.branch_and_bound(*args)
        assert tuple(_kernels.branch_and_bound_shared(*args)) == tuple(seq), case
        if v.dtype == np.uint8 and seq[0] >= 0:
            ex = exhaustive(MatchGrid(v, np.zeros(2), 0.05, unknown), cells, args[6],
                            DeltaPenalty(w_t, w_r) if w_t else None, args[5])
            ties += int(np.count_nonzero(np.abs(ex - ex.max()) < 1e-6) > 1)
    assert ties > 50  # the order among tied poses was put to the test


@pytest.mark.parametrize("seed", range(6))
def test_scaled_uint8_grid_scores_and_refines_as_its_dequantized_copy(seed):
    """``MatchGrid.scale``: a uint8 grid read with scale 1/255 gives exhaustive scores and refined
    poses bit for bit equal to those of its ``dequantize``d float32 copy (windows across the
    borders included), and scale 1 leaves raw uint8 scores as they were."""
    from slam2d.grid.probability_grid import dequantize
    from slam2d.matching.refine import refine

    rng = np.random.default_rng(300 + seed)
    q = rng.integers(0, 256, size=(60, 70)).astype(np.uint8)
    q[20:24, 5:60] = 250  # a wall for the refinement to lock on
    origin, res, unknown = np.array([-1.0, -0.5]), 0.05, 0.12
    scaled = MatchGrid(q, origin, res, unknown, 1.0 / 255.0)
    dense = MatchGrid(dequantize(q), origin, res, unknown)
    pts = rng.uniform([-1.5, -0.8], [3.5, 3.2], size=(120, 2))
    angles = np.linspace(-0.05, 0.05, 5)
    for pose in ([0.3, 0.2, 0.01], [-0.9, -0.4, -0.2], [2.8, 2.6, 0.5]):
        cells = dense.cells(pts, np.array(pose), angles)
        np.testing.assert_array_equal(exhaustive(scaled, cells, 6), exhaustive(dense, cells, 6))
        raw = exhaustive(MatchGrid(q, origin, res, 30.0), cells, 2)
        np.testing.assert_allclose(raw, score_oracle(q.astype(np.float64), cells, 2, 30.0), rtol=1e-5)
        a = refine(scaled, np.array(pose), pts, 1.0, 1.0, 1.0, 20)
        b = refine(dense, np.array(pose), pts, 1.0, 1.0, 1.0, 20)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1] == b[1]


def test_precomputation_stack_written_into_a_given_buffer():
    """A stack built into a spare buffer (an evicted stack's) holds the same levels as a fresh one and
    uses that memory; a buffer too small, or more than twice the size needed, is not used."""
    rng = np.random.default_rng(8)
    values = (rng.random((19, 23)) * 255).astype(np.uint8)
    grid = MatchGrid(values, np.zeros(2), 0.05, 40.0)
    fresh = PrecomputationStack(grid, 4)
    need = fresh.buffer.nbytes
    spare = np.full(need + 100, 7, dtype=np.uint8)  # stale content: every level must be written
    reused = PrecomputationStack(grid, 4, buffer=spare)
    assert reused.buffer is spare and np.shares_memory(reused.data, spare)
    for d in range(5):
        np.testing.assert_array_equal(reused.level(d), fresh.level(d))
    assert reused.nbytes == spare.nbytes  # the whole buffer counts against a cache's budget
    for size in (need - 1, 2 * need + 1):
        other = np.zeros(size, dtype=np.uint8)
        assert not np.shares_memory(PrecomputationStack(grid, 4, buffer=other).data, other)
    floats = MatchGrid(rng.random((19, 23)).astype(np.float32), np.zeros(2), 0.05, 0.1)
    f_fresh = PrecomputationStack(floats, 3)
    f_reused = PrecomputationStack(floats, 3, buffer=np.zeros(f_fresh.buffer.nbytes, dtype=np.uint8))
    for d in range(4):
        np.testing.assert_array_equal(f_reused.level(d), f_fresh.level(d))
