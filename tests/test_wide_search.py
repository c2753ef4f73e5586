"""The loop search after a long stretch without loop closure (slam2d/backend/wide_search.py)."""
import math

import numpy as np
import pytest

from slam2d.backend.wide_search import (COARSE_FACTOR, NEUTRAL, coarse_grid, coarse_match,
                                        frame_offset, submap_content)
from slam2d.geometry import between, compose, inverse
from slam2d.grid.probability_grid import ProbabilityGrid
from slam2d.io.simulator import floor_plan, raycast

ANGLES = -math.pi + 2 * math.pi / 360 * np.arange(360)


def _grid(segs, poses, max_range=12.0):
    """A finished submap grid (uint8 probabilities and a known mask) of scans taken at ``poses``."""
    g = ProbabilityGrid(0.05)
    for p in poses:
        r = raycast(segs, p[:2], ANGLES + p[2], max_range)
        ok = np.isfinite(r)
        pts = np.stack([r[ok] * np.cos(ANGLES[ok]), r[ok] * np.sin(ANGLES[ok])], axis=1)
        g.insert(p[:2], compose(p, np.c_[pts, np.zeros(len(pts))])[:, :2])
    g.freeze(*g.known_bounds())
    return g


def test_coarse_grid_is_the_block_maximum_with_unobserved_cells_neutral():
    segs = floor_plan()
    g = _grid(segs, [np.array([6.0, 1.25, 0.0]), np.array([14.0, 6.0, 0.5])])
    c = coarse_grid(g)
    f = COARSE_FACTOR
    q = np.where(g.known > 0, g.prob, NEUTRAL).astype(np.uint8)
    rows, cols = q.shape
    assert c.values.shape == (math.ceil(rows / f), math.ceil(cols / f))
    for r, col in [(0, 0), (3, 7), (c.values.shape[0] - 1, c.values.shape[1] - 1), (10, 20)]:
        block = q[r * f:(r + 1) * f, col * f:(col + 1) * f]
        pad = block.size < f * f  # the last row/column of blocks is padded with unobserved cells
        want = max(int(block.max()), NEUTRAL) if pad else int(block.max())
        assert int(c.values[r, col]) == want
    assert np.allclose(c.origin, g.origin) and math.isclose(c.resolution, 0.05 * f)


@pytest.mark.parametrize("budget", [(0, 0.0), (100, 0.9)], ids=["every-2x2-coarse-cells", "loop-point-budget"])
def test_coarse_match_finds_a_submap_moved_far_beyond_the_regular_window(budget):
    """The content of one submap, moved by 6 m and 70° (drift), is put back onto an older submap of
    the same place, also when the true pose lies near the older submap's border; also with the
    content thinned to the loop-closure points' budget (the default config's)."""
    segs = floor_plan()
    older = _grid(segs, [np.array([x, 6.0, 0.0]) for x in np.linspace(4.0, 26.0, 12)])
    target = coarse_grid(older)
    for path in ([np.array([x, 6.0, 0.3]) for x in np.linspace(5.0, 15.0, 6)],      # the middle
                 [np.array([x, 1.25, 0.0]) for x in np.linspace(20.0, 28.5, 5)]):    # the bottom-right corner
        newer = _grid(segs, path)
        content = submap_content(newer, *budget)
        if budget[0]:  # thinned: fewer points, but never below the budget
            assert budget[0] <= len(content) < len(submap_content(newer))
        centre = np.r_[content.mean(axis=0), 0.0]
        # where local SLAM put the newer submap: turned by 70° about its centre and moved 6 m
        drift = compose(compose(centre, np.array([4.0, -4.5, math.radians(70.0)])), inverse(centre))
        moved = compose(drift, np.c_[content, np.zeros(len(content))])[:, :2]
        moved_centre = compose(drift, centre)
        found = coarse_match(moved, np.r_[moved_centre[:2], 0.0], np.r_[moved_centre[:2], 0.0], target, 8.0,
                             math.radians(90.0))
        assert found is not None
        pose, score = found
        # the true pose of the moved centre frame: undo the drift
        truth = compose(inverse(drift), np.r_[moved_centre[:2], 0.0])
        dt, dr = frame_offset(pose, truth, np.zeros(3))
        assert dt < 2 * target.resolution and dr < math.radians(3.0), (dt, math.degrees(dr))
        assert score > NEUTRAL / 255.0
        # and the search at the drifted pose alone does not get there
        d0 = between(truth, np.r_[moved_centre[:2], 0.0])
        assert math.hypot(d0[0], d0[1]) > 3.0


