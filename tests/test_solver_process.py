"""The pose graph solved in a child process gives the in-process graph's numbers exactly."""
import math

import numpy as np
import pytest

from slam2d.backend.pose_graph import PoseGraph
from slam2d.backend.solver_process import RemotePoseGraph, SolverError
from slam2d.geometry import between, compose

from conftest import indeterminate_graph


def _trajectory(n=60, seed=3):
    """A noisy walk around a square (returns to its start) and its noisy odometry estimate."""
    rng = np.random.default_rng(seed)
    side = n // 4
    gt = [np.zeros(3)]
    for k in range(1, n):
        turn = math.pi / 2 if k % side == 0 else 0.0
        gt.append(compose(gt[-1], [0.5, 0.0, turn]))
    est = [gt[0]]
    for k in range(1, n):
        est.append(compose(est[-1], between(gt[k - 1], gt[k]) + [0.0, 0.0, 0.015] + rng.normal(0, 0.01, 3)))
    return np.array(gt), np.array(est)


def _feed(g, gt, est, rng):
    """Chain, solves along the way, true and false loops, a removal, GNC: what global SLAM does."""
    out = []
    n = len(gt)
    false = None
    for k, p in enumerate(est):
        g.add_node(k, p)
        if k:
            cov = np.diag([1e-2, 2e-2, 1e-3]) + 1e-3 * np.eye(3)
            g.add_intra(k - 1, k, between(est[k - 1], est[k]), cov)
        if k and k % 15 == 0:
            g.add_loop(0, k, between(gt[0], gt[k]) + rng.normal(0, 0.01, 3), [0.05, 0.05, 0.01], {})
            if k == 30:
                false = g.add_loop(3, k, np.array([4.0, -2.0, 1.0]), np.diag([4e-4, 4e-4, 1e-4]), {})
            out.append(("opt", [f.record.get("reason") for f in g.optimize()]))
    g.add_loop(0, n - 1, between(gt[0], gt[-1]), [0.02, 0.02, 0.005], {})
    out.append(("residual check dropped the false loop", false not in g.loops))
    g.remove_loop(g.add_loop(10, n - 5, np.array([2.0, 2.0, 0.5]), [0.02, 0.02, 0.005], {}), "removed by the caller")
    out.append(("gnc", [f.record.get("reason") for f in g.gnc_prune()]))
    out.append(("final", [f.record.get("reason") for f in g.optimize(batch=True)]))
    return out


@pytest.mark.parametrize("incremental", [False, True])
def test_remote_graph_gives_the_in_process_numbers_exactly(incremental):
    gt, est = _trajectory()
    local = PoseGraph(1.0, 0.3, 0.05, incremental=incremental)
    remote = RemotePoseGraph(1.0, 0.3, 0.05, incremental=incremental)
    try:
        a = _feed(local, gt, est, np.random.default_rng(5))
        b = _feed(remote, gt, est, np.random.default_rng(5))
        assert ("residual check dropped the false loop", True) in a
        assert a == b  # the same loops dropped, for the same reasons, at the same solves
        ids_a, poses_a = local.all_node_poses()
        ids_b, poses_b = remote.all_node_poses()
        assert np.array_equal(ids_a, ids_b) and np.array_equal(poses_a, poses_b)  # bit for bit
        assert [f.node for f in local.loops] == [f.node for f in remote.loops]
        assert [(f.node, f.record["reason"]) for f in local.removed] == [(f.node, f.record["reason"]) for f in remote.removed]
        assert local.iterations == remote.iterations
        # the closed square: the last node is back near the first
        assert math.hypot(*(poses_b[-1][:2] - poses_b[0][:2] - (gt[-1][:2] - gt[0][:2]))) < 0.2
    finally:
        remote.close()
    assert remote._proc.poll() is not None  # the child is gone
    assert remote.peak_rss_mb > 0


def test_an_unsolved_node_reads_back_as_gtsam_stores_it():
    """Before any solve, a node's estimate is what an in-process graph would return for it."""
    local, remote = PoseGraph(), RemotePoseGraph()
    try:
        for j, p in enumerate([[1.0, 2.0, 3.14159], [0.1, -0.2, -3.0], [5.0, 5.0, 7.0]]):
            local.add_node(j, p)
            remote.add_node(j, p)
            assert np.array_equal(local.node_pose(j), remote.node_pose(j))
    finally:
        remote.close()


def test_a_solver_failure_is_raised_not_hung():
    g = RemotePoseGraph()
    try:
        g.add_node(0, [0.0, 0.0, 0.0])
        g.add_intra(0, 7, [1.0, 0.0, 0.0], np.eye(3) * 1e-2)  # node 7 was never added
        with pytest.raises(SolverError, match="pose-graph solver"):
            g.optimize()
    finally:
        g.close()


def test_the_solver_process_solves_an_indeterminate_graph_and_says_so_on_stderr(capfd):
    """The graph iSAM2 calls indeterminate (``test_global_slam``'s) solved in the child process: no
    SolverError, the in-process batch numbers, and the fallback's warning on the caller's stderr in
    the CLI's form."""
    def build(g):
        indeterminate_graph(g).optimize()
        return g

    remote = build(RemotePoseGraph(1.0, 1e3, 1e3, incremental=True))
    local = build(PoseGraph(1.0, 1e3, 1e3, incremental=False))
    try:
        for j in range(4):
            np.testing.assert_allclose(remote.node_pose(j), local.node_pose(j), atol=1e-9)
    finally:
        remote.close()
    err = capfd.readouterr().err
    assert "slam2d: WARNING: pose graph: iSAM2 found the system indeterminate near n" in err


@pytest.mark.parametrize("remote", [False, True])
def test_the_residual_check_spares_the_loops_it_is_told_to_and_only_those(remote):
    """A true loop the stiff chain cannot follow keeps a large residual: the check removes it unless
    it is exempt (``consistency.confirmed``); a false loop in the same graph goes either way. The
    exempt ids are the caller's loop ids, in the child process too."""
    gt, est = _trajectory()
    n = len(gt)
    outcomes = []
    for exempt in (False, True):
        g = (RemotePoseGraph if remote else PoseGraph)(1.0, 0.3, 0.05)
        try:
            for k, p in enumerate(est):
                g.add_node(k, p)
                if k:  # a chain far stiffer than its drift: it will not bend to the loop
                    g.add_intra(k - 1, k, between(est[k - 1], est[k]), np.diag([1e-8, 1e-8, 1e-9]))
            true = g.add_loop(0, n - 1, between(gt[0], gt[-1]), [0.02, 0.02, 0.005], {})
            false = g.add_loop(3, 30, np.array([4.0, -2.0, 1.0]), [0.02, 0.02, 0.005], {})
            g.optimize(exempt=[true.index] if exempt else [])
            outcomes.append((true in g.loops, false in g.loops))
        finally:
            if remote:
                g.close()
    assert outcomes == [(False, False), (True, False)]
