"""Range data and voxel filter kernels against plain-numpy oracles."""
import numpy as np
import pytest

from slam2d.config import RangeFilterConfig
from slam2d.geometry import transform_points
from slam2d.range_data import SAME_SURFACE_GAP, adaptive_voxel_filter, range_data, voxel_filter
from slam2d.types import Scan


def range_data_oracle(scan: Scan, cfg: RangeFilterConfig):
    r = scan.ranges.astype(np.float64)
    a = scan.angles
    valid = scan.valid & (r >= max(cfg.min_range, scan.range_min))
    hit = valid & (r <= cfg.max_range)
    far = valid & (r > cfg.max_range)
    c, s = np.cos(a), np.sin(a)
    hits = np.stack([r[hit] * c[hit], r[hit] * s[hit]], axis=1)
    parts = [np.stack([cfg.max_range * c[far], cfg.max_range * s[far]], axis=1)]
    if cfg.missing_data_ray_length > 0:
        length = np.full(len(r), min(cfg.missing_data_ray_length, cfg.max_range))
        # cut at the nearer flank where both flanks (the nearest valid readings) lie on one surface
        flank = np.flatnonzero(valid & ~scan.no_return)
        for i in np.flatnonzero(scan.no_return):
            left, right = flank[flank < i], flank[flank > i]
            if len(left) and len(right):
                a, b = left[-1], right[0]
                if np.hypot(r[a] * c[a] - r[b] * c[b], r[a] * s[a] - r[b] * s[b]) <= SAME_SURFACE_GAP:
                    length[i] = min(length[i], r[a], r[b])
        nr = scan.no_return
        parts.append(np.stack([length[nr] * c[nr], length[nr] * s[nr]], axis=1))
    off = scan.laser_offset
    return transform_points(off, hits), transform_points(off, np.vstack(parts)), int(far.sum())


def voxel_oracle(points, size):
    seen, keep = set(), []
    for i, p in enumerate(points):
        key = tuple(np.floor(p / size).astype(int))
        if key not in seen:
            seen.add(key)
            keep.append(i)
    return points[keep]


def random_scan(rng, n=181):
    ranges = rng.uniform(0.0, 40.0, n).astype(np.float32)
    no_return = rng.random(n) < 0.1
    ranges[no_return] = 50.0
    valid = ~no_return & (rng.random(n) < 0.95)
    return Scan(0.0, ranges, -np.pi / 2, np.pi / (n - 1), 0.1, 50.0, valid, no_return=no_return,
                laser_offset=np.array([0.2, -0.05, rng.uniform(-0.3, 0.3)]))


def room_scan(rng, n=181, dropout=0.1):
    """A robot in a 4 m × 3 m room with an open door (1.6 m wide, open space beyond) in its far wall:
    the door's beams are no-returns, and ``dropout`` of the others too (a wall's dark patches)."""
    a = np.linspace(-np.pi / 2, np.pi / 2, n)
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        t = np.minimum(np.where(c > 0, 2.5 / c, np.inf), np.where(s > 0, 1.5 / s, np.where(s < 0, 1.5 / -s, np.inf)))
    door = (c > 0) & (2.5 / np.maximum(c, 1e-9) <= t + 1e-9) & (np.abs(2.5 * np.tan(a)) < 0.8)
    dropped = ~door & (rng.random(n) < dropout)
    ranges = (t + rng.normal(0, 0.01, n)).astype(np.float32)
    no_return = door | dropped
    ranges[no_return] = 50.0
    return Scan(0.0, ranges, a[0], a[1] - a[0], 0.1, 50.0, ~no_return, no_return=no_return,
                laser_offset=np.zeros(3)), t, door, dropped


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("miss", [0.0, 5.0])
@pytest.mark.parametrize("scene", ["random", "room"])
def test_range_data_matches_oracle(seed, miss, scene):
    rng = np.random.default_rng(seed)
    if scene == "room":
        scan = room_scan(rng, dropout=0.3)[0]
        cfg = RangeFilterConfig(min_range=0.5, max_range=30.0, missing_data_ray_length=miss)
        hits, misses, far = range_data_oracle(scan, cfg)
        rd = range_data(scan, cfg)
        np.testing.assert_allclose(rd.hits, hits, atol=1e-12)
        np.testing.assert_allclose(rd.misses, misses, atol=1e-12)
        assert far == rd.far == 0
        if miss:  # both kinds of no-return: cut at a wall, and the door's full length
            lengths = np.hypot(*misses.T)
            assert (lengths < 3.0).sum() > 10 and (lengths == 5.0).sum() > 10
        return
    scan = random_scan(rng)
    cfg = RangeFilterConfig(min_range=0.5, max_range=30.0, missing_data_ray_length=miss)
    rd = range_data(scan, cfg)
    hits, misses, far = range_data_oracle(scan, cfg)
    assert len(rd.hits) > 100 and len(rd.misses) > (10 if miss else 0)
    np.testing.assert_allclose(rd.hits, hits, atol=1e-12)
    np.testing.assert_allclose(rd.misses, misses, atol=1e-12)
    np.testing.assert_allclose(rd.origin, scan.laser_offset[:2])
    # the misses of returns beyond max_range come first, and ``far`` says how many (the health
    # report's free space is theirs and the returns', not the no-returns')
    assert rd.far == far and 10 < far <= len(rd.misses) - (10 if miss else 0)
    moved = rd.transformed(np.array([1.0, 2.0, 0.3]))
    assert moved.far == far


