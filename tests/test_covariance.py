"""Node-in-submap covariances: frame, truncation, unmatched scans (issue 12, defect 2)."""
import math

import gtsam
import numpy as np

from slam2d.backend.global_slam import node_frame_covariance
from slam2d.backend.pose_graph import PoseGraph
from slam2d.config import SlamConfig
from slam2d.backend.global_slam import GlobalSlam
from slam2d.geometry import between, compose
from slam2d.grid.probability_grid import ProbabilityGrid
from slam2d.io.simulator import raycast
from slam2d.matching.real_time import RealTimeCorrelativeScanMatcher, unmatched_covariance
from slam2d.matching.search import MatchGrid
from slam2d.types import Scan

ANGLES = -math.pi + 2 * math.pi / 360 * np.arange(360)


def corridor(phi, length=40.0, width=2.0):
    """Two parallel walls along direction ``phi`` through the origin (ends far out of range)."""
    d = np.array([math.cos(phi), math.sin(phi)])
    n = np.array([-d[1], d[0]])
    a, b = -0.5 * length * d, 0.5 * length * d
    off = 0.5 * width * n
    return np.array([[*(a + off), *(b + off)], [*(a - off), *(b - off)]])


def points(segs, pose, max_range=8.0):
    r = raycast(segs, pose[:2], ANGLES + pose[2], max_range)
    ok = np.isfinite(r)
    return np.stack([r[ok] * np.cos(ANGLES[ok]), r[ok] * np.sin(ANGLES[ok])], axis=1)


def corridor_grid(segs, phi):
    g = ProbabilityGrid(0.05, field_sigma=0.1)
    d = np.array([math.cos(phi), math.sin(phi)])
    for s in np.linspace(-4, 4, 17):
        p = np.array([*(s * d), phi + 0.3])
        g.insert(p[:2], compose(p, np.c_[points(segs, p), np.zeros(len(points(segs, p)))])[:, :2])
    return MatchGrid(g.field, g.origin, g.resolution, 0.0)


def long_axis(cov2):
    w, v = np.linalg.eigh(cov2)
    return v[:, -1], w[-1] / w[0]


def axis_angle_deg(u, phi):
    """Angle between the undirected axis u and direction phi, in [0, 90] degrees."""
    a = math.degrees(math.atan2(u[1], u[0]) - phi) % 180.0
    return min(a, 180.0 - a)


def test_corridor_covariance_long_axis_lies_along_the_corridor_in_the_node_frame():
    phi = math.radians(35.0)
    segs = corridor(phi)
    grid = corridor_grid(segs, phi)
    heading = phi + math.radians(50.0)  # the robot looks across the corridor, not along it
    truth = np.array([0.3 * math.cos(phi), 0.3 * math.sin(phi), heading])
    m = RealTimeCorrelativeScanMatcher(0.3, math.radians(5.0), 0, 0.1, 0.1)
    res = m.match(grid, truth + [0.02, -0.02, 0.01], points(segs, truth))
    cov = res.covariance
    u, ratio = long_axis(cov[:2, :2])
    assert ratio > 20 and axis_angle_deg(u, phi) < 5.0  # map frame: along the corridor
    node = node_frame_covariance(cov, truth[2])
    u, ratio = long_axis(node[:2, :2])
    assert ratio > 20 and axis_angle_deg(u, phi - heading) < 5.0  # node frame: corridor direction seen from the robot
    # the penalty (which prefers the prediction) does not shrink it: same covariance without the penalty
    plain = RealTimeCorrelativeScanMatcher(0.3, math.radians(5.0), 0, 0.0, 0.0).match(grid, truth + [0.02, -0.02, 0.01],
                                                                                       points(segs, truth))
    np.testing.assert_allclose(cov, plain.covariance, rtol=1e-6, atol=1e-12)


def test_a_one_cell_window_does_not_make_the_corridor_look_certain():
    """A 5 cm window is a 3 × 3 lattice, which cannot step along a corridor at -20°: the moment
    covariance alone claims about a cell in every direction. The curvature (Laplace) cover turns
    the long axis along the corridor and widens it several-fold (the rasterized field is not quite
    flat along the walls, so it stays below the unmatched variance here)."""
    phi = math.radians(-20.0)
    segs = corridor(phi)
    grid = corridor_grid(segs, phi)
    truth = np.array([0.0, 0.0, phi + 1.0])
    m = RealTimeCorrelativeScanMatcher(0.3, math.radians(10.0), 0, 0.1, 0.1)
    res = m.match(grid, truth, points(segs, truth), linear_window=0.05, angular_window=math.radians(1.0))
    assert res.params.linear_cells == 1
    cov = res.covariance[:2, :2]
    d = np.array([math.cos(phi), math.sin(phi)])
    n = np.array([-d[1], d[0]])
    u, ratio = long_axis(cov)
    assert axis_angle_deg(u, phi) < 10.0 and ratio > 5
    assert float(d @ cov @ d) > 9.0 * float(n @ cov @ n)
    res.prior = None  # the moment covariance alone
    moment = res.covariance[:2, :2]
    assert float(d @ cov @ d) > 4.0 * float(d @ moment @ d)


