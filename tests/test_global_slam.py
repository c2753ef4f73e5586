"""Pose graph and global SLAM on synthetic data."""
import math

import numpy as np
import pytest

from slam2d.backend.pose_graph import PoseGraph
from slam2d.config import SlamConfig
from slam2d.frontend import LocalSlam
from slam2d.geometry import between, compose
from slam2d.backend.global_slam import GlobalSlam
from slam2d.io.mcap import McapLog
from slam2d.slam import Slam

from conftest import BUNDLED, indeterminate_graph


def square_loop(n=40, side=10.0):
    """Ground-truth poses around a square, ending where it started."""
    per = n // 4
    poses = []
    for s in range(4):
        for i in range(per):
            a = s * math.pi / 2
            x0, y0 = [(0, 0), (side, 0), (side, side), (0, side)][s]
            poses.append((x0 + math.cos(a) * side * i / per, y0 + math.sin(a) * side * i / per, a))
    return np.array(poses)


def test_pose_graph_closes_a_loop_and_drops_a_false_constraint():
    gt = square_loop()
    g = PoseGraph(huber_scale=1.0, max_residual_trans=0.3, max_residual_rot=0.05)
    rng = np.random.default_rng(0)
    # one submap per node (submap k anchored at node k), drifting odometry-like chain
    est = [gt[0]]
    for k in range(1, len(gt)):
        step = between(gt[k - 1], gt[k]) + [0.0, 0.0, 0.02] + rng.normal(0, 0.005, 3)
        est.append(compose(est[-1], step))
    for k, p in enumerate(est):
        g.add_node(k, p)
        if k:
            g.add_intra(k - 1, k, between(est[k - 1], est[k]), np.diag([1e-2, 1e-2, 1e-3]))
    before = np.hypot(*(np.array(est[-1][:2]) - gt[-1][:2]))
    true = {"accepted": True}
    g.add_loop(0, len(gt) - 1, between(gt[0], gt[-1]), [0.02, 0.02, 0.005], true)
    false = {"accepted": True, "in_final_graph": True}
    g.add_loop(5, 25, np.array([3.0, -2.0, 1.0]), [0.02, 0.02, 0.005], false)
    dropped = g.optimize()
    after = np.hypot(*(g.node_pose(len(gt) - 1)[:2] - g.node_pose(0)[:2] - (gt[-1][:2] - gt[0][:2])))
    assert before > 1.0 and after < 0.1
    assert [f.record for f in dropped] == [false] and false["in_final_graph"] is False
    assert len(g.loops) == 1


@pytest.fixture(scope="module")
def sim_run():
    cfg = SlamConfig()
    scans = list(McapLog(BUNDLED))
    slam = Slam(cfg)
    gs = slam.global_slam
    res = slam.run(scans)
    gt = np.array([s.ground_truth for s in scans])
    return res, gs, gt


def test_incremental_pose_graph_agrees_with_batch_and_forgets_removed_loops():
    """iSAM2 fed in three steps (chain, then a true loop, then a false loop later removed) ends where
    batch Levenberg-Marquardt over the final graph ends; the removed loop no longer pulls its nodes."""
    gt = square_loop()
    rng = np.random.default_rng(1)
    est = [gt[0]]
    for k in range(1, len(gt)):
        est.append(compose(est[-1], between(gt[k - 1], gt[k]) + [0.0, 0.0, 0.02] + rng.normal(0, 0.005, 3)))
    graphs = {m: PoseGraph(1.0, 1e3, 1e3, incremental=m) for m in (False, True)}  # residual check off
    for m, g in graphs.items():
        half = len(gt) // 2
        for k, p in enumerate(est):
            g.add_node(k, p)
            if k:
                g.add_intra(k - 1, k, between(est[k - 1], est[k]), np.diag([1e-2, 1e-2, 1e-3]))
            if k == half:
                g.optimize()  # the first half alone
        g.add_loop(0, len(gt) - 1, between(gt[0], gt[-1]), [0.02, 0.02, 0.005], {})
        g.optimize()
        false = g.add_loop(5, 25, np.array([3.0, -2.0, 1.0]), [0.02, 0.02, 0.005], {})
        g.optimize()
        bent = g.node_pose(25).copy()
        g.remove_loop(false, "test")
        g.optimize()
        assert math.hypot(*(g.node_pose(25)[:2] - bent[:2])) > 0.05  # the false loop had bent it; gone now
    ids = range(len(gt))
    a = np.array([graphs[False].node_pose(k) for k in ids])
    b = np.array([graphs[True].node_pose(k) for k in ids])
    assert np.abs(a - b)[:, :2].max() < 2e-3 and np.abs(a - b)[:, 2].max() < 2e-4
    assert math.hypot(*(b[-1][:2] - b[0][:2] - (gt[-1][:2] - gt[0][:2]))) < 0.1  # the true loop closed