@pytest.mark.parametrize("size", [0.025, 0.1, 1.0])
def test_voxel_filter_matches_oracle(size):
    rng = np.random.default_rng(7)
    pts = rng.normal(0, 2.0, (500, 2))
    pts[250:] = pts[:250] + rng.normal(0, 0.01, (250, 2))  # near-duplicates share cells
    got = voxel_filter(pts, size)
    want = voxel_oracle(pts, size)
    np.testing.assert_array_equal(got, want)
    assert len(got) < len(pts) or size < 0.05


@pytest.mark.parametrize("no_return", [None, 50.0])
def test_classify_readings_matches_oracle(no_return):
    from slam2d._kernels import classify_readings

    rng = np.random.default_rng(4)
    r = rng.uniform(0, 60, 300)
    r[::17] = np.nan
    r[::23] = np.inf
    r[::31] = 0.0
    r[5] = 50.0
    valid = np.empty(300, bool)
    no_ret = np.empty(300, bool)
    neg, all_nan = classify_readings(r, np.nan if no_return is None else no_return, valid, no_ret)
    want_nr = np.isposinf(r) | ((r >= no_return) if no_return is not None else False)
    np.testing.assert_array_equal(no_ret, want_nr)
    np.testing.assert_array_equal(valid, ~np.isnan(r) & ~want_nr & (r > 0))
    assert neg == -1 and not all_nan
    r[[40, 90]] = [-1.0, -np.inf]
    assert classify_readings(r, 50.0, valid, no_ret)[0] == 40
    assert classify_readings(np.full(4, np.nan), 50.0, valid[:4], no_ret[:4]) == (-1, True)


def survey_band_oracle(ranges, threshold):
    """The no-return survey's band in plain numpy: the finite readings at or above ``threshold``."""
    band = ranges[ranges >= threshold]
    return band[np.isfinite(band)]


def test_survey_band_matches_oracle():
    from slam2d._kernels import survey_band

    cases = [(np.array([1.0, np.inf, 81.83, np.nan, 81.91, -np.inf, 3.0, 40.0]), -np.inf),
             (np.array([1.0, 2.0, 3.0]), 50.0),         # all below: nothing
             (np.array([np.nan, np.inf, -np.inf]), 12.0),  # nothing finite: nothing
             (np.zeros(0), -np.inf)]
    rng = np.random.default_rng(0)
    cases += [(np.where(rng.random(300) < 0.1, np.inf, rng.uniform(0, 80, 300)).astype(dt), m)
              for dt in (np.float32, np.float64) for m in (-np.inf, 30.0, 95.0)]
    for ranges, threshold in cases:
        got = survey_band(ranges, threshold)
        assert got.dtype == ranges.dtype
        np.testing.assert_array_equal(got, survey_band_oracle(ranges, threshold))
    assert survey_band(cases[0][0], 36.0).tolist() == [81.83, 81.91, 40.0]


