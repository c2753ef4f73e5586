"""Grid kernels against plain-numpy oracles."""
import math

import numpy as np
import pytest

from slam2d.grid import _kernels
from slam2d.grid.probability_grid import ProbabilityGrid, field_kernel, logit


def cells_crossed_oracle(o, e, samples=20000):
    """Cells a segment passes through, by dense sampling (plain numpy)."""
    t = np.linspace(0.0, 1.0, samples)
    pts = o[None, :] + t[:, None] * (e - o)[None, :]
    cells = np.floor(pts).astype(int)
    keep = np.ones(len(cells), bool)
    keep[1:] = np.any(cells[1:] != cells[:-1], axis=1)
    return [tuple(c) for c in cells[keep]]


def insert_oracle(shape, o, ends, is_hit, hit, miss, lo_min, lo_max, logodds=None):
    lo = np.zeros(shape) if logodds is None else logodds.astype(float).copy()
    updated = set()
    for e, h in zip(ends, is_hit):
        if h:
            c, r = (int(math.floor(v)) for v in e)
            if 0 <= r < shape[0] and 0 <= c < shape[1] and (r, c) not in updated:
                updated.add((r, c))
                lo[r, c] = np.clip(lo[r, c] + hit, lo_min, lo_max)
    for e, h in zip(ends, is_hit):
        cells = cells_crossed_oracle(np.asarray(o, float), np.asarray(e, float))
        end = (int(math.floor(e[0])), int(math.floor(e[1])))
        for c, r in cells:
            if (c, r) == end and h:
                break
            if 0 <= r < shape[0] and 0 <= c < shape[1] and (r, c) not in updated:
                updated.add((r, c))
                lo[r, c] = np.clip(lo[r, c] + miss, lo_min, lo_max)
    return lo, updated


@pytest.mark.parametrize("seed", range(5))
def test_insert_rays_matches_oracle(seed):
    rng = np.random.default_rng(seed)
    shape = (60, 70)
    o = rng.uniform([20, 20], [50, 40])
    ends = rng.uniform([-5, -5], [75, 65], size=(40, 2))
    is_hit = rng.random(40) < 0.7
    hit, miss, lo_min, lo_max = logit(0.55), logit(0.49), logit(0.12), logit(0.97)
    base = rng.normal(0, 0.3, size=shape).astype(np.float32)
    lo = base.copy()
    prob = 1 / (1 + np.exp(-base))
    stamp = np.zeros(shape, np.int32)
    flips = np.zeros((1000, 2), np.int32)
    nflips = np.zeros(1, np.int64)
    _kernels.insert_rays(lo, prob, stamp, 1, o[0], o[1], ends, is_hit, hit, miss, lo_min, lo_max, flips, nflips, 0, -1, 0)
    known = (stamp > 0).astype(np.uint8)
    want, updated = insert_oracle(shape, o, ends, is_hit, hit, miss, lo_min, lo_max, base)
    # dense sampling can miss a cell whose corner a ray only grazes; allow a handful of such cells
    diff = np.argwhere(np.abs(lo - want) > 1e-5)
    assert len(diff) <= 3, diff
    assert known.sum() >= len(updated) - 3
    np.testing.assert_allclose(prob, 1 / (1 + np.exp(-lo)), rtol=1e-5)
    flipped = {tuple(f) for f in flips[: nflips[0]]}
    assert flipped == {tuple(x) for x in np.argwhere((base > 0) != (lo > 0))}


def test_one_hit_per_cell_per_scan():
    g = ProbabilityGrid(0.05)
    pts = np.array([[1.001, 0.001], [1.01, 0.01], [1.02, 0.02]])  # all in one cell
    g.insert((0.0, 0.0), pts)
    r, c = np.floor((pts[0] - g.origin) / 0.05).astype(int)[::-1]
    assert g.logodds[r, c] == pytest.approx(logit(0.55))