def test_an_indeterminate_isam2_update_falls_back_to_levenberg_marquardt(caplog):
    """A stretch of nodes held a thousand million times tighter to each other than to the rest (the
    information spans more than floating point keeps): iSAM2's undamped elimination calls the
    system indeterminate (a real no-odometry run hit it and stopped with gtsam's traceback). The
    graph is then solved by Levenberg-Marquardt, as the batch graph is, from then on too; loops
    added later still close."""
    def build(incremental):
        return indeterminate_graph(PoseGraph(1.0, 1e3, 1e3, incremental=incremental))

    plain = build(True)
    with pytest.raises(RuntimeError, match="Indeterminate"):
        plain._update_isam()  # what iSAM2 itself does with it
    batch, inc = build(False), build(True)
    with caplog.at_level("WARNING"):
        batch.optimize()
        inc.optimize()
    assert inc.isam_failed_at is not None and not inc.incremental and "indeterminate" in caplog.text
    for g in (batch, inc):  # a loop added afterwards: both solve it the same way
        g.add_node(4, [4.5, 0.3, 0.0])
        g.add_intra(3, 4, [1, 0, 0], np.diag([1e-2, 1e-2, 1e-3]))
        g.add_loop(0, 4, [4.0, 0.0, 0.0], [0.02, 0.02, 0.005], {})
        g.optimize()
    for j in range(5):
        np.testing.assert_allclose(inc.node_pose(j), batch.node_pose(j), atol=1e-6)
    assert abs(inc.node_pose(2)[0] - 2.0) < 1e-6 and abs(inc.node_pose(4)[0] - 4.0) < 0.05


def test_global_slam_on_the_simulated_loops(sim_run):
    res, gs, gt = sim_run
    s = gs.summary()["loop_closure"]
    assert s["accepted"] > 10 and s["in_final_graph"] > 10
    # every constraint left in the final graph agrees with the ground truth (0.3 m / 2°)
    for r in gs.records:
        if r.get("in_final_graph"):
            e = between(between(gt[r["from_scan"]], gt[r["to_scan"]]), np.array(r["relative_pose"]))
            assert math.hypot(e[0], e[1]) < 0.3 and abs(math.degrees(e[2])) < 2.0
    # the trajectory is consistent with the ground truth over long spans (the ring closes)
    k = 400
    e = between(between(gt[:-k], gt[k:]), between(res.poses[:-k], res.poses[k:]))
    assert np.hypot(e[:, 0], e[:, 1]).mean() < 0.15


