"""The map health report flags a broken map and passes a good one (no ground truth used)."""
import math

import numpy as np
import pytest

from slam2d.config import config_from_dict
from slam2d.geometry import compose, transform_points
from slam2d.health import VIOLATION_RANGE_SHARE, assess


def _world(nodes, poses):
    """The health report's ray geometry in plain numpy (oracles of ``_kernels.world_beams`` and
    ``_kernels.free_space_counts``). Per node: sensor origin (2,), hits (N, 2) and every ray end (hits then misses), in the map frame."""
    return [_node_world(n, poses[n.scan_index]) for n in nodes]


def _node_world(n, q):
    """One node of ``_world`` at pose ``q``."""
    o = transform_points(q, np.asarray(n.origin, dtype=np.float64).reshape(1, 2))[0]
    h = transform_points(q, np.asarray(n.hits, dtype=np.float64).reshape(-1, 2))
    m = transform_points(q, np.asarray(n.misses, dtype=np.float64).reshape(-1, 2))
    return o, h, np.concatenate([h, m])


def _beams(o, ends):
    """Bearings (sorted), ranges and the median bearing step of the rays from ``o`` to ``ends``."""
    d = ends - o
    b = np.arctan2(d[:, 1], d[:, 0])
    order = np.argsort(b, kind="stable")
    b, r = b[order], np.hypot(d[order, 0], d[order, 1])
    step = float(np.median(np.diff(b))) if len(b) > 2 else np.inf
    return b, r, step


def _violation(hits, o, beams, resolution):
    """(violating hits, checked hits) of ``hits`` against the beams of a scan taken at ``o``."""
    b, r, step = beams
    if len(b) < 3 or len(hits) == 0:
        return 0, 0
    d = hits - o
    qb = np.arctan2(d[:, 1], d[:, 0])
    qr = np.hypot(d[:, 0], d[:, 1])
    idx = np.searchsorted(b, qb)
    lo, hi = (idx - 1) % len(b), idx % len(b)
    seen = np.remainder(b[hi] - b[lo], 2 * np.pi) <= 3 * step  # inside the other's field of view
    free = np.minimum(r[lo], r[hi])
    bad = seen & (qr < free - (2 * resolution + VIOLATION_RANGE_SHARE * qr))
    return int(bad.sum()), int(seen.sum())


def _bundled_local_run():
    from conftest import BUNDLED
    from slam2d.io.source import open_source
    from slam2d.slam import Slam

    cfg = config_from_dict({})
    slam = Slam(cfg, mode="local")
    result = slam.run(open_source(BUNDLED))
    return cfg, slam.tracker, result


def test_health_passes_a_good_map_and_flags_a_broken_one():
    cfg, tracker, result = _bundled_local_run()
    good = assess(cfg, result.nodes, result.poses, tracker.summary()["local_slam"])
    assert good["status"] == "OK", good
    assert good["scans_agreeing_with_map"] > 0.95
    # break it: the second half of the trajectory turned by 8° and shifted by 0.5 m (a failed match)
    poses = result.poses.copy()
    half = len(poses) // 2
    kink = np.array([0.5, 0.0, math.radians(8.0)])
    for i in range(half, len(poses)):
        poses[i] = compose(kink, poses[i])
    bad = assess(cfg, result.nodes, poses, tracker.summary()["local_slam"])
    assert bad["status"] == "BROKEN", bad
    assert bad["reasons"]