def test_frame_offset_measures_at_the_given_point():
    a = np.array([1.0, 2.0, 0.3])
    b = compose(a, np.array([0.0, 0.0, math.radians(1.0)]))  # the same origin, turned by 1°
    dt0, dr0 = frame_offset(a, b, np.zeros(3))
    dt, dr = frame_offset(a, b, np.array([20.0, 0.0, 0.0]))  # 20 m away that turn is 0.35 m
    assert dt0 < 1e-9 and math.isclose(dr0, math.radians(1.0), rel_tol=1e-9)
    assert math.isclose(dt, 20 * 2 * math.sin(math.radians(0.5)), rel_tol=1e-6)


def _scan_points(segs, pose, max_range=12.0):
    r = raycast(segs, pose[:2], ANGLES + pose[2], max_range)
    ok = np.isfinite(r)
    return np.stack([r[ok] * np.cos(ANGLES[ok]), r[ok] * np.sin(ANGLES[ok])], axis=1)


def _submap(index, segs, true_poses, local_poses):
    from types import SimpleNamespace

    g = ProbabilityGrid(0.05)
    for t, p in zip(true_poses, local_poses):
        pts = _scan_points(segs, t)
        g.insert(p[:2], compose(p, np.c_[pts, np.zeros(len(pts))])[:, :2])
    g.freeze(*g.known_bounds())
    return SimpleNamespace(grid=g, local_pose=np.asarray(local_poses[0], float), index=index, node_indices=[])


def _global_slam_with_a_return(detour: float, cfg=None, segs=None, first=None, again=None, mid=None, drift=None):
    """Submap 0 maps a corridor; after ``detour`` metres of driving elsewhere the robot maps it again
    (submap 3), but local SLAM's frame has drifted about the corridor's middle ``mid`` by ``drift``
    (its pose there; default: the office's corridor, 5 m and 40°). ``first`` / ``again``: the true
    poses of the two passes."""
    from types import SimpleNamespace

    from slam2d.backend.global_slam import GlobalSlam
    from slam2d.config import SlamConfig

    segs = floor_plan() if segs is None else segs
    gs = GlobalSlam(cfg or SlamConfig())
    first = [np.array([x, 6.0, 0.0]) for x in np.linspace(4.0, 26.0, 23)] if first is None else first
    again = [np.array([x, 6.0, math.pi]) for x in np.linspace(24.0, 8.0, 17)] if again is None else again
    mid = np.array([15.0, 6.0, 0.0]) if mid is None else mid
    drift = compose(compose(mid, np.array([3.0, -4.0, math.radians(40.0)]) if drift is None else drift), inverse(mid))

    def node(j, true, local, submap):
        scan = SimpleNamespace(index=j, timestamp=float(j), timestamp_text=None)
        gs.add_node(scan, local, _scan_points(segs, true), None, [(submap.index, submap.local_pose)])
        submap.node_indices.append(j)

    s0 = _submap(0, segs, first, first)
    for j, p in enumerate(first):
        node(j, p, p, s0)
    gs.add_finished_submap(s0)
    j = len(first)
    if detour:  # somewhere far away and back: the path between the two passes grows by 2 × detour
        far = SimpleNamespace(index=1, local_pose=mid + [0.0, detour, 0.0], node_indices=[])
        for p in (far.local_pose, ):
            gs.add_node(SimpleNamespace(index=j, timestamp=float(j), timestamp_text=None), p,
                        np.zeros((0, 2)), None, [(far.index, far.local_pose)])
            j += 1
    local = [compose(drift, p) for p in again]
    s3 = _submap(3, segs, again, local)
    for t, p in zip(again, local):
        node(j, t, p, s3)
        j += 1
    gs.add_finished_submap(s3)
    return gs, first, again


def test_a_return_beyond_the_regular_window_is_closed_by_the_wide_search():
    gs, first, again = _global_slam_with_a_return(detour=1000.0)
    wide = [r for r in gs.records if "wide" in r.get("search", "")]
    assert gs.wide_searches >= 1 and wide
    accepted = [r for r in wide if r["accepted"]]
    assert len(accepted) == 2, [r["reason"] for r in wide]
    n0 = len(first) + 1  # the first node of the second pass
    for r in accepted:
        truth = between(first[r["from_scan"]], again[r["to_scan"] - n0])
        d = between(truth, np.array(r["relative_pose"]))
        assert math.hypot(d[0], d[1]) < 0.1 and abs(d[2]) < math.radians(1.0), (r, truth)
    # the regular search, from the drifted estimate, found none of it
    assert not any(r["accepted"] for r in gs.records if "wide" not in r.get("search", ""))