def test_a_cell_at_its_clamp_is_not_written_again():
    """Most misses land on cells already at the lower clamp, and most repeated hits on cells at the
    upper one: those are skipped (the float64 clamp is compared with the float32 cell as stored),
    while every other crossed cell is updated as before."""
    g = ProbabilityGrid(0.05)
    g.insert((0.0, 0.0), np.array([[3.0, 0.025]]))
    for _ in range(200):  # the ray's cells reach the lower clamp, its end cell the upper one
        g.insert((0.0, 0.0), np.array([[3.0, 0.025]]))
    r, c0 = np.floor((np.array([0.0, 0.025]) - g.origin) / 0.05).astype(int)[::-1]
    free = (r, c0 + 20)  # a cell 1 m along the ray
    end = tuple(np.floor((np.array([3.0, 0.025]) - g.origin) / 0.05).astype(int)[::-1])
    assert g.logodds[free] == np.float32(g.lo_min) and g.logodds[end] == np.float32(g.lo_max)
    g.prob[free] = g.prob[end] = 0.5  # marks: a cell written again would get its probability back
    g.insert((0.0, 0.0), np.array([[3.0, 0.025], [0.0, 3.0]]))
    assert g.prob[free] == 0.5 and g.prob[end] == 0.5
    assert g.logodds[free] == np.float32(g.lo_min) and g.logodds[end] == np.float32(g.lo_max)
    # a fresh ray's cells are updated as always
    r2, c2 = np.floor((np.array([0.0, 1.0]) - g.origin) / 0.05).astype(int)[::-1]
    assert g.logodds[r2, c2] == pytest.approx(logit(0.49), abs=1e-6)
    assert g.prob[r2, c2] == pytest.approx(0.49, abs=1e-6)


def test_no_return_rays_free_only():
    g = ProbabilityGrid(0.05)
    g.insert((0.0, 0.0), np.zeros((0, 2)), np.array([[2.0, 0.0]]))
    assert (g.logodds <= 0).all() and g.known.sum() >= 40


def test_grid_grows_and_keeps_content():
    g = ProbabilityGrid(0.05)
    g.insert((0.0, 0.0), np.array([[1.0, 0.0]]))
    before = g.probability(0.5)
    occ_world = g.origin + (np.argwhere(before > 0.5)[0][::-1] + 0.5) * 0.05
    g.insert((0.0, 0.0), np.array([[-30.0, 25.0]]))
    after = g.probability(0.5)
    rc = np.floor((occ_world - g.origin) / 0.05).astype(int)[::-1]
    assert after[rc[0], rc[1]] == pytest.approx(before.max())
    assert g.known.sum() > 500


def test_grid_grows_geometrically_along_a_long_path():
    """A laser carried 200 m down a corridor: the grid reallocates a few dozen times, not once every
    few metres, and ends up with the same content as a grid sized for the whole path up front."""
    rng = np.random.default_rng(2)
    res = 1 / 16  # cells and points on binary fractions: both grids compute every cell exactly
    g, big = ProbabilityGrid(res), ProbabilityGrid(res)
    big.ensure_contains(-35.0, -35.0, 235.0, 35.0)
    shapes = set()
    for x in np.arange(0.0, 200.0, 0.5):
        hits = np.c_[x + rng.integers(-30 * 64, 30 * 64, 50) / 64, rng.choice([-2.0, 2.0], 50)]
        g.insert((x, 0.0), hits)
        big.insert((x, 0.0), hits)
        shapes.add(g.shape)
    assert len(shapes) < 30, len(shapes)
    # the same cells, wherever each grid's origin lies
    r0, r1, c0, c1 = g.known_bounds()  # g also holds a margin beyond what it observed
    off = np.round((g.origin - big.origin) / res).astype(int)
    np.testing.assert_array_equal(g.probability(0.5)[r0:r1, c0:c1],
                                  big.probability(0.5)[off[1] + r0:off[1] + r1, off[0] + c0:off[0] + c1])
    assert np.count_nonzero(big.known) == np.count_nonzero(g.known)


