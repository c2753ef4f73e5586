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
from slam2d.mapper import Mapper

from conftest import BUNDLED


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
    gs = GlobalSlam(cfg)
    res = Mapper(cfg, LocalSlam(cfg), None, gs).run(scans)
    gt = np.array([s.ground_truth for s in scans])
    return res, gs, gt


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