def test_health_flags_a_revisit_that_was_not_closed():
    """The robot comes back along its earlier path but the map puts it a metre and a few degrees
    off (a loop that was never closed): its scans agree with their own pass, not with the earlier
    one. The revisit share judges exactly those scans, and says so."""
    cfg, tracker, result = _bundled_local_run()
    good = assess(cfg, result.nodes, result.poses, tracker.summary()["local_slam"])
    assert good["revisits_checked"] > 100 and good["revisits_agreeing"] > 0.95, good
    poses = result.poses.copy()
    start = int(0.75 * len(poses))  # the last quarter drifted away, rigidly
    off = np.array([1.0, 0.3, math.radians(4.0)])
    for i in range(start, len(poses)):
        poses[i] = compose(off, poses[i])
    bad = assess(cfg, result.nodes, poses, tracker.summary()["local_slam"])
    assert bad["revisits_agreeing"] < good["revisits_agreeing"] - 0.1, bad
    assert bad["status"] != "OK" and any("came back" in r for r in bad["reasons"]), bad
    # where: the longest stretches of disagreeing revisits, each with the position of its middle node;
    # one of them is the drifted quarter itself, and the good map's are few and short
    where = bad["revisits_disagreeing_at"]
    assert where and len(where) <= 5 and where[0]["nodes"] >= where[-1]["nodes"]
    assert any(w["scans"][0] >= start for w in where), where
    assert where[0]["nodes"] > max([w["nodes"] for w in good["revisits_disagreeing_at"]], default=0), (where, good)
    by_scan = {n.scan_index: n for n in result.nodes}
    for w in where:
        a, b = w["scans"]
        assert a in by_scan and b in by_scan and a <= b
        mids = poses[[i for i in by_scan if a <= i <= b]]
        assert np.min(np.hypot(mids[:, 0] - w["at"][0], mids[:, 1] - w["at"][1])) < 0.06
    assert f"scans {where[0]['scans'][0]}-{where[0]['scans'][1]}" in " ".join(bad["reasons"])


def test_health_flags_untrusted_matches():
    local = {"matched_scans": 900, "untrusted": 100}
    h = assess(config_from_dict({}), [], np.zeros((0, 3)), local)
    assert h["status"] == "BROKEN" and "matched with confidence" in h["reasons"][0]


@pytest.mark.parametrize("matched, still, status", [(1000, 0, "OK"), (850, 100, "OK"), (850, 0, "WARN"),
                                                   (300, 100, "BROKEN"), (0, 0, "BROKEN")])
def test_health_flags_scans_never_matched(matched, still, status):
    """A log of 2-beam scans leaves local SLAM nothing to match: the trajectory is the odometry's, and
    the report must not say OK. Scans skipped while the robot stood still are not unmatched."""
    local = {"matched_scans": matched, "untrusted": 0, "still": still}
    h = assess(config_from_dict({}), [], np.zeros((0, 3)), local, scans=1000)
    assert h["status"] == status
    assert h["unmatched_share"] == pytest.approx(max(0.0, 1 - (matched + still + 1) / 1000), abs=1e-4)  # the first scan has no submap
    assert ("never matched" in " ".join(h["reasons"])) == (status != "OK")


@pytest.mark.parametrize("scans", [1, 5, 9])
def test_a_short_run_s_first_scan_is_not_unmatched(scans):
    """The first scan has no submap to be matched against: --max-scans 5 read as 20 % unmatched (WARN)."""
    h = assess(config_from_dict({}), [], np.zeros((0, 3)), {"matched_scans": scans - 1, "untrusted": 0, "still": 0},
               scans=scans)
    assert h["status"] == "OK" and h["unmatched_share"] == 0.0


def _box_scan(pose, half=(5.0, 3.0), person=None, beams=360):
    """Hits of a 360° scan taken at ``pose`` inside a box room centred on the origin (tracking frame),
    with an optional round obstacle (x, y, radius) that only this scan sees."""
    from slam2d.types import Node

    x, y, th = pose
    hits = []
    for a in np.linspace(-math.pi, math.pi, beams, endpoint=False):
        dx, dy = math.cos(th + a), math.sin(th + a)
        r = min((half[0] * math.copysign(1, dx) - x) / dx if abs(dx) > 1e-9 else math.inf,
                (half[1] * math.copysign(1, dy) - y) / dy if abs(dy) > 1e-9 else math.inf)
        if person is not None:  # ray / circle
            px, py, pr = person
            b = dx * (x - px) + dy * (y - py)
            c = (x - px) ** 2 + (y - py) ** 2 - pr * pr
            if b * b - c >= 0 and -b - math.sqrt(b * b - c) > 0:
                r = min(r, -b - math.sqrt(b * b - c))
        hits.append((r * math.cos(a), r * math.sin(a)))
    return Node(0, 0.0, np.array(pose), np.array(hits, np.float32), np.zeros((0, 2), np.float32), np.zeros(2, np.float32))