@pytest.mark.parametrize("seed", range(3))
def test_incremental_likelihood_field_equals_distance_transform(seed):
    rng = np.random.default_rng(seed)
    g = ProbabilityGrid(0.05, field_sigma=0.1)
    for _ in range(30):
        origin = rng.uniform(-1, 1, 2)
        hits = origin + rng.uniform(-4, 4, size=(60, 2))
        misses = origin + rng.uniform(-4, 4, size=(30, 2))
        g.insert(origin, hits, misses)
    np.testing.assert_allclose(g.field, g.compute_field(), atol=1e-6)


def test_field_kernel_oracle():
    k = field_kernel(0.1, 0.05, 6)
    for (i, j), v in np.ndenumerate(k):
        d = math.hypot(i - 6, j - 6) * 0.05
        assert v == pytest.approx(math.exp(-d * d / 0.02) if d <= 0.3 + 1e-9 else 0.0, abs=1e-7)


@pytest.mark.parametrize("sigma", [None, 0.1])
def test_two_grids_in_parallel_equal_one_at_a_time(sigma):
    """The active submaps are updated by one parallel kernel; the result must equal separate inserts."""
    from slam2d.grid.probability_grid import insert_scan

    rng = np.random.default_rng(3)
    angles = np.linspace(-np.pi / 2, np.pi / 2, 180)
    pair = [ProbabilityGrid(0.05, field_sigma=sigma) for _ in range(2)]
    single = [ProbabilityGrid(0.05, field_sigma=sigma) for _ in range(2)]
    for i in range(12):
        r = rng.uniform(0.5, 6.0, 180)
        d = rng.normal(0, 0.3, 2)
        hits = np.c_[r * np.cos(angles), r * np.sin(angles)] + d
        misses = hits[::20] * 1.5
        grids = pair if i < 4 else pair[1:]  # the first grid stops taking scans, like a finished submap
        insert_scan(grids + ([ProbabilityGrid(0.05, field_sigma=sigma)] if i >= 8 else []), d, hits, misses)
        for g in (single if i < 4 else single[1:]):
            g.insert(d, hits, misses)
    for a, b in zip(pair, single):
        assert a.shape == b.shape and np.array_equal(a.origin, b.origin)
        np.testing.assert_array_equal(a.logodds, b.logodds)
        np.testing.assert_array_equal(a.prob, b.prob)
        np.testing.assert_array_equal(a.stamp > 0, b.stamp > 0)
        if sigma:
            np.testing.assert_array_equal(a.field, b.field)
            np.testing.assert_allclose(a.field, a.compute_field(), atol=1e-6)
            assert a.field.max() == 1.0


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_many_scans_striped_equal_one_at_a_time(threads):
    """The map is built by one kernel whose threads own bands of rows; it must equal scan-by-scan insertion."""
    rng = np.random.default_rng(5)
    angles = np.linspace(-np.pi / 2, np.pi / 2, 90)
    scans = []
    for i in range(25):
        r = rng.uniform(0.3, 5.0, 90)
        o = rng.normal(0, 1.0, 2)
        hits = np.c_[r * np.cos(angles + i), r * np.sin(angles + i)] + o
        misses = (hits[::15] - o) * 2.0 + o if i % 3 else np.zeros((0, 2))
        scans.append((o, hits, misses))
    scans.append((np.zeros(2), np.zeros((0, 2)), np.zeros((0, 2))))  # an empty scan changes nothing
    many = ProbabilityGrid(0.05)
    many.insert_scans(scans, threads=threads)
    one = ProbabilityGrid(0.05)
    for o, h, m in scans:
        one.insert(o, h, m)
    # the grids grew differently (at once / step by step): compare the observed parts in place
    crops = []
    for g in (many, one):
        r0, r1, c0, c1 = g.known_bounds()
        crops.append((g.origin + np.array([c0, r0]) * g.resolution, g.logodds[r0:r1, c0:c1], g.prob[r0:r1, c0:c1],
                      g.known[r0:r1, c0:c1]))
    (oa, la, pa, ka), (ob, lb, pb, kb) = crops
    np.testing.assert_allclose(oa, ob, atol=1e-9)
    np.testing.assert_array_equal(la, lb)
    np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(ka, kb)
    assert (la > 0).sum() > 500