def test_summary_reports_ate_against_ground_truth(tmp_path):
    import json

    from slam2d.cli import main

    out = tmp_path / "run"
    assert main(["run", str(BUNDLED), "--out", str(out), "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["ate_vs_ground_truth"]["trans_m"]["rmse"] < 0.1
    assert s["loop_closure"]["in_final_graph"] > 10
    local = tmp_path / "local"
    assert main(["run", str(BUNDLED), "--out", str(local), "--no-progress", "--odometry-only"]) == 0
    odo = json.loads((local / "summary.json").read_text())
    assert odo["ate_vs_ground_truth"]["trans_m"]["rmse"] > 5 * s["ate_vs_ground_truth"]["trans_m"]["rmse"]


def test_branch_and_bound_equals_exhaustive_on_a_real_submap():
    """A finished submap from the Intel log; a node's scan searched by B&B and exhaustively."""
    import itertools

    from conftest import dataset
    from slam2d.backend.loop_closure import SubmapMatcher, loop_points
    from slam2d.io.carmen import CarmenLog
    from slam2d.matching.search import PrecomputationStack, SearchParameters, branch_and_bound, exhaustive
    from slam2d.range_data import range_data

    cfg = SlamConfig()
    tracker = LocalSlam(cfg)
    scans = list(itertools.islice(CarmenLog(dataset("intel")), 1200))
    results = [tracker.add_scan(s) for s in scans]
    assert tracker.finished_submaps, "no submap finished"
    sub = tracker.finished_submaps[0]
    m = SubmapMatcher(sub, 4)
    rng = np.random.default_rng(0)
    for j in rng.choice(sub.node_indices, 3, replace=False):
        pts = loop_points(range_data(scans[j], cfg.range_filter).hits, 0.05)
        initial = results[j].local_pose + [0.2, -0.15, 0.03]
        params = SearchParameters.make(0.6, 0.08, m.grid.resolution, pts)
        cells = m.grid.cells(pts, initial, params.angles)
        ex = exhaustive(m.grid, cells, params.linear_cells)
        a, dx, dy, s = branch_and_bound(PrecomputationStack(m.grid, 4), cells, params.linear_cells, 0.0)
        w = params.linear_cells
        assert s == pytest.approx(float(ex.max()), rel=1e-6)
        assert ex[a, dy + w, dx + w] == pytest.approx(s, rel=1e-6)
        # and the best pose is the node's own pose (within a cell and an angular step)
        best = initial + [dx * m.grid.resolution, dy * m.grid.resolution, params.angles[a]]
        assert np.hypot(*(best - results[j].local_pose)[:2]) <= 0.075


def test_final_refinement_pulls_perturbed_scans_onto_the_map():
    """Scans whose poses are a few cm / tenths of a degree off move back toward the truth; exact ones stay."""
    from test_matchers import scan_points
    from slam2d.backend.final_refinement import refine_trajectory
    from slam2d.grid.probability_grid import ProbabilityGrid

    rng = np.random.default_rng(11)
    center = np.array([6.0, 1.25, 0.0])
    truths = [center + [rng.uniform(-1, 1), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)] for _ in range(30)]
    points = [scan_points(p, 0.01, rng) for p in truths]
    grid = ProbabilityGrid(0.05)
    for p, pts in zip(truths, points):
        grid.insert(p[:2], compose(p, np.c_[pts, np.zeros(len(pts))])[:, :2])
    truths = np.array(truths)
    noisy = truths + np.c_[rng.uniform(-0.03, 0.03, (30, 2)), rng.uniform(-0.006, 0.006, 30)]
    points_or_none = points[:-1] + [None]  # a scan without points keeps its pose
    out = refine_trajectory(grid, noisy, points_or_none, translation_weight=1.0, rotation_weight=3.0)
    before = np.hypot(*(noisy - truths)[:-1, :2].T)
    after = np.hypot(*(out - truths)[:-1, :2].T)
    assert after.mean() < 0.5 * before.mean()
    assert np.abs(out - truths)[:-1, 2].mean() < np.abs(noisy - truths)[:-1, 2].mean()
    np.testing.assert_allclose(out[-1], noisy[-1], atol=1e-12)
    exact = refine_trajectory(grid, truths, points, 1.0, 3.0)
    assert np.hypot(*(exact - truths)[:, :2].T).max() < 0.02


def test_nodes_are_sampled_per_count_or_per_distance():
    """Dense (nodes 1 cm apart): every 5th node; sparse (1 m apart): every node, as densely per metre."""
    from slam2d.backend.global_slam import GlobalSlam
    from slam2d.config import config_from_dict

    cfg = config_from_dict({"loop_closure": {"sample_every_n_nodes": 5}, "motion_filter": {"max_distance": 0.2}})
    dense, sparse = GlobalSlam(cfg), GlobalSlam(cfg)
    picked_dense = [j for j in range(20) if dense._sample(j, np.array([0.01 * j, 0.0, 0.0]))]
    picked_sparse = [j for j in range(20) if sparse._sample(j, np.array([1.0 * j, 0.0, 0.0]))]
    assert picked_dense == [4, 9, 14, 19]
    assert picked_sparse == list(range(1, 20))


def test_loop_score_threshold_follows_how_often_a_submap_was_observed():
    """A submap whose own nodes score low at their own poses (each wall seen by a few scans) gets a
    lower loop threshold: its own scans re-scored must pass it, and a scan placed 0.7 m and 20° off must not."""
    from slam2d.backend.global_slam import min_score_for
    from slam2d.backend.loop_closure import SubmapMatcher, loop_points
    from slam2d.io.source import open_source

    cfg = SlamConfig()
    lc = cfg.loop_closure
    assert min_score_for(lc, 0.9) == lc.min_score and min_score_for(lc, float("nan")) == lc.min_score
    assert min_score_for(lc, 0.6) == pytest.approx(lc.min_relative_score * 0.6)
    local = LocalSlam(cfg)
    kept = {}
    for scan in open_source(BUNDLED):
        r = local.add_scan(scan)
        if r.inserted:
            kept[scan.index] = (loop_points(r.range_data.hits, lc.voxel_filter_size), r.local_pose)
        if local.finished_submaps:
            break
    sub = local.finished_submaps[0]
    m = SubmapMatcher(sub, lc.branch_depth)
    own = [kept[j] for j in sub.node_indices]
    s = m.self_score(own)
    threshold = min_score_for(lc, s)
    j = sub.node_indices[len(sub.node_indices) // 2]
    pts, pose = kept[j]
    found = m.match(pts, pose, 0.3, math.radians(3), threshold, (20.0, 10.0, 1.0, 20))
    assert found is not None and found.reason is None
    assert np.hypot(*(found.pose[:2] - pose[:2])) < 0.05
    off = m.self_score([(pts, compose(pose, [0.5, 0.5, math.radians(20.0)]))])
    assert off < threshold


def test_a_nodes_searches_run_cached_stacks_first_with_the_same_outcome(monkeypatch):
    """``_search_node`` searches the submaps whose stacks are cached first (fewer rebuilds when the
    cache holds fewer stacks than a node searches) and commits nearest first: the records, the
    constraints and the trajectory are those of searching nearest first. The cache's floor of one
    node's working set (the default) rebuilds fewer still, with the same outcome."""
    import slam2d.backend.global_slam as gsm
    from slam2d.backend.loop_closure import StackCache

    scans = list(McapLog(BUNDLED))

    def run(cached_first: bool, floor: bool):
        # room for about two stacks: a node searches up to three submaps
        monkeypatch.setattr(gsm, "STACK_CACHE_BYTES", 2 * 1024 * 1024)
        if not floor:
            monkeypatch.setattr(gsm, "StackCache", lambda max_bytes, min_stacks=1: StackCache(max_bytes, 1))
        if not cached_first:
            monkeypatch.setattr(StackCache, "holds", lambda self, key: False)
        slam = Slam(SlamConfig())
        res = slam.run(scans)
        monkeypatch.undo()
        recs = [{k: v for k, v in r.items() if k != "search_ms"} for r in slam.global_slam.records]
        return res.poses, recs, slam.global_slam.stacks.builds

    poses_a, recs_a, builds_a = run(True, floor=False)
    poses_b, recs_b, builds_b = run(False, floor=False)
    poses_c, recs_c, builds_c = run(True, floor=True)
    assert recs_a == recs_b == recs_c and np.array_equal(poses_a, poses_b) and np.array_equal(poses_a, poses_c)
    assert builds_c < builds_a < builds_b


def test_an_unsampled_nodes_loop_points_go_once_its_submaps_are_finished(monkeypatch):
    """Global SLAM keeps a node's loop points while a search can read them: a sampled node's for good,
    any other node's until every submap it lies in is finished (``_release_points``). Which nodes
    lose them is exactly that set, and the run's records and poses are those of a run that keeps
    every node's points."""
    scans = list(McapLog(BUNDLED))

    def run(release: bool):
        cfg = SlamConfig()
        cfg.loop_closure.background = False
        if not release:
            monkeypatch.setattr(GlobalSlam, "_release_points", lambda self, submap: None)
        slam = Slam(cfg)
        gs = slam.global_slam
        without = []  # per finished submap, after global SLAM took it: the nodes without points
        add = gs.add_finished_submap

        def add_and_look(sub):
            add(sub)
            without.append({j for j, n in gs.nodes.items() if "points" not in n})

        gs.add_finished_submap = add_and_look
        submaps = slam.tracker.all_submaps
        res = slam.run(scans)
        monkeypatch.undo()
        recs = [{k: v for k, v in r.items() if k != "search_ms"} for r in gs.records]
        return res.poses, recs, gs, without, submaps()

    poses_a, recs_a, gs, without, submaps = run(True)
    poses_b, recs_b, _, kept, _ = run(False)
    assert recs_a == recs_b and np.array_equal(poses_a, poses_b)
    assert not any(kept[-1])
    finished = set(gs.matchers)
    holders: dict[int, set] = {}
    for sub in submaps:
        for j in sub.node_indices:
            holders.setdefault(j, set()).add(sub.index)
    expected = {j for j in gs.nodes if j not in gs._sampled_at and holders.get(j) and holders[j] <= finished}
    assert without[-1] == expected and len(expected) > len(gs.nodes) // 2
    assert all("points" in gs.nodes[j] for j in gs._sampled_at)
    # released as the submaps finish, not only at the end
    assert 0 < len(without[len(without) // 2]) < len(without[-1])


def test_local_match_covariances_are_computed_on_global_slam_s_thread(monkeypatch):
    """``add_scan`` hands global SLAM the local match itself, whose covariance the worker computes:
    none on the caller's thread, and the same graph as covariances computed up front; with no
    room for score volumes waiting in the worker's queue, every covariance is computed up front."""
    import threading

    from slam2d.matching.real_time import MatchResult

    scans = list(McapLog(BUNDLED))
    lazy = MatchResult.covariance
    threads = []

    def recorded(self):
        threads.append(threading.current_thread().name)
        return lazy.fget(self)

    monkeypatch.setattr(MatchResult, "covariance", property(recorded))
    slam = Slam(SlamConfig())
    res = slam.run(scans)
    assert threads and set(threads) == {"slam2d-global"} and slam._handed_over == 0

    import slam2d.slam as slam_module

    threads.clear()
    monkeypatch.setattr(slam_module, "HANDOVER_BYTES", 0)
    bounded = Slam(SlamConfig())
    res_bounded = bounded.run(scans)
    assert threads and set(threads) == {threading.main_thread().name}
    assert np.array_equal(res.poses, res_bounded.poses)
    monkeypatch.undo()

    eager = Slam(SlamConfig())
    submit = eager._global

    def up_front(fn, *args):  # the covariance computed on the caller's thread, as before
        if fn.__name__ == "add_node" and args[3] is not None and not isinstance(args[3], np.ndarray):
            args = args[:3] + (args[3].covariance,) + args[4:]
        submit(fn, *args)

    eager._global = up_front
    res_eager = eager.run(scans)
    assert sum(r["in_final_graph"] for r in slam.global_slam.records) > 10  # the covariances weigh in a solve
    assert np.array_equal(res.poses, res_eager.poses)
    strip = lambda recs: [{k: v for k, v in r.items() if k != "search_ms"} for r in recs]  # noqa: E731
    assert strip(slam.global_slam.records) == strip(eager.global_slam.records)


def test_a_node_near_a_submaps_track_searches_it_when_no_centre_is_near(monkeypatch):
    """A submap built along a corridor sees far down it, and its content centre lies far from where
    the robot stood. A node back in that corridor with no submap whose centre is near is matched
    against the submaps built from poses near it, nearest pose first; where centres are near, they
    decide alone; the newest submaps stay with local SLAM."""
    from types import SimpleNamespace

    cfg = SlamConfig()
    assert cfg.loop_closure.max_submaps_per_node == 3 and cfg.loop_closure.exclude_recent_submaps == 2
    gs = GlobalSlam(cfg)
    tracks = {0: (0.0, 0.0), 1: (0.0, 10.0), 2: (0.0, 20.0), 3: (0.0, 30.0), 4: (0.0, 0.2), 5: (0.0, 0.3)}
    for k, (x0, y) in tracks.items():  # five nodes a metre apart along x
        idx = list(range(10 * k, 10 * k + 5))
        for i, j in enumerate(idx):
            gs.nodes[j] = {"local": np.array([x0 + i, y, 0.0])}
        gs.matchers[k] = SimpleNamespace(submap=SimpleNamespace(node_indices=idx))
    node = np.array([0.0, 0.5, 0.0])

    def centres(c):
        monkeypatch.setattr(gs, "_submap_centres", lambda: (np.arange(6), np.array([[x, y, 0.0] for x, y in c])))

    # submap 0's centre 30 m down the corridor, submap 1's 9.7 m away, the others far; 4 and 5 are newest
    centres([(30, 0), (2, 10), (2, 20), (2, 30), (0, 0.2), (0, 0.3)])
    assert gs._candidate_submaps(node) == [1]
    # three centres near: they are the node's submaps, nearest first
    centres([(30, 0), (2, 10), (0, 4), (1, -6), (0, 0.2), (0, 0.3)])
    assert gs._candidate_submaps(node) == [2, 3, 1]
    # a node of the past (the final search), inserted into submaps 1 and 2: the submaps within two
    # of its own are local SLAM's on either side, later ones are fair game
    assert gs._candidate_submaps(node, own=(1, 2, 0)) == [5]
    assert gs._candidate_submaps(node, own=(4, 5, 0)) == [1]
    assert gs._candidate_submaps(node, own=(5, 5, 0)) == [2, 1]
    # no centre near: the nearest tracks decide (submap 1's at 9.5 m; 2's and 3's beyond reach)
    centres([(30, 0), (30, 10), (30, 20), (30, 30), (0, 0.2), (0, 0.3)])
    assert gs._candidate_submaps(node) == [0, 1]


def test_a_fresh_start_of_local_slam_hangs_on_a_loose_step_and_is_searched_against_the_old_submaps():
    """Local SLAM loses track (a 90° jump no prediction knows of, ``test_frontend._teleported``) and
    starts new submaps at the forced scan. No submap then holds both that node and the one before, so
    the step between them is the only link: a constraint as loose as local SLAM's doubt about the step
    (the recovery window), without which the graph would fall apart. And the submaps finished by the
    fresh start, though the newest, are searched at once: local SLAM no longer matches against them."""
    import gtsam
    from conftest import BUNDLED
    from slam2d.config import config_from_dict
    from slam2d.io.source import open_source
    from test_frontend import _teleported

    from slam2d.observer import Observer

    class Qualities(Observer):
        def __init__(self):
            self.forced = []

        def on_scan(self, scan, result):
            if result.quality == "forced":
                self.forced.append(scan.index)

    scans = _teleported(list(open_source(BUNDLED))[:330], 170, 25)
    seen = Qualities()
    slam = Slam(config_from_dict({"loop_closure": {"background": False}}), observer=seen)
    for s in scans:
        slam.add_scan(s)
    gs = slam.global_slam
    (j,) = seen.forced
    prev = gs.node_order[gs.node_order.index(j) - 1]

    def submaps_of(n):  # the finished submaps holding node n, and those it started
        return {k for k, m in gs.matchers.items() if n in m.submap.node_indices} | \
            {k for k, a in gs.submap_anchor.items() if a == n}

    assert submaps_of(j) and submaps_of(prev) and not submaps_of(j) & submaps_of(prev)
    assert gs._segment_start == min(submaps_of(j))
    g = gs.graph.graph
    steps = [g.at(i) for i in range(g.size()) if g.exists(i)
             and set(g.at(i).keys()) == {gtsam.symbol("n", prev), gtsam.symbol("n", j)}]
    assert len(steps) == 1
    # it is the only link, so GNC's screen keeps it; a step that a submap spans it leaves out
    at = [i for i in range(g.size()) if g.exists(i) and set(g.at(i).keys()) == {gtsam.symbol("n", prev), gtsam.symbol("n", j)}]
    assert at[0] not in gs.graph._unscreened and len(gs.graph._unscreened) >= len(gs.node_order) - 3
    rt = slam.config.real_time_matcher
    sigma = np.sqrt(np.diag(steps[0].noiseModel().covariance()))
    assert sigma[2] >= math.radians(rt.recovery_angular_window_deg) and sigma[0] >= rt.recovery_linear_window
    # the nodes after it were matched against the two submaps the fresh start finished (the newest)
    old = submaps_of(prev)
    assert max(old) == max(gs.matchers)
    assert any(r["submap"] in old and r["to_scan"] > j for r in gs.records)
    res = slam.finish()  # the graph solves: every node hangs on the rest
    assert np.all(np.isfinite(res.poses))


def test_a_fresh_start_no_loop_ties_back_is_reported_by_the_health_check():
    """Local SLAM loses track at a 90° jump (``test_frontend._teleported``) and no loop closure ties the
    stretch after it to the one before within the run: the map is broken, its parts 90° apart, but
    no revisit shows it, so only the untied fresh start can say so. The same scans without the jump
    have no fresh start and pass."""
    from conftest import BUNDLED
    from slam2d.io.source import open_source
    from test_frontend import _teleported

    plain = list(open_source(BUNDLED))[:400]
    jumped = _teleported(plain, 170, 25)
    res = Slam().run(jumped)
    lc, health = res.summary["loop_closure"], res.summary["health"]
    assert res.summary["ate_vs_ground_truth"]["trans_m"]["rmse"] > 1.0  # really broken
    (h,) = lc["fresh_starts"]
    assert lc["fresh_starts_untied"] == [h] and health["fresh_starts_untied"] == [h]
    assert health["status"] != "OK" and any(f"lost track at scan {h}" in r for r in health["reasons"])
    ok = Slam().run(plain).summary
    assert ok["loop_closure"]["fresh_starts"] == [] and ok["health"]["status"] == "OK"


def test_a_loop_ties_a_fresh_start_when_it_spans_it():
    """``untied_fresh_starts``: a fresh start is tied by a loop in the graph whose two nodes lie on
    either side of it (the node itself counts as after), whichever end is the anchor; a heading
    constraint ties no position, so it ties none."""
    from types import SimpleNamespace

    gs = GlobalSlam(SlamConfig())
    gs.fresh_starts = [100, 200, 300]
    gs.graph = SimpleNamespace(loops=[SimpleNamespace(anchor=250, node=150, heading_only=False),   # spans 200
                                      SimpleNamespace(anchor=90, node=100, heading_only=False),    # ends at 100: spans it
                                      SimpleNamespace(anchor=310, node=390, heading_only=False),   # after 300 only
                                      SimpleNamespace(anchor=280, node=320, heading_only=True)])   # spans 300: heading only
    assert gs.untied_fresh_starts() == [300]
    gs.graph = SimpleNamespace(loops=[])
    assert gs.untied_fresh_starts() == [100, 200, 300]


def test_auto_scores_weakly_observed_submaps_on_their_likelihood_field():
    """``loop_closure.score_grid: auto``: a finished submap whose own nodes score low enough on its
    probabilities that ``min_relative_score`` lowers its threshold is scored on its likelihood field,
    every other on its probabilities. The bundled log inserted every 1.5 m gives both kinds; the
    rule holds for each submap, the summary counts the field's, submaps scored on it hold loops of
    the final graph, and every one of them agrees with the simulator's ground truth (0.3 m / 2°)."""
    from slam2d.backend.global_slam import min_score_for
    from slam2d.backend.loop_closure import probability_self_score
    from slam2d.eval.loops import agrees

    cfg = SlamConfig()
    cfg.loop_closure.background = False
    cfg.motion_filter.max_distance = 1.5
    lc = cfg.loop_closure
    assert lc.score_grid == "auto"
    scans = list(McapLog(BUNDLED))
    slam = Slam(cfg)
    gs = slam.global_slam
    seen = []
    add = gs.add_finished_submap

    def add_and_check(sub):
        own = [(gs.nodes[j]["points"], gs.nodes[j]["local"]) for j in sub.node_indices if j in gs.nodes]
        score = probability_self_score(sub, own)  # before the grid is packed, as global SLAM reads it
        add(sub)
        seen.append((min_score_for(lc, score) < lc.min_score, gs.matchers[sub.index].scores_field))

    gs.add_finished_submap = add_and_check
    result = slam.run(scans)
    assert all(weak == field for weak, field in seen), seen
    fields = sum(field for _, field in seen)
    assert 0 < fields < len(seen)  # both kinds
    assert result.summary["loop_closure"]["submaps_scored_on_field"] == fields
    gt = np.array([s.ground_truth for s in scans])
    final = [r for r in gs.records if r["in_final_graph"]]
    assert final and all(agrees(gt, r, 0.3, 2.0) for r in final)
    on_field = {k for k, m in gs.matchers.items() if m.scores_field}
    assert any(r["submap"] in on_field for r in final)  # the field's matches close loops too
    # constraints.jsonl says which grid each search scored
    assert all(r["score_grid"] == ("likelihood_field" if r["submap"] in on_field else "probability") for r in gs.records)


def _return_corrected_later(final_search: bool, correct: bool, budget=None):
    """The corridor mapped twice (``test_wide_search._global_slam_with_a_return``), the second pass
    5 m and 40° off in local SLAM's frame, beyond the regular window, and the wide search off: no
    search closes the loop while the robot is there. Then (``correct``) a loop closed elsewhere,
    later, puts the second pass where it belongs: a constraint with the true relative pose between
    a node of each pass."""
    from test_wide_search import _global_slam_with_a_return

    cfg = SlamConfig(loop_closure={"wide_search": False, "final_search": final_search})
    gs, first, again = _global_slam_with_a_return(detour=1000.0, cfg=cfg)
    n0 = len(first) + 1  # the first node of the second pass
    assert not any(r["accepted"] for r in gs.records)
    if correct:
        a, b = 11, n0 + 8
        gs.graph.add_loop(a, b, between(first[a], again[b - n0]), np.diag([1e-4, 1e-4, 1e-6]),
                          {"submap": 0, "from_scan": a, "to_scan": b, "accepted": True, "in_final_graph": True})
    searched = len(gs.records)
    assert gs.searches == searched
    if budget is not None:
        gs.searches = budget  # as if the run had made only this many searches
    gs.final_search()
    return gs, first, again, n0, gs.records[searched:]


def test_the_final_search_closes_a_loop_a_later_correction_brought_within_reach():
    """Once a later loop has moved the second pass by more than the window its nodes were searched in,
    the final search matches them against the submap now near them: the loops it accepts are the
    true ones. Nodes that did not move are not searched again, and the search can be switched off."""
    gs, first, again, n0, new = _return_corrected_later(final_search=True, correct=True)
    assert new and all(r["search"] == "final" for r in new)
    accepted = [r for r in new if r["accepted"]]
    assert len(accepted) >= 3, [r["reason"] for r in new]
    assert gs.final_searches == len(new) and gs.final_accepted >= len(accepted) > 0
    for r in accepted:
        assert r["submap"] == 0 and r["to_scan"] >= n0  # second-pass nodes, against the first pass's submap
        truth = between(first[r["from_scan"]], again[r["to_scan"] - n0])
        d = between(truth, np.array(r["relative_pose"]))
        assert math.hypot(d[0], d[1]) < 0.1 and abs(d[2]) < math.radians(1.0), (r, truth)
    # the first pass did not move: none of its nodes was searched again
    assert all(r["to_scan"] >= n0 for r in new)
    # nothing moved: nothing is stale
    gs, *_, new = _return_corrected_later(final_search=True, correct=False)
    assert new == [] and gs.final_searches == 0
    # switched off
    gs, *_, new = _return_corrected_later(final_search=False, correct=True)
    assert new == [] and gs.final_searches == 0


def test_the_final_search_makes_no_more_searches_than_the_run_made_the_most_stale_first():
    """A run whose every stretch a late loop moved would be searched all over again at the end: the
    final search is bounded by the searches the run made, and spends them on the nodes that moved
    farthest beyond their windows."""
    gs, *_ = _return_corrected_later(final_search=True, correct=True)
    unbounded = gs.final_searches
    gs, *_, new = _return_corrected_later(final_search=True, correct=True, budget=3)
    assert unbounded > 3 and gs.final_searches == len(new) == 3
    # the three it searched are the three most stale pairs of its first round
    gs0, *_ = _return_corrected_later(final_search=False, correct=True)
    gs0.optimize()
    stale = gs0._stale_pairs()
    assert len(stale) > 3
    top = sorted(stale, key=lambda t: (-t[0], t[1], t[2]))[:3]
    assert {(r["to_scan"], r["submap"]) for r in new} == {(j, k) for _, j, k in top}


def test_a_loop_bends_the_chain_instead_of_pulling_its_end_node_away_from_the_nodes_beside_it():
    """A node tied loosely to its submap (a weak match: no covariance, σ of the whole window) that a
    loop constraint pulls 0.3 m sideways: local SLAM's step to the nodes beside it, which were matched
    against the same submap, holds it in the chain, so the chain bends and no step of the solution
    differs from local SLAM's by more than a third of the pull. (Without the steps the node alone
    jumped: fr-clinic's trajectory zigzagged by 0.4 m between consecutive scans where loops ended.)"""
    from types import SimpleNamespace

    gs = GlobalSlam(SlamConfig())
    local = [np.array([0.2 * j, 0.0, 0.0]) for j in range(41)]
    for j, p in enumerate(local):
        cov = None if 12 <= j <= 28 else np.diag([1e-4, 1e-4, 1e-6])  # weak matches in the middle
        gs.add_node(SimpleNamespace(index=j, timestamp=float(j), timestamp_text=None), p, np.zeros((0, 2)), cov,
                    [(0, local[0])])
    pulled = local[20] + [0.0, 0.3, 0.0]
    gs.graph.add_loop(0, 20, between(local[0], pulled), [0.02, 0.02, 0.005], {"accepted": True})
    gs.graph.optimize(batch=True)
    poses = [gs.graph.node_pose(j) for j in range(41)]
    assert poses[20][1] > 0.1  # the loop does move the node: the comparison below means something
    worst = max(np.hypot(*(between(poses[j - 1], poses[j]) - between(local[j - 1], local[j]))[:2])
                for j in range(1, 41))
    assert worst < 0.1, worst