@pytest.mark.parametrize("check", [True, False])
def test_only_matches_searched_from_the_estimate_are_held_against_it(monkeypatch, check):
    """The regular search starts from where the pose graph places the node, and verification holds
    its match against that estimate (``loop_closure.estimate_check``); the wide search's node
    matches start from a coarse submap match, which is no estimate, and are not held against it."""
    import slam2d.backend.global_slam as gsmod
    from slam2d.backend.loop_closure import SubmapMatcher
    from slam2d.config import SlamConfig

    seen = {"wide": set(), "regular": set()}
    inside = []
    match, wide = SubmapMatcher.match, gsmod.GlobalSlam._search_wide

    def spy_match(self, *a, estimate=False, **k):
        seen["wide" if inside else "regular"].add(estimate)
        return match(self, *a, estimate=estimate, **k)

    def spy_wide(self, submap):
        inside.append(1)
        try:
            return wide(self, submap)
        finally:
            inside.pop()

    monkeypatch.setattr(SubmapMatcher, "match", spy_match)
    monkeypatch.setattr(gsmod.GlobalSlam, "_search_wide", spy_wide)
    gs, _, _ = _global_slam_with_a_return(detour=1000.0, cfg=SlamConfig(loop_closure={"estimate_check": check}))
    assert gs.wide_searches >= 1
    assert seen["wide"] == {False}
    assert seen["regular"] == {check}


def test_no_wide_search_where_the_regular_window_covers_the_drift():
    gs, _, _ = _global_slam_with_a_return(detour=0.0)
    assert gs.wide_searches == 0


def test_wide_search_can_be_switched_off(monkeypatch):
    from types import SimpleNamespace

    import slam2d.backend.global_slam as gsmod
    from slam2d.config import SlamConfig

    calls = []
    monkeypatch.setattr(gsmod.GlobalSlam, "_search_wide", lambda self, submap: calls.append(submap.index))
    segs = floor_plan()
    pose = np.array([6.0, 6.0, 0.0])
    for cfg, want in ((SlamConfig(loop_closure={"wide_search": False}), []), (SlamConfig(), [0])):
        gs = gsmod.GlobalSlam(cfg)
        s0 = _submap(0, segs, [pose], [pose])
        gs.add_node(SimpleNamespace(index=0, timestamp=0.0, timestamp_text=None), pose, _scan_points(segs, pose), None,
                    [(0, pose)])
        s0.node_indices.append(0)
        gs.add_finished_submap(s0)
        assert calls == want


def test_coarse_match_finds_nothing_where_the_content_lies_off_the_map():
    """No placement in the window puts the content on observed occupied cells: nothing scores above
    the never-observed value, so there is no match (not a best-of-nothing pose)."""
    segs = floor_plan()
    target = coarse_grid(_grid(segs, [np.array([6.0, 6.0, 0.0])]))
    content = submap_content(_grid(segs, [np.array([14.0, 6.0, 0.0])]))
    centre = np.r_[content.mean(axis=0), 0.0]
    far = np.array([200.0, 200.0, 0.0])  # the window lies wholly outside the older submap
    assert coarse_match(content, centre, far, target, 3.0, math.radians(10.0)) is None
    assert coarse_match(content, centre, centre, target, 3.0, math.radians(10.0)) is not None


def test_a_return_along_a_featureless_corridor_adds_heading_constraints_that_turn_it_back():
    """Two walls 2 m apart and 120 m long, no end in range: the robot maps a stretch, drives 2 × 60 m
    elsewhere, and maps it again on the way back, local SLAM's frame turned by 6° and slid along. The
    wide search finds the corridor, but every node match slides along it (ambiguous, no loop); their
    heading holds, and the heading constraints turn the return back, without a position loop."""
    from slam2d.config import SlamConfig

    segs = np.array([[-60.0, 1.0, 60.0, 1.0], [-60.0, -1.0, 60.0, -1.0]])
    first = [np.array([x, 0.0, 0.0]) for x in np.linspace(-10.0, 10.0, 21)]
    again = [np.array([x, 0.0, math.pi]) for x in np.linspace(9.0, -9.0, 19)]
    first_again = len(first) + 1  # after the node far away
    for enabled in (True, False):
        cfg = SlamConfig()
        cfg.loop_closure.wide_heading_constraints = enabled
        gs, _, _ = _global_slam_with_a_return(60.0, cfg, segs, first, again, np.zeros(3),
                                              np.array([2.5, 0.0, math.radians(6.0)]))
        gs.optimize()
        heading = [r for r in gs.records if "heading_constraint" in r]
        assert not any(r["accepted"] for r in gs.records if r["to_scan"] >= first_again)  # no position loop
        turned = [math.degrees(math.remainder(gs.graph.node_pose(first_again + i)[2] - t[2], 2 * math.pi))
                  for i, t in enumerate(again)]
        s = gs.summary()["loop_closure"]
        if enabled:
            assert heading and all(r["heading_constraint"]["in_final_graph"] for r in heading), gs.records
            assert all(r["reason"].startswith("ambiguous") and not r["in_final_graph"] for r in heading)
            assert s["heading_constraints"] == s["heading_constraints_in_final_graph"] == len(heading)
            assert max(abs(t) for t in turned) < 1.0, turned  # turned back within a degree
        else:
            assert not heading and s["heading_constraints"] == 0
            assert min(abs(t) for t in turned) > 5.0, turned  # still 6° off