def test_adaptive_voxel_filter_keeps_about_the_minimum():
    """Cartographer's adaptive voxel filter: a small cloud is kept whole; a cloud that the coarsest
    cell still leaves large enough gets that cell; otherwise the cell is bisected until just enough
    points remain (a straight wall: points ≈ length / cell, so within the 10 % bisection step)."""
    rng = np.random.default_rng(5)
    few = rng.uniform(-5, 5, (80, 2))
    assert adaptive_voxel_filter(few, 100, 0.9) is few
    spread = rng.uniform(-100, 100, (400, 2))  # 0.9 m cells keep almost all of them
    np.testing.assert_array_equal(adaptive_voxel_filter(spread, 100, 0.9), voxel_filter(spread, 0.9))
    wall = np.c_[np.linspace(0.013, 19.987, 2000), np.full(2000, 3.01)]  # 20 m of wall, 1 cm apart
    out = adaptive_voxel_filter(wall, 100, 0.9)
    assert 100 <= len(out) <= 125, len(out)
    assert len(voxel_filter(wall, 0.9)) < 100  # the coarsest cell alone would keep too few
    rows = {tuple(p) for p in wall.tolist()}
    assert all(tuple(p) in rows for p in out.tolist())  # a subset of the input, not new points
    assert adaptive_voxel_filter(wall, 0, 0.9) is wall  # 0 disables it


def adaptive_voxel_oracle(points, min_points, max_length):
    """The bisection in plain Python over ``voxel_oracle``."""
    if min_points <= 0 or len(points) <= min_points:
        return points
    coarsest = voxel_oracle(points, max_length)
    if len(coarsest) >= min_points:
        return coarsest
    high, result = max_length, coarsest
    while high > 0.01 * max_length:
        low = 0.5 * high
        result = voxel_oracle(points, low)
        if len(result) >= min_points:
            while high / low > 1.1:
                mid = 0.5 * (low + high)
                cand = voxel_oracle(points, mid)
                if len(cand) >= min_points:
                    low, result = mid, cand
                else:
                    high = mid
            return result
        high = low
    return result


@pytest.mark.parametrize("seed", range(6))
def test_adaptive_voxel_filter_matches_oracle(seed):
    """Clouds of every kind the bisection meets: enough points at the coarsest cell, a bisection
    that ends between two cells, and one that never reaches ``min_points`` (all points in a few cm)."""
    rng = np.random.default_rng(seed)
    clouds = [rng.uniform(-30, 30, (300, 2)),
              np.c_[np.linspace(0.013, 19.987, 1500), np.full(1500, 3.01)] + rng.normal(0, 0.01, (1500, 2)),
              rng.normal(0, 0.002, (150, 2)),
              np.vstack([rng.normal(0, 3.0, (120, 2)), rng.normal(5, 0.05, (200, 2))])]
    for pts in clouds:
        for min_points, max_length in ((100, 0.9), (50, 0.5), (140, 2.0)):
            np.testing.assert_array_equal(adaptive_voxel_filter(pts, min_points, max_length),
                                          adaptive_voxel_oracle(pts, min_points, max_length))


@pytest.mark.parametrize("seed", range(4))
def test_voxel_filter_index_picks_the_filters_points(seed):
    """``voxel_filter_index`` names (increasing) exactly the points ``voxel_filter`` returns, also
    when the filter keeps everything (size 0, few points, no points)."""
    from slam2d.range_data import voxel_filter_index

    rng = np.random.default_rng(seed)
    for pts in (rng.uniform(-20, 20, (400, 2)), rng.normal(0, 0.01, (30, 2)), np.zeros((0, 2))):
        for size in (0.0, 0.05, 0.5):
            idx = voxel_filter_index(pts, size)
            assert np.all(np.diff(idx) > 0)
            np.testing.assert_array_equal(pts[idx], voxel_filter(pts, size))