@pytest.mark.parametrize("band_cells,threads", [(1, 1), (700, 2), (5000, 2), (1 << 22, 1)])
def test_map_built_in_bands_equals_scan_by_scan(band_cells, threads):
    """``build_finished`` holds log-odds for one band of rows at a time and skips rays that miss a
    band: bands of one row up to the whole grid must give the probabilities and known mask of
    scan-by-scan insertion, with rays crossing band borders in both directions."""
    rng = np.random.default_rng(11)
    angles = np.linspace(-np.pi, np.pi, 120, endpoint=False)
    scans = []
    for i in range(30):
        r = rng.uniform(0.3, 6.0, 120)
        o = rng.normal(0, 2.0, 2)
        hits = np.c_[r * np.cos(angles + 0.1 * i), r * np.sin(angles + 0.1 * i)] + o
        misses = (hits[::10] - o) * 1.7 + o if i % 2 else np.zeros((0, 2))
        scans.append((o, hits, misses))
    scans.append((np.zeros(2), np.zeros((0, 2)), np.zeros((0, 2))))  # an empty scan changes nothing
    built = ProbabilityGrid(0.05)
    built.build_finished(scans, threads=threads, band_cells=band_cells)
    one = ProbabilityGrid(0.05)
    for o, h, m in scans:
        one.insert(o, h, m)
    assert built.logodds.size == 0 and built.stamp.size == 0 and built.prob.dtype == np.float32
    rows = built.shape[0]
    cols = built.shape[1]
    assert band_cells >= rows * cols or max(1, band_cells // cols) < rows  # several bands, or one
    crops = []
    for g in (built, one):
        r0, r1, c0, c1 = g.known_bounds()
        crops.append((g.origin + np.array([c0, r0]) * g.resolution, g.prob[r0:r1, c0:c1], g.known[r0:r1, c0:c1]))
    (oa, pa, ka), (ob, pb, kb) = crops
    np.testing.assert_allclose(oa, ob, atol=1e-9)
    np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(ka, kb)
    # unknown cells read the unknown probability, as matching expects; probability() says NaN there
    assert (built.prob[built.known == 0] == np.float32(built.unknown_probability)).all()
    p = built.probability(unknown_value=np.nan)
    assert np.array_equal(np.isnan(p), built.known == 0)
    assert (pa > 0.5).sum() > 500 and (pa < 0.3).sum() > 500


def test_frozen_grid_keeps_its_probabilities_without_log_odds():
    g = ProbabilityGrid(0.05)
    rng = np.random.default_rng(5)
    for _ in range(20):
        g.insert(np.zeros(2), rng.uniform(-3, 3, (50, 2)), rng.uniform(-4, 4, (20, 2)))
    before = g.probability(unknown_value=np.nan)
    r0, r1, c0, c1 = g.known_bounds()
    g.freeze(r0, r1, c0, c1)
    assert g.logodds.size == 0 and g.shape == (r1 - r0, c1 - c0)
    # kept as uint8 (p × 255) beside the known mask: two bytes a cell, within half a step of the float
    assert g.prob.dtype == np.uint8 and g.prob.nbytes + g.known.nbytes == 2 * g.prob.size
    after = g.probability(unknown_value=np.nan)
    assert np.array_equal(np.isnan(after), np.isnan(before[r0:r1, c0:c1]))  # unknown stays unknown
    np.testing.assert_allclose(after, before[r0:r1, c0:c1], rtol=0, atol=0.5 / 255 + 1e-6)


def test_map_export_in_bands_equals_one_pass(monkeypatch):
    import slam2d.grid.map_export as me

    g = ProbabilityGrid(0.05)
    rng = np.random.default_rng(9)
    hits, misses = rng.uniform(-4, 4, (60, 2)), rng.uniform(-5, 5, (20, 2))
    for _ in range(50):  # the same scan again and again: free cells need many misses at 0.49
        g.insert(rng.uniform(-0.1, 0.1, 2), hits, misses)
    np.testing.assert_array_equal(np.concatenate([g.probability_rows(a, min(a + 7, g.shape[0]), np.nan)
                                                  for a in range(0, g.shape[0], 7)]), g.probability(np.nan))
    whole = me.occupancy_image(g, 0.65, 0.196)
    monkeypatch.setattr(me, "BAND_ROWS", 5)
    banded = me.occupancy_image(g, 0.65, 0.196)
    np.testing.assert_array_equal(banded[0], whole[0])
    assert banded[1:] == whole[1:]
    assert (whole[0] == me.FREE).any() and (whole[0] == me.OCCUPIED).any()


def test_frozen_grid_keeps_known_mask_and_observed_cells_exactly():
    """A finished submap keeps its known mask as bits: the mask, ``observed_at`` (cells inside,
    outside and on every bit position of a byte) and the probabilities read back as before freezing."""
    rng = np.random.default_rng(11)
    g = ProbabilityGrid(0.05)
    for _ in range(30):
        o = rng.uniform(-1, 1, 2)
        g.insert(o, o + rng.uniform(-3, 3, (40, 2)))
    r0, r1, c0, c1 = g.known_bounds()
    if (c1 - c0) % 8 == 0:  # a width that leaves the last byte of each row part padding
        c1 -= 1
    known = g.known[r0:r1, c0:c1].copy()
    prob = g.probability(unknown_value=0.5)[r0:r1, c0:c1].copy()
    cells = np.c_[rng.integers(-5, c1 - c0 + 5, 3000), rng.integers(-5, r1 - r0 + 5, 3000)]
    want = np.zeros(len(cells), bool)
    inside = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < c1 - c0) & (cells[:, 1] < r1 - r0)
    want[inside] = known[cells[inside, 1], cells[inside, 0]] > 0
    g.freeze(r0, r1, c0, c1)
    np.testing.assert_array_equal(g.known, known)
    np.testing.assert_array_equal(g.observed_at(cells), want)
    assert want.any() and (~want).any()
    np.testing.assert_allclose(g.probability(unknown_value=0.5), prob, atol=0.5 / 255)
    assert g._known_bits.nbytes <= known.size // 8 + known.shape[0]  # a bit a cell (plus a row's last byte)