def test_between_factor_noise_is_in_the_node_frame():
    """gtsam's BetweenFactorPose2 error is Logmap(measured⁻¹ · a⁻¹ · b): translation along b's own
    axes. A covariance long along the map's x, rotated by the node's map heading, lets the node
    slide along map x and holds it along map y — also when the anchor itself is rotated."""
    anchor, node = np.array([1.0, 2.0, 0.7]), np.array([3.0, 1.0, 1.6])
    cov_map = np.diag([1.0, 1e-4, 1e-6])

    def error(theta, delta):
        g = PoseGraph()
        g.add_node(0, anchor)
        g.add_node(1, node)
        g.add_intra(0, 1, between(anchor, node), node_frame_covariance(cov_map, theta))
        v = gtsam.Values()
        v.insert(gtsam.symbol("n", 0), gtsam.Pose2(*anchor))
        v.insert(gtsam.symbol("n", 1), gtsam.Pose2(*(node + delta)))
        return g.graph.error(v) - g.graph.error(g.values)

    along, across = np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.1, 0.0])
    assert error(node[2], along) < 0.01 and error(node[2], across) > 10.0
    # the relative heading alone (ignoring the anchor's) would be wrong
    assert error(node[2] - anchor[2], along) > 1.0


def test_unmatched_scans_get_the_loosest_covariance():
    cfg = SlamConfig()
    gs = GlobalSlam(cfg)
    scan = Scan(0.0, np.ones(3, np.float32), 0.0, 0.1, 0.0, 10.0, np.ones(3, bool), index=0)
    gs.add_node(scan, np.zeros(3), np.zeros((0, 2)), None, [(0, np.zeros(3))])
    rt = cfg.real_time_matcher
    prior = unmatched_covariance(rt.linear_search_window, math.radians(rt.angular_search_window_deg))
    for j, cov in [(1, np.diag([1e-6, 1e-6, 1e-8])), (2, None), (3, np.diag([1e-6, 1e-6, 1e-8]))]:
        s = Scan(float(j), np.ones(3, np.float32), 0.0, 0.1, 0.0, 10.0, np.ones(3, bool), index=j)
        gs.add_node(s, np.array([0.1 * j, 0.0, 0.4]), np.zeros((0, 2)), cov, [(0, np.zeros(3))])
    g = gs.graph.graph

    def in_submap(j):  # node j's constraint to the submap's first node (node 0), not its step from j - 1
        (i,) = [i for i in range(g.size()) if set(g.at(i).keys()) == {gtsam.symbol("n", 0), gtsam.symbol("n", j)}]
        return g.at(i)

    f_unmatched, f_matched = in_submap(2), in_submap(3)
    cov_u = np.linalg.inv(f_unmatched.noiseModel().R().T @ f_unmatched.noiseModel().R())
    cov_m = np.linalg.inv(f_matched.noiseModel().R().T @ f_matched.noiseModel().R())
    # the unmatched prior plus the submap's drift over the 0.2 m travelled since its first node
    np.testing.assert_allclose(np.linalg.eigvalsh(cov_u), np.linalg.eigvalsh(prior + gs._drift_covariance(0.2, 0.2)), rtol=1e-6)
    # never tighter than a matched scan's, in any direction
    assert np.all(np.linalg.eigvalsh(cov_u - cov_m) > 0)
    # and no matched window can hold a variance larger than the unmatched one
    assert prior[0, 0] >= rt.linear_search_window ** 2 and prior[2, 2] >= math.radians(rt.angular_search_window_deg) ** 2


def test_heading_drift_grows_with_the_turn_as_with_the_path():
    """A node-in-submap constraint's heading is as uncertain after turning on the spot by θ, with
    hits at range R, as after driving R·θ in a straight line; its translation only follows the path."""
    cfg = SlamConfig()
    ring = 4.0 * np.c_[np.cos(np.linspace(0, 6, 200)), np.sin(np.linspace(0, 6, 200))]  # hits 4 m out

    def in_submap_cov(poses):
        gs = GlobalSlam(cfg)
        for j, pose in enumerate(poses):
            s = Scan(float(j), np.ones(3, np.float32), 0.0, 0.1, 0.0, 10.0, np.ones(3, bool), index=j)
            gs.add_node(s, np.asarray(pose, float), ring, np.diag([1e-6, 1e-6, 1e-8]), [(0, np.zeros(3))])
        g, last = gs.graph.graph, len(poses) - 1
        (i,) = [i for i in range(g.size()) if set(g.at(i).keys()) == {gtsam.symbol("n", 0), gtsam.symbol("n", last)}]
        r = g.at(i).noiseModel().R()
        return np.linalg.inv(r.T @ r)

    turning = in_submap_cov([(0.0, 0.0, 0.3 * k) for k in range(6)])     # 1.5 rad on the spot
    driving = in_submap_cov([(1.2 * k, 0.0, 0.0) for k in range(6)])     # 6 m = 4 m × 1.5 rad
    still = in_submap_cov([(0.0, 0.0, 0.0) for k in range(6)])
    np.testing.assert_allclose(turning[2, 2], driving[2, 2], rtol=1e-6)
    r = math.radians(cfg.loop_closure.local_drift_deg) * 6.0
    assert turning[2, 2] >= r * r > 10 * still[2, 2]
    np.testing.assert_allclose(np.diag(turning)[:2], np.diag(still)[:2], rtol=1e-6)  # no path: no translation drift
    t = cfg.loop_closure.local_drift * 6.0
    assert np.all(np.diag(driving)[:2] >= t * t)