def test_free_space_check_ignores_a_person_seen_by_one_scan_and_flags_a_wrong_pose():
    from slam2d.health import MAX_VIOLATION, free_space_violation

    a_pose, b_pose = np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.5, 0.4])
    a = _box_scan(a_pose)
    b = _box_scan(b_pose, person=(1.5, -0.3, 0.4))  # someone stood next to b while it was taken
    a.scan_index, b.scan_index = 0, 1
    right = np.array([a_pose, b_pose])
    # one way the person is a violation (b's hits on them lie in a's free space), and a big one ...
    (o_a, _, ends_a), (_, hits_b, _) = _world([a, b], right)
    bad, seen = _violation(hits_b, o_a, _beams(o_a, ends_a), 0.05)
    assert bad / seen > MAX_VIOLATION
    # ... but nothing of a's lies in b's free space: the pair agrees
    v = free_space_violation([a, b], right, 0.05)
    assert (v <= MAX_VIOLATION).all(), v
    # the same scans with b's pose 0.4 m and 3° off: each sees the other's walls in its free space
    wrong = np.array([a_pose, compose(b_pose, [0.4, -0.3, math.radians(3.0)])])
    v = free_space_violation([a, b], wrong, 0.05)
    assert (v > MAX_VIOLATION).all(), v


def test_no_return_rays_are_no_free_space_evidence_but_returns_beyond_range_are():
    """A sensor drops returns (glass, black or shiny surfaces, grazing angles); CARMEN logs write a
    dropped beam as a no-return, which local SLAM inserts as a short free-space ray. Where such
    rays cross a wall another scan saw, the poses are not wrong: two scans of a room at their
    true poses, each with a quarter of its beams dropped (a dark wall) and a few more at random,
    agree. The same rays as returns beyond the usable range (``far_misses``) are real free space,
    and the walls inside them make the pair disagree."""
    from slam2d.health import MAX_VIOLATION, free_space_violation

    rng = np.random.default_rng(2)
    poses = np.array([[-1.0, 0.0, 0.0], [1.0, 0.5, 0.4]])
    nodes = []
    for k, (pose, sector) in enumerate(zip(poses, ((0, 90), (180, 270)))):
        n = _box_scan(pose)
        bearing = np.degrees(np.arctan2(n.hits[:, 1], n.hits[:, 0])) % 360
        dropped = ((bearing >= sector[0]) & (bearing < sector[1])) | (rng.random(len(n.hits)) < 0.1)
        rays = n.hits[dropped] / np.linalg.norm(n.hits[dropped], axis=1, keepdims=True) * 5.0  # missing_data_ray_length
        assert (5.0 > np.linalg.norm(n.hits[dropped], axis=1)).mean() > 0.5  # most of them cross a wall
        n.hits, n.misses, n.scan_index = n.hits[~dropped], rays.astype(np.float32), k
        nodes.append(n)
    assert (free_space_violation(nodes, poses, 0.05) <= MAX_VIOLATION).all()
    for n in nodes:
        n.far_misses = len(n.misses)
    assert (free_space_violation(nodes, poses, 0.05) > MAX_VIOLATION).all()