@pytest.mark.parametrize("fill", [0, 0.5])
@pytest.mark.parametrize("r0,c0,extra_r,extra_c", [(0, 0, 3, 2), (4, 0, 0, 5), (0, 6, 2, 0), (3, 2, 5, 4), (2, 3, 0, 0)])
def test_grown_array_matches_a_filled_copy(fill, r0, c0, extra_r, extra_c):
    """``_grown`` (the grid's growth: every element written once) against np.full and a slice copy,
    the old array placed on every side of the new one."""
    from slam2d.grid.probability_grid import _grown

    old = np.arange(1, 13, dtype=np.float32).reshape(3, 4)
    shape = (3 + r0 + extra_r, 4 + c0 + extra_c)
    want = np.full(shape, fill, dtype=np.float32)
    want[r0:r0 + 3, c0:c0 + 4] = old
    got = _grown(old, shape, r0, c0, fill)
    assert got.dtype == old.dtype
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("scans", [1, 2, 3])
def test_refinement_is_not_pulled_toward_where_a_wall_was_seen_from(scans):
    """A corridor with an end wall ahead, mapped by a few scans from behind, and a scan from 1-2 m
    closer refined from its true pose. Read at the minimum probability (the default), the
    never-observed cells behind the end wall pull the refined pose back toward where the wall was
    seen from (the robot seems to have advanced less, the map shrinks); where never-observed
    cells just behind a surface mirror its free side (``refine.unobserved: mirrored``), the pull is
    smaller (the cells two behind the wall still read at the minimum, so one scan keeps most of it)."""
    from slam2d.config import SlamConfig
    from slam2d.grid.submap import Submap
    from slam2d.matching.refine import refine

    cfg = SlamConfig()
    rng = np.random.default_rng(0)

    def scan_from(x, noise):
        a = np.linspace(-np.pi / 2, np.pi / 2, 181)
        dx, dy = np.cos(a), np.sin(a)
        with np.errstate(divide="ignore"):
            t = np.minimum(np.where(dx > 1e-9, (6.0 - x) / dx, np.inf), np.where(np.abs(dy) > 1e-9, 1.5 / np.abs(dy), np.inf))
        return np.c_[x + t * dx, t * dy] + rng.normal(0, noise, (181, 2))

    g = ProbabilityGrid.from_config(cfg.grid)
    sub = Submap(0, np.zeros(3), g)
    for x in np.linspace(0.0, 1.0, scans):
        g.insert((x, 0.0), scan_from(x, 0.01))
        sub.num_range_data += 1
    truth = np.array([2.0, 0.0, 0.0])
    pts = scan_from(2.0, 0.0) - truth[:2]
    r = cfg.refine
    pull = {}
    for mode in ("min_probability", "mirrored"):
        p, _ = refine(sub.refinement_grid(mode), truth, pts, r.occupied_space_weight, r.translation_weight,
                      r.rotation_weight, r.max_iterations)
        pull[mode] = p[0] - truth[0]
    assert pull["min_probability"] < -0.25 * g.resolution  # back toward where the wall was seen from
    assert abs(pull["mirrored"]) < 0.75 * abs(pull["min_probability"])