def test_floored_matches_the_eigendecomposition_it_shortcuts():
    """``_floored`` skips the eigendecomposition when every eigenvalue is already above the floor;
    on random covariances, tight and loose, with and without off-diagonal terms, it must agree with
    the plain rule (symmetrize, raise the variances, raise the eigenvalues to the smallest floor)."""
    from slam2d.backend.global_slam import _floored

    def reference(cov, st, sr):
        c = 0.5 * (cov + cov.T)
        floor = np.array([st * st, st * st, sr * sr])
        c[np.diag_indices(3)] = np.maximum(np.diag(c), floor)
        w, v = np.linalg.eigh(c)
        return (v * np.maximum(w, floor.min())) @ v.T, w.min() > floor.min()

    rng = np.random.default_rng(3)
    shortcut = raised = 0
    for _ in range(2000):
        a = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-3, 0, size=(3, 1))
        cov = a @ a.T + np.diag(10.0 ** rng.uniform(-8, -1, size=3))
        if rng.random() < 0.3:  # an asymmetric input (as summed float terms can be)
            cov[0, 1] += 1e-9
        st, sr = 10.0 ** rng.uniform(-3, -1), math.radians(10.0 ** rng.uniform(-1, 1))
        got, (want, above) = _floored(cov, st, sr), reference(cov.copy(), st, sr)
        assert np.allclose(got, want, rtol=1e-9, atol=1e-15)
        assert np.allclose(got, got.T)
        assert np.linalg.eigvalsh(got).min() >= min(st * st, sr * sr) * (1 - 1e-9)
        shortcut += above
        raised += not above
    assert shortcut > 100 and raised > 100  # both paths were exercised
    assert np.array_equal(_floored(None, 0.1, 0.2), np.diag([0.1 ** 2, 0.1 ** 2, 0.2 ** 2]))


def test_a_node_in_submap_constraint_carries_the_doubt_of_the_steps_since_the_submap_began():
    """Local SLAM's doubt on the steps between a submap's first node and a node (a weak match's score
    surface, a recovery's jump) adds to the node's constraint to that first node, variances summed:
    the submap was built across those steps. A node before them, and the step factors, are as before."""
    cfg = SlamConfig()
    doubts = {3: (0.05, 0.01), 5: (0.03, 0.02)}

    def in_submap_covs(with_doubt):
        gs = GlobalSlam(cfg)
        for j in range(6):
            s = Scan(float(j), np.ones(3, np.float32), 0.0, 0.1, 0.0, 10.0, np.ones(3, bool), index=j)
            gs.add_node(s, np.array([0.2 * j, 0.0, 0.1 * j]), np.zeros((0, 2)), np.diag([1e-6, 1e-6, 1e-8]),
                        [(0, np.zeros(3))], doubt=doubts.get(j, (0.0, 0.0)) if with_doubt else (0.0, 0.0))
        g, out = gs.graph.graph, {}
        for j in (2, 4, 5):  # (node 1's step from node 0 joins the same two nodes)
            (i,) = [i for i in range(g.size()) if set(g.at(i).keys()) == {gtsam.symbol("n", 0), gtsam.symbol("n", j)}]
            r = g.at(i).noiseModel().R()
            out[j] = np.linalg.inv(r.T @ r)
        return out

    plain, doubted = in_submap_covs(False), in_submap_covs(True)
    np.testing.assert_allclose(doubted[2], plain[2], rtol=1e-9)  # no doubtful step before node 2
    np.testing.assert_allclose(doubted[4] - plain[4], np.diag([0.05 ** 2, 0.05 ** 2, 0.01 ** 2]), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(doubted[5] - plain[5], np.diag([0.05 ** 2 + 0.03 ** 2, 0.05 ** 2 + 0.03 ** 2,
                                                               0.01 ** 2 + 0.02 ** 2]), rtol=1e-6, atol=1e-12)