def test_free_space_kernel_matches_the_numpy_oracle():
    from slam2d import _kernels

    rng = np.random.default_rng(4)
    nodes = []
    for k in range(6):
        n = _box_scan((rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(-math.pi, math.pi)), beams=int(rng.integers(3, 200)),
                      person=(rng.uniform(-3, 3), rng.uniform(-2, 2), 0.3) if k % 2 else None)
        n.hits = n.hits[rng.random(len(n.hits)) < 0.8]  # dropped beams: gaps wider than 3 steps
        n.scan_index = k
        nodes.append(n)
    poses = np.array([n.local_pose for n in nodes]) + rng.normal(0, 0.1, (6, 3))  # some wrong poses
    world = _world(nodes, poses)
    beams = [_beams(o, ends) for o, _, ends in world]
    pairs = np.array([(a, b) for a in range(6) for b in range(6) if a != b], dtype=np.int64)
    got = _kernels.free_space_counts(
        np.concatenate([w[1] for w in world]), np.r_[0, np.cumsum([len(w[1]) for w in world])].astype(np.int64),
        np.array([w[0] for w in world]), np.concatenate([b[0] for b in beams]), np.concatenate([b[1] for b in beams]),
        np.r_[0, np.cumsum([len(b[0]) for b in beams])].astype(np.int64), np.array([b[2] for b in beams]), pairs,
        0.05, VIOLATION_RANGE_SHARE)
    want = [_violation(world[a][1], world[b][0], beams[b], 0.05) for a, b in pairs]
    np.testing.assert_array_equal(got, np.array(want))
    assert (got[:, 0] > 0).any() and (got[:, 1] > 0).all()


def test_world_beams_kernel_matches_the_numpy_oracle():
    """Sensors, hits, sorted bearings, ranges and median steps of every node at its pose, from the
    flat float32 rays the report hands the kernel; nodes with no misses, with fewer than 3 beams,
    and beams at equal bearings (the stable order) included."""
    from slam2d import _kernels

    rng = np.random.default_rng(11)
    nodes = []
    for k in range(7):
        n = _box_scan((rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(-math.pi, math.pi)),
                      beams=[360, 2, 90, 1, 200, 45, 120][k], person=(0.5, 0.2, 0.3) if k == 4 else None)
        n.hits = n.hits[rng.random(len(n.hits)) < 0.8]
        if k % 2:  # misses: rays with no return, ending farther out
            n.misses = (n.hits[::3] * np.float32(1.7)).astype(np.float32)
        if k == 5:  # two rays along one bearing
            n.hits = np.concatenate([n.hits, n.hits[:3] * np.float32(0.5)])
        n.scan_index = k
        nodes.append(n)
    poses = np.array([n.local_pose for n in nodes]) + rng.normal(0, 0.1, (7, 3))
    starts = [np.r_[0, np.cumsum([len(getattr(n, a)) for n in nodes])].astype(np.int64) for a in ("hits", "misses")]
    o, h, b, r, bs, steps = _kernels.world_beams(
        poses, np.array([n.origin for n in nodes], dtype=np.float64),
        np.concatenate([n.hits for n in nodes]).astype(np.float32), starts[0],
        np.concatenate([n.misses for n in nodes]).astype(np.float32), starts[1])
    for k, (wo, wh, ends) in enumerate(_world(nodes, poses)):
        wb, wr, wstep = _beams(wo, ends)
        np.testing.assert_allclose(o[k], wo, rtol=0, atol=1e-12)
        np.testing.assert_allclose(h[starts[0][k]:starts[0][k + 1]], wh, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b[bs[k]:bs[k + 1]], wb, rtol=0, atol=1e-12)
        np.testing.assert_allclose(r[bs[k]:bs[k + 1]], wr, rtol=0, atol=1e-12)
        assert steps[k] == wstep if not np.isfinite(wstep) else abs(steps[k] - wstep) < 1e-12


def _neighbours_oracle(origins, path, radius, per_pass):
    """The health report's neighbour choice in plain numpy (the loop the kernel replaced)."""
    from scipy.spatial import cKDTree

    picks = []
    near = cKDTree(origins).query_ball_point(origins, radius, return_sorted=True)
    for i in range(len(origins)):
        cand = np.asarray(near[i], dtype=np.int64)
        cand = cand[cand != i]
        if len(cand) == 0:
            continue
        dist = np.hypot(*(origins[cand] - origins[i]).T)
        same = np.abs(path[cand] - path[i]) < 2 * radius
        for other, mask in ((0, same), (1, ~same)):
            picks.extend((i, int(j), other) for j in cand[mask][np.argsort(dist[mask], kind="stable")[:per_pass]])
    return np.array(picks, dtype=np.int64).reshape(-1, 3)