@pytest.mark.parametrize("seed", range(4))
def test_stamped_bounds_and_frozen_cells_oracle(seed):
    """``stamped_bounds`` equals the bounds of ``np.argwhere(stamp > 0)``; ``frozen_cells`` equals
    ``quantize`` of the crop (half steps included, rounded to even) and ``np.packbits`` of its known
    mask, for widths that are and are not whole bytes and crops that touch every border."""
    from slam2d.grid.probability_grid import quantize

    rng = np.random.default_rng(seed)
    rows, cols = int(rng.integers(1, 40)), int(rng.integers(1, 40))
    stamp = np.where(rng.random((rows, cols)) < [0.0, 0.002, 0.05, 0.6][seed], rng.integers(1, 9, (rows, cols)), 0)
    stamp = stamp.astype(np.int32)
    got = _kernels.stamped_bounds(stamp)
    rc = np.argwhere(stamp > 0)
    if len(rc) == 0:
        assert got == (0, 0, 0, 0)
    else:
        assert got == (rc[:, 0].min(), rc[:, 0].max() + 1, rc[:, 1].min(), rc[:, 1].max() + 1)
    steps = rng.integers(0, 511, (rows, cols)) / 2.0  # whole and half steps of 1/255
    prob = np.clip(steps / 255.0, 0.0, 1.0).astype(np.float32)
    prob.flat[rng.integers(0, prob.size, 5)] = rng.random(5).astype(np.float32)
    for r0, r1, c0, c1 in [(0, rows, 0, cols), (rows // 3, rows, cols // 4, cols - cols // 5 or cols)]:
        q, bits = _kernels.frozen_cells(prob, stamp, r0, r1, c0, c1)
        np.testing.assert_array_equal(q, quantize(prob[r0:r1, c0:c1]))
        np.testing.assert_array_equal(bits, np.packbits(stamp[r0:r1, c0:c1] > 0, axis=1))


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_occupied_field_oracle(dtype):
    """``occupied_field`` against plain numpy: around every known cell above ``half`` the kernel is
    laid with ``np.maximum``; at uint8 it equals ``quantize`` of the float field (quantizing is
    monotone), which is what a finished submap's likelihood field is."""
    from slam2d.grid.probability_grid import quantize

    rng = np.random.default_rng(3)
    rows, cols, radius = 37, 29, 3
    kernel = field_kernel(0.1, 0.05, radius)
    prob = rng.random((rows, cols)).astype(np.float32)
    prob[0, 0] = prob[rows - 1, cols - 1] = 0.9  # surfaces on the corners
    known = rng.random((rows, cols)) < 0.8
    known[0, 0] = known[rows - 1, cols - 1] = True
    occ = known & (prob > 0.85)
    want = np.zeros((rows + 2 * radius, cols + 2 * radius), np.float32)
    for r, c in np.argwhere(occ):
        np.maximum(want[r:r + 2 * radius + 1, c:c + 2 * radius + 1], kernel, out=want[r:r + 2 * radius + 1, c:c + 2 * radius + 1])
    want = want[radius:radius + rows, radius:radius + cols]
    bits = np.packbits(known, axis=1)
    if dtype == np.uint8:
        got = _kernels.occupied_field(quantize(prob), bits, np.uint8(np.round(0.85 * 255)), quantize(kernel), radius)
        occ_q = known & (quantize(prob) > np.round(0.85 * 255))
        want_q = np.zeros((rows + 2 * radius, cols + 2 * radius), np.float32)
        for r, c in np.argwhere(occ_q):
            sl = (slice(r, r + 2 * radius + 1), slice(c, c + 2 * radius + 1))
            np.maximum(want_q[sl], kernel, out=want_q[sl])
        np.testing.assert_array_equal(got, quantize(want_q[radius:radius + rows, radius:radius + cols]))
    else:
        got = _kernels.occupied_field(prob, bits, np.float32(0.85), kernel, radius)
        np.testing.assert_array_equal(got, want)
    assert got.dtype == dtype and got[0, 0] == got.max() and (got == 0).any()


def test_insert_scans_lays_the_field_the_incremental_stamping_keeps():
    """A batch of scans into a grid with a likelihood field: the cells equal scan-by-scan insertion
    exactly; the field is the kernel laid afresh around every occupied cell (exactly the rule), and
    the field kept up scan by scan differs from it only in the last bits."""
    rng = np.random.default_rng(6)
    angles = np.linspace(-np.pi, np.pi, 120, endpoint=False)
    scans = []
    for i in range(30):
        o = rng.normal(0, 0.5, 2)
        r = rng.uniform(0.5, 4.0, 120)
        scans.append((o, np.c_[r * np.cos(angles), r * np.sin(angles)] + o, np.zeros((0, 2))))
    batch, one = ProbabilityGrid(0.05, field_sigma=0.1), ProbabilityGrid(0.05, field_sigma=0.1)
    batch.insert_scans(scans)
    for o, h, m in scans:
        one.insert(o, h, m)
    # the same lattice, other extents: compare where both grids are (every observed cell is in both)
    off = np.round((batch.origin - one.origin) / 0.05).astype(int)  # batch cell (0, 0) in one's cells (col, row)
    lo = np.maximum(off, 0)
    hi = np.minimum(off + np.array(batch.shape[::-1]), np.array(one.shape[::-1]))
    sl = (slice(lo[1], hi[1]), slice(lo[0], hi[0]))
    bl = (slice(lo[1] - off[1], hi[1] - off[1]), slice(lo[0] - off[0], hi[0] - off[0]))
    assert batch.known[bl].sum() == batch.known.sum() == one.known.sum()
    np.testing.assert_array_equal(batch.logodds[bl], one.logodds[sl])
    np.testing.assert_array_equal(batch.stamp[bl], one.stamp[sl])
    occ = np.argwhere(batch.logodds > 0)
    rows, cols = batch.shape
    want = np.zeros((rows + 2 * batch.field_radius, cols + 2 * batch.field_radius), np.float32)
    k = batch.field_kernel
    for r, c in occ:
        win = want[r:r + k.shape[0], c:c + k.shape[1]]
        np.maximum(win, k, out=win)
    rad = batch.field_radius
    np.testing.assert_array_equal(batch.field, want[rad:rad + rows, rad:rad + cols])
    np.testing.assert_allclose(batch.field[bl], one.field[sl], rtol=0, atol=1e-6)
    assert len(occ) > 300 and (one.field[sl] > 0).sum() > len(occ)