def test_no_return_rays_stop_at_the_sensor_range():
    """A no-return says nothing lies within the sensor's range; beyond it the space is unknown, so a
    4 m sensor's no-return rays insert free space to 4 m, not to missing_data_ray_length (5 m)."""
    r = np.array([2.0, np.inf, 3.0, np.inf], np.float32)
    for sensor, want in ((4.0, 4.0), (30.0, 5.0)):
        scan = Scan.from_ranges(0.0, r, -0.3, 0.2, sensor)
        rd = range_data(scan, RangeFilterConfig())
        assert len(rd.hits) == 2 and len(rd.misses) == 2
        np.testing.assert_allclose(np.hypot(*rd.misses.T), want, rtol=1e-6)


def test_dropped_beams_do_not_erase_the_walls():
    """A third of the beams at the walls of a room come back without an echo (dark patches). Their
    free-space rays stop at the wall, so the walls stay occupied and what lies behind them stays
    unknown; through the open door, where no beam returns, free space goes on to
    ``missing_data_ray_length``. With every no-return ray at its full length (as Cartographer
    inserts them) the same scans mark the space behind the walls free: in a building, the next
    room, whose walls are then weaker when the robot gets there."""
    from slam2d.grid.probability_grid import ProbabilityGrid

    cfg = RangeFilterConfig()
    rng = np.random.default_rng(3)
    scans = [room_scan(rng, dropout=0.3) for _ in range(30)]
    t, door = scans[0][1], scans[0][2]
    dropped_any = np.any([d for *_, d in scans], axis=0)
    for scan, _, _, dropped in scans:
        rd = range_data(scan, cfg)
        lengths = np.hypot(*rd.misses.T)
        beams = np.flatnonzero(scan.no_return)
        # a dropped beam between two returns, with no door beam between them either: its ray ends
        # at a flank, a few cm from the wall at most (next to the door it cannot be told from the
        # door's beams, and keeps its full length)
        returns = np.flatnonzero(~scan.no_return)
        inner = []
        for k, b in enumerate(beams):
            if dropped[b] and returns[0] < b < returns[-1]:
                lo, hi = returns[returns < b][-1], returns[returns > b][0]
                if not door[lo:hi].any():
                    inner.append(k)
        assert len(inner) > 20
        assert np.all(lengths[inner] <= t[beams[inner]] + 0.1)
        np.testing.assert_allclose(lengths[door[beams]], cfg.missing_data_ray_length)

    def build(full_rays: bool):
        g = ProbabilityGrid(0.05)
        for scan, *_ in scans:
            rd = range_data(scan, cfg)
            if full_rays:  # every no-return ray at its full length
                m = rd.misses / np.hypot(*rd.misses.T)[:, None] * cfg.missing_data_ray_length
                rd = type(rd)(rd.origin, rd.hits, m, rd.far)
            g.insert(rd.origin, rd.hits, rd.misses)
        return g

    def value_at(g, pts):
        p = g.probability(unknown_value=-1.0)
        c = np.floor((pts - g.origin) / g.resolution).astype(int)
        return p[c[:, 1], c[:, 0]]

    # where beams were dropped: the wall cell, and a point 0.5 m behind it
    a = scans[0][0].angles[dropped_any & ~door]
    u = np.c_[np.cos(a), np.sin(a)]
    wall, behind = u * t[dropped_any & ~door][:, None], u * (t[dropped_any & ~door][:, None] + 0.5)
    d = scans[0][0].angles[door]
    through = 4.0 * np.c_[np.cos(d), np.sin(d)]  # along the door's beams, well beyond it
    ours, full = build(False), build(True)
    assert (value_at(ours, wall) > 0.5).mean() > 0.95
    # (beams at the scan's ends and next to the door have no flank on one side, or the door's
    # beams as one: they keep their full length)
    assert (value_at(ours, behind) == -1.0).mean() > 0.8
    assert (value_at(ours, through) < 0.5).all() and (value_at(ours, through) >= 0).all()
    assert (value_at(full, behind) == -1.0).mean() < 0.2