def test_neighbour_kernel_matches_the_numpy_oracle():
    """Exactly the oracle's pairs, in its order, on a path that comes back several times (other passes),
    with nodes on a lattice so that many distances tie (and some lie exactly on the radius), far from
    and around the origin (negative cells)."""
    from slam2d._kernels import pick_neighbours
    from slam2d.health import NEIGHBOUR_RADIUS, NEIGHBOURS_PER_PASS

    rng = np.random.default_rng(4)
    t = np.linspace(0, 6 * math.pi, 900)
    for shift in (0.0, 1000.0, -37.0):
        origins = np.round(np.c_[20 * np.cos(t) + 0.5 * t, 12 * np.sin(t)] + rng.normal(0, 0.3, (900, 2)), 0) + shift
        path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(origins, axis=0).T))])
        want = _neighbours_oracle(origins, path, NEIGHBOUR_RADIUS, NEIGHBOURS_PER_PASS)
        got = pick_neighbours(origins, path, NEIGHBOUR_RADIUS, 2 * NEIGHBOUR_RADIUS, NEIGHBOURS_PER_PASS)
        assert (want[:, 2] == 1).sum() > 500 and len(want) > 3000  # other passes are there
        np.testing.assert_array_equal(got, want)
    # a neighbour exactly on the radius is one (scipy's ball is closed); one just beyond is not
    origins = np.array([[0.0, 0.0], [NEIGHBOUR_RADIUS, 0.0], [0.0, -NEIGHBOUR_RADIUS - 1e-9]])
    path = np.array([0.0, 100.0, 200.0])
    got = pick_neighbours(origins, path, NEIGHBOUR_RADIUS, 2 * NEIGHBOUR_RADIUS, NEIGHBOURS_PER_PASS)
    np.testing.assert_array_equal(got, _neighbours_oracle(origins, path, NEIGHBOUR_RADIUS, NEIGHBOURS_PER_PASS))
    assert [tuple(r) for r in got] == [(0, 1, 1), (1, 0, 1)]


def test_disagreeing_stretches_follow_the_path():
    """Runs of disagreeing nodes: an agreeing node ends a run, unchecked nodes (NaN) neither extend nor
    end it unless the path between two checked nodes exceeds the neighbour radius; longest first."""
    from types import SimpleNamespace

    from slam2d.health import MAX_VIOLATION, NEIGHBOUR_RADIUS, disagreeing_stretches

    n = 40
    poses = np.zeros((n, 3))
    poses[:, 0] = 0.5 * np.arange(n)  # 0.5 m between scans
    poses[35:, 0] += 3 * NEIGHBOUR_RADIUS  # a jump in the path before scan 35
    nodes = [SimpleNamespace(scan_index=i) for i in range(n)]
    bad, good = 2 * MAX_VIOLATION, 0.0
    v = np.full(n, np.nan)
    v[[2, 3, 5, 6]] = bad      # one run across an unchecked node (4)
    v[7] = good                # ... ended by an agreeing one
    v[[10, 11, 12]] = bad      # a second, shorter run
    v[[33, 34, 36]] = bad      # 10.5 m of path after 12, not the same run; broken again by the jump
    out = disagreeing_stretches(nodes, poses, v)
    assert [w["scans"] for w in out] == [[2, 6], [10, 12], [33, 34], [36, 36]]
    assert [w["nodes"] for w in out] == [4, 3, 2, 1]
    assert out[0]["at"] == [2.5, 0.0]  # the middle disagreeing node, scan 5
    assert disagreeing_stretches(nodes, poses, np.full(n, good)) == []
    assert len(disagreeing_stretches(nodes, poses, v, most=2)) == 2
