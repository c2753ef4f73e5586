"""Loop verification (issue 12, defect 3): re-score, ambiguity margin, consistency among loops."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from slam2d.backend.consistency import ConsistencyParams, candidate_pairs, fresh_pairs, inconsistent, loop_errors, pair_tests
from slam2d.backend.loop_closure import LoopMatch, SubmapMatcher
from slam2d.config import SlamConfig
from slam2d.eval.loops import agrees
from slam2d.geometry import between, compose, inverse
from slam2d.grid.probability_grid import ProbabilityGrid
from slam2d.io.mcap import McapLog
from slam2d.io.simulator import floor_plan, raycast
from slam2d.matching.observed import observed_scores
from slam2d.slam import Slam

from conftest import BUNDLED

ANGLES = -math.pi + 2 * math.pi / 360 * np.arange(360)
REFINE = (20.0, 10.0, 1.0, 20)


def scan_points(segs, pose, max_range=10.0):
    r = raycast(segs, pose[:2], ANGLES + pose[2], max_range)
    ok = np.isfinite(r)
    return np.stack([r[ok] * np.cos(ANGLES[ok]), r[ok] * np.sin(ANGLES[ok])], axis=1)


def submap(segs, poses, beam_step=1, max_range=10.0):
    """A submap of scans from ``poses`` (every ``beam_step``-th beam), frozen as a finished one is."""
    g = ProbabilityGrid(0.05)
    for p in poses:
        pts = scan_points(segs, p, max_range)[::beam_step]
        g.insert(p[:2], compose(p, np.c_[pts, np.zeros(len(pts))])[:, :2])
    b = g.known_bounds()
    g.freeze(*b)
    return SimpleNamespace(grid=g, local_pose=np.zeros(3), index=0, node_indices=[])


SCORE_GRIDS = pytest.mark.parametrize("field_sigma", [None, 0.1], ids=["probability", "likelihood_field"])


@SCORE_GRIDS
def test_refined_pose_is_re_scored(field_sigma):
    """A match whose refined pose no longer scores min_score is rejected, with the reason."""
    segs = floor_plan()
    center = np.array([6.0, 1.25, 0.0])
    m = SubmapMatcher(submap(segs, [center + [dx, 0.0, 0.0] for dx in np.linspace(-1, 1, 9)]), 4, field_sigma=field_sigma)
    pts = scan_points(segs, center)
    good = m.verify(LoopMatch(center.copy(), center.copy(), 0.7, 0.0), pts, 0.55, 0.0, (0.3, 0.035), (0.2, 0.0175), 0.004)
    assert good.reason is None and good.rescore > 0.55
    off = center + [0.0, 0.35, 0.05]  # e.g. a lucky lattice cell that the refinement slid off
    bad = m.verify(LoopMatch(off, off, 0.7, 0.0), pts, 0.55, 0.0, (0.3, 0.035), (0.2, 0.0175), 0.004)
    assert bad.rescore < 0.55 and bad.reason.startswith("refined pose scores")


@SCORE_GRIDS
def test_a_refined_pose_that_is_not_the_peak_is_rejected(field_sigma):
    """The margin is measured from the best pose of the verification window; a constraint whose own
    (refined) pose is not that peak, with a better pose beyond the exclusion zone, is rejected, even
    when it scores enough and the margin alone would pass."""
    segs = floor_plan()
    center = np.array([6.0, 1.25, 0.0])
    m = SubmapMatcher(submap(segs, [center + [dx, 0.0, 0.0] for dx in np.linspace(-1, 1, 9)]), 4, field_sigma=field_sigma)
    pts = scan_points(segs, center)
    # a threshold the pose 0.3 m off still reaches (the field falls off faster than the probabilities)
    min_score = 0.3 if field_sigma is None else 0.15
    args = (pts, min_score, 0.02, (0.6, 0.035), (0.2, 0.0175), 0.004)
    good = m.verify(LoopMatch(center.copy(), center.copy(), 0.7, 0.0), *args)
    assert good.reason is None and good.margin >= 0.02
    off = center + [0.0, 0.3, 0.0]  # the true pose lies 0.3 m away, inside the window, outside the exclusion
    bad = m.verify(LoopMatch(off, off, 0.7, 0.0), *args)
    assert bad.rescore >= min_score and bad.margin >= 0.02  # re-score and margin (the peak's) would both pass
    assert bad.reason.startswith("ambiguous: a pose 0.30 m"), bad.reason


@SCORE_GRIDS
def test_ambiguous_match_in_a_symmetric_world_is_rejected(field_sigma):
    """Two long parallel walls, no ends in range: every slide along them scores the same."""
    segs = np.array([[-30.0, 1.0, 30.0, 1.0], [-30.0, -1.0, 30.0, -1.0]])
    m = SubmapMatcher(submap(segs, [np.array([x, 0.0, 0.3]) for x in np.linspace(-3, 3, 13)]), 4, field_sigma=field_sigma)
    truth = np.array([0.4, 0.1, 0.2])
    res = m.match(scan_points(segs, truth, 8.0), truth + [0.3, 0.05, 0.02], 1.0, math.radians(5), 0.55, REFINE, 0.02)
    assert res is not None and res.rescore >= 0.55  # it scores well ...
    assert res.margin < 0.02 and res.reason.startswith("ambiguous")  # ... but so does a slide along the corridor
    # the same search in the office (not symmetric) is accepted, with a covariance from its score surface
    segs = floor_plan()
    center = np.array([6.0, 1.25, 0.0])
    m = SubmapMatcher(submap(segs, [center + [dx, 0.0, 0.0] for dx in np.linspace(-1, 1, 9)]), 4, field_sigma=field_sigma)
    res = m.match(scan_points(segs, center), center + [0.3, 0.05, 0.02], 1.0, math.radians(5), 0.55, REFINE, 0.02)
    assert res.reason is None and res.margin >= 0.02
    assert np.hypot(*(res.pose - center)[:2]) < 0.05
    assert res.covariance.shape == (3, 3) and np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_likelihood_field_equals_a_distance_transform():
    """``likelihood_field`` (local SLAM's kernel stamped around every occupied cell) against plain numpy:
    exp(−d²/2σ²) of the distance to the nearest known cell with p > 0.5, zero beyond 3σ, as uint8;
    unknown cells never count as surfaces, and cells at the grid's borders get their full value."""
    from scipy.ndimage import distance_transform_edt

    from slam2d.backend.loop_closure import likelihood_field
    from slam2d.grid.probability_grid import quantize

    rng = np.random.default_rng(5)
    for sigma, res in [(0.1, 0.05), (0.07, 0.05), (0.1, 0.03)]:
        prob = quantize(np.where(rng.random((60, 90)) < 0.03, 0.8, rng.uniform(0.12, 0.5, (60, 90))).astype(np.float32))
        prob[0, 5] = prob[59, 89] = 200  # surfaces on the borders
        known = (rng.random((60, 90)) < 0.9).astype(np.uint8)
        known[0, 5] = known[59, 89] = 1
        grid = SimpleNamespace(prob=prob, known=known, resolution=res, known_bits=lambda k=known: np.packbits(k, axis=1))
        occ = (known > 0) & (prob.astype(np.float32) / 255.0 > 0.5)
        d = distance_transform_edt(~occ) * res
        radius = math.ceil(3 * sigma / res)  # whole cells, as local SLAM's field (ProbabilityGrid.field_radius)
        want = np.where(d <= radius * res + 1e-9, np.exp(-0.5 * (d / sigma) ** 2), 0.0)
        got = likelihood_field(grid, sigma).astype(int)
        assert np.abs(got - np.round(want * 255).astype(int)).max() <= 1
        assert got[0, 5] == 255 and got[59, 89] == 255
        assert (got[occ] == 255).all() and (got[d > radius * res + 1e-9] == 0).all()


def test_known_centre_is_the_mean_of_the_known_cells():
    """A matcher's centre (counts per row and per column) equals the mean of ``np.argwhere`` of the
    known cells, to the last bit, on an active and on a finished grid; an empty grid gives its origin."""
    from slam2d.backend.loop_closure import _known_centre

    rng = np.random.default_rng(12)
    g = ProbabilityGrid(0.05)
    for _ in range(15):
        o = rng.uniform(-1, 1, 2)
        g.insert(o, o + rng.uniform(-3, 3, (40, 2)))
    for frozen in (False, True):
        if frozen:
            g.freeze(*g.known_bounds())
        k = np.argwhere(g.known > 0)
        assert np.array_equal(_known_centre(g), g.origin + (k.mean(axis=0)[::-1] + 0.5) * g.resolution)
    empty = ProbabilityGrid(0.05, origin=(1.0, 2.0), shape=(4, 5))
    assert np.array_equal(_known_centre(empty), [1.0, 2.0])


def test_stack_cache_builds_into_the_buffer_it_evicted():
    """With room for one stack, the stack evicted for a new one is the memory the build after it
    writes into (submaps of the same size); the levels are those of a fresh build."""
    from slam2d.backend.loop_closure import StackCache
    from slam2d.matching.search import PrecomputationStack

    segs = floor_plan()
    subs = [submap(segs, [np.array([x, 0.0, 0.0])]) for x in (0.0, 0.0, 0.0)]
    for i, s in enumerate(subs):
        s.index = i
    cache = StackCache(0, min_stacks=1)
    matchers = [SubmapMatcher(s, 4, cache) for s in subs]
    first = matchers[0].stack
    buf = first.buffer
    matchers[1].stack  # evicts the first: its buffer is kept
    third = matchers[2].stack
    assert third.buffer is buf and cache.builds == 3
    fresh = PrecomputationStack(matchers[2].source_grid(), 4)
    for d in range(5):
        np.testing.assert_array_equal(third.level(d), fresh.level(d))
    cache.clear()
    assert cache._spare is None


def test_a_submap_seen_by_few_scans_is_matched_on_its_likelihood_field():
    """A submap built from three scans with one beam in four: its walls read a probability of about
    0.55 and its floor about 0.48, so on the probabilities a scan scores nearly the same at its true
    pose and 0.4 m off, and the margin to a separated peak is a fraction of the likelihood field's.
    On the field the match comes back to the true pose with a margin that passes verification."""
    segs = floor_plan()
    center = np.array([6.0, 1.25, 0.0])
    sub = submap(segs, [center + [dx, 0.0, 0.0] for dx in (-0.8, 0.0, 0.8)], beam_step=4)
    truth = center + [0.3, 0.05, 0.02]
    pts = scan_points(segs, truth)
    initial = truth + [0.25, -0.15, 0.03]
    found = {}
    for sigma in (None, 0.1):
        m = SubmapMatcher(sub, 4, field_sigma=sigma)
        own = m.self_score([(scan_points(segs, center), center)])
        found[sigma] = m.match(pts, initial, 1.0, math.radians(5), 0.7 * own, REFINE, 0.02)
        assert found[sigma] is not None
    field, prob = found[0.1], found[None]
    assert field.reason is None, field.reason
    assert np.hypot(*(field.pose - truth)[:2]) < 0.05 and abs(field.pose[2] - truth[2]) < math.radians(0.5)
    assert field.margin > 3 * prob.margin


def test_pair_consistency_flags_the_contradicting_loop():
    """Four loops from one place to another along a straight drive; one is shifted by 1 m."""
    local = np.array([[x, 0.0, 0.0] for x in np.arange(0, 40, 1.0)])
    path = np.arange(40, dtype=float)
    truth = local + [[0.5, 0.2, 0.0]] * 40  # local SLAM is off by a constant near both ends: loops agree
    anchors, nodes = [0, 1, 2, 3], [30, 31, 32, 33]
    rel = np.array([between(truth[a], truth[j] + [0, 0, 0]) for a, j in zip(anchors, nodes)])
    rel[1] = compose(rel[1], [1.0, 0.0, 0.05])
    t = pair_tests(rel, local[anchors], local[nodes], path[anchors], path[nodes], ConsistencyParams())
    m = t.dense()
    assert m[0, 2] == 1 and m[0, 3] == 1 and m[0, 1] == -1 and m[1, 2] == -1
    assert [i for i, _ in inconsistent(t, np.array([0.7, 0.9, 0.6, 0.6]))] == [1]
    # two loops that contradict each other and nothing else: undecided here (the residual check judges)
    two = pair_tests(rel[:2], local[anchors[:2]], local[nodes[:2]], path[anchors[:2]], path[nodes[:2]], ConsistencyParams())
    assert two.dense()[0, 1] == -1 and inconsistent(two, np.array([0.7, 0.9])) == []


def _straight_loops(n=40):
    """``n`` true loops of a robot that drives a straight line, out of sight for 100 m, and back along
    it, one metre apart: loop i ties the return pass's node at x = i to the first pass's node there.
    Local SLAM has no drift here, so every cycle closes exactly."""
    line = np.array([[x, 0.0, 0.0] for x in np.arange(n, dtype=float)])
    rel = np.zeros((n, 3))
    return rel, line, line.copy(), np.arange(n, dtype=float), 100.0 + np.arange(n, dtype=float)


def test_a_loop_that_every_cycle_puts_off_is_removed_though_far_partners_tolerate_it():
    """A loop 0.6 m off contradicts its near partners (chains under 10 m, tolerances under 0.6 m) but
    passes the looser tolerance of more partners further along the chain, so counting keeps it. All
    its cycles put it the same 0.6 m off: the tolerance-weighted mean of its cycle errors removes it;
    a true loop with two such partners nearby keeps a diluted mean and stays; the same for a loop
    whose rotation alone is off (3.4°)."""
    p = ConsistencyParams()
    scores = np.full(40, 0.8)
    rel, la, lj, pa, pj = _straight_loops()
    assert inconsistent(pair_tests(rel, la, lj, pa, pj, p), scores) == []
    one = rel.copy()
    one[5] = compose(one[5], [0.6, 0.0, 0.0])
    t = pair_tests(one, la, lj, pa, pj, p)
    m = t.dense()
    assert np.sum(m[5] == -1) < np.sum(m[5] == 1)  # more partners tolerate it than contradict it
    out = inconsistent(t, scores)
    assert [i for i, _ in out] == [5] and "times its tolerance" in out[0][1]
    means = loop_errors(t, np.ones(40, bool))
    assert means[5] == pytest.approx(0.6 / p.tol_t)  # every cycle puts it the same 0.6 m off
    assert means[7] < 0.5  # a true neighbour: only its cycle with loop 5 is off
    two = one.copy()
    two[6] = compose(two[6], [0.6, 0.0, 0.0])
    assert sorted(i for i, _ in inconsistent(pair_tests(two, la, lj, pa, pj, p), scores)) == [5, 6]
    turned = rel.copy()
    turned[20] = compose(turned[20], [0.0, 0.0, 0.06])
    t = pair_tests(turned, la, lj, pa, pj, p)
    assert np.sum(t.dense()[20] == -1) < np.sum(t.dense()[20] == 1)
    assert [i for i, _ in inconsistent(t, scores)] == [20]


def test_a_loop_contradicted_once_is_left_to_the_residual_check_whatever_its_mean():
    """Two loops that contradict each other and have no other partner: neither can be told false."""
    p = ConsistencyParams()
    rel, la, lj, pa, pj = _straight_loops(2)
    rel[1] = compose(rel[1], [1.0, 0.0, 0.0])
    t = pair_tests(rel, la, lj, pa, pj, p)
    assert loop_errors(t, np.ones(2, bool))[1] > 1 and inconsistent(t, np.array([0.7, 0.9])) == []


def test_the_doubt_of_a_recovered_step_on_a_leg_widens_the_pair_tolerance():
    """On the return pass local SLAM recovered from a lost match with a jump of 0.8 m that the truth
    does not have (the recovery chose wrong, and said by how much it might be off: its doubt). Every
    loop is true, but the cycles of loops on either side of the jump carry the jump. With the drift
    budgets (``DriftBound``: drift per metre plus each step's doubt) the pair tolerance covers it
    and no loop is removed; with drift per metre alone, those pairs contradict and true loops go."""
    p = ConsistencyParams()
    rel, la, lj, pa, pj = _straight_loops()
    lj = lj.copy()
    lj[20:, 0] += 0.8  # local poses after the jump
    doubt = np.where(np.arange(40) >= 20, 0.8, 0.0)
    ba = np.c_[p.drift_t * pa, p.drift_r * pa]
    bj = np.c_[p.drift_t * pj + doubt, p.drift_r * pj]
    with_doubt = pair_tests(rel, la, lj, pa, pj, p, ba, bj)
    assert np.all(with_doubt.consistent)
    assert inconsistent(with_doubt, np.full(40, 0.8)) == []
    without = pair_tests(rel, la, lj, pa, pj, p)
    assert not np.all(without.consistent) and inconsistent(without, np.full(40, 0.8)) != []
    # budgets of drift per metre alone give the drift-per-metre verdicts
    plain = pair_tests(rel, la, lj, pa, pj, p, ba, np.c_[p.drift_t * pj, p.drift_r * pj])
    assert np.array_equal(plain.dense(), without.dense())


def _all_pairs_reference(rel, la, lj, pa, pj, p):
    """Every pair (i < k) enumerated and tested one by one: what ``pair_tests`` must equal."""
    n = len(rel)
    out = np.zeros((n, n), dtype=np.int8)
    for i in range(n):
        for k in range(i + 1, n):
            chain = abs(pa[i] - pa[k]) + abs(pj[i] - pj[k])
            if chain > p.max_chain:
                continue
            e = compose(compose(compose(rel[i], between(lj[i], lj[k])), inverse(rel[k])), between(la[k], la[i]))
            ok = math.hypot(e[0], e[1]) <= p.tol_t + p.drift_t * chain and abs(e[2]) <= p.tol_r + p.drift_r * chain
            out[i, k] = out[k, i] = 1 if ok else -1
    return out


def test_pair_tests_equal_testing_every_pair():
    """Pairs found by sorting along the path are exactly the pairs an all-pairs loop tests, with the
    same verdicts, including pairs exactly at the chain limit and loops in any order."""
    rng = np.random.default_rng(3)
    p = ConsistencyParams()
    for trial in range(30):
        n = int(rng.integers(0, 60))
        pa = rng.uniform(0, 200, n)
        pj = pa + rng.uniform(0, 300, n)
        if n > 3:  # ties and pairs exactly at max_chain
            pa[1] = pa[0]
            pa[2], pj[2] = pa[0] + p.max_chain, pj[0]
        la = np.c_[rng.uniform(-20, 20, (n, 2)), rng.uniform(-3, 3, n)]
        lj = np.c_[rng.uniform(-20, 20, (n, 2)), rng.uniform(-3, 3, n)]
        truth = np.array([between(a, b) for a, b in zip(la, lj)]).reshape(-1, 3)
        rel = truth + rng.normal(0, [0.3, 0.3, 0.03], (n, 3)) * (rng.uniform(size=(n, 1)) < 0.5)
        ref = _all_pairs_reference(rel, la, lj, pa, pj, p)
        t = pair_tests(rel, la, lj, pa, pj, p)
        assert np.array_equal(t.dense(), ref), trial
        assert len(t.src) == 2 * np.count_nonzero(np.triu(ref))  # each tested pair once each way, nothing else
        i, k = candidate_pairs(pa, p.max_chain)
        assert np.all(i < k) and len(set(zip(i.tolist(), k.tolist()))) == len(i)


def test_fresh_pairs_are_the_candidate_pairs_that_touch_a_fresh_loop():
    """Found from the fresh loops' windows alone, they are exactly the pairs ``candidate_pairs`` lists
    with a fresh loop in them, each once: with ties, pairs exactly at the limit, no fresh loop, all."""
    rng = np.random.default_rng(5)
    for trial in range(300):
        n = int(rng.integers(0, 80))
        pa = np.round(rng.uniform(0, 120, n), int(rng.integers(0, 3)))
        if n > 3:
            pa[1], pa[2] = pa[0], pa[0] + 30.0
        fresh = rng.uniform(size=n) < [0.0, 0.1, 0.5, 1.0][trial % 4]
        i, k = candidate_pairs(pa, 30.0)
        m = fresh[i] | fresh[k]
        a, b = fresh_pairs(pa, fresh, 30.0)
        got = list(zip(a.tolist(), b.tolist()))
        assert np.all(a < b) and len(got) == len(set(got)), trial
        assert set(got) == set(zip(i[m].tolist(), k[m].tolist())), trial


def test_pair_cache_equals_testing_the_current_loops_afresh():
    """Loops arrive in batches and some are removed between calls (as in global SLAM): every call's
    tests, taken partly from earlier calls, are exactly ``pair_tests`` of the loops alive then."""
    from slam2d.backend.consistency import PairCache

    rng = np.random.default_rng(11)
    p = ConsistencyParams()
    total = 150
    pa = np.sort(rng.uniform(0, 400, total))  # loops found along the way: anchors in any order of path
    rng.shuffle(pa[: total // 2])
    pj = pa + rng.uniform(0, 300, total)
    la = np.c_[rng.uniform(-20, 20, (total, 2)), rng.uniform(-3, 3, total)]
    lj = np.c_[rng.uniform(-20, 20, (total, 2)), rng.uniform(-3, 3, total)]
    truth = np.array([between(a, b) for a, b in zip(la, lj)])
    rel = truth + rng.normal(0, [0.3, 0.3, 0.03], (total, 3)) * (rng.uniform(size=(total, 1)) < 0.5)
    ids = np.cumsum(rng.integers(1, 30, total))  # factor indices: increasing, with gaps
    cache, alive, added = PairCache(p), [], 0
    while added < total:
        step = int(rng.integers(0, 12))
        alive += list(range(added, min(total, added + step)))
        added = min(total, added + step)
        for _ in range(int(rng.integers(0, 3))):  # removals, new loops or old
            if len(alive) > 2:
                alive.pop(int(rng.integers(0, len(alive))))
        a = np.array(alive, dtype=np.int64)
        got = cache.tests(ids[a], rel[a], la[a], lj[a], pa[a], pj[a])
        want = pair_tests(rel[a], la[a], lj[a], pa[a], pj[a], p)
        assert got.n == want.n and np.array_equal(got.dense(), want.dense())
        assert len(got.src) == len(want.src)


def _run_with_false_loops(cfg, take):
    """Run the simulator's log; copy the accepted records for which ``take(rec, injected)`` says so (once
    15 loops are in the graph) as false loops: the same ends, the relative pose off by 0.6 m, 0.4 m and
    0.08 rad. Returns (ground-truth poses, the global SLAM, the injected records)."""
    scans = list(McapLog(BUNDLED))
    gt = np.array([s.ground_truth for s in scans])
    slam = Slam(cfg)
    gs = slam.global_slam
    commit = gs._commit
    injected = []

    def commit_and_inject(rec, loop):  # every search's record passes here, accepted or not
        commit(rec, loop)
        if rec["accepted"] and len(gs.graph.loops) >= 15 and take(rec, injected):
            false = dict(rec, relative_pose=list(compose(np.array(rec["relative_pose"]), [0.6, -0.4, 0.08])),
                         reason="accepted", in_final_graph=True, injected=True)
            gs.graph.add_loop(rec["from_scan"], rec["to_scan"], np.array(false["relative_pose"]),
                              [0.02, 0.02, math.radians(0.3)], false)
            gs.records.append(false)
            injected.append(false)

    gs._commit = commit_and_inject
    slam.run(scans)
    return gt, gs, injected


def test_consistency_check_rejects_an_injected_false_loop_on_the_simulator():
    cfg = SlamConfig()
    # the consistency check alone judges here: the residual check and GNC, which can reach the false
    # loop first when the graph is optimized before it has enough partners, are switched off
    cfg.loop_closure.max_residual_translation, cfg.loop_closure.max_residual_rotation_deg = 1e3, 1e3
    cfg.loop_closure.gnc_final = False
    gt, gs, injected = _run_with_false_loops(cfg, lambda rec, injected: not injected)
    assert injected, "no true loop to copy"
    false = injected[0]
    assert agrees(gt, false, 0.3, 2.0) is False
    assert false["in_final_graph"] is False and false["reason"].startswith("inconsistent")
    final = [r for r in gs.records if r.get("in_final_graph")]
    assert len(final) >= 20
    assert all(agrees(gt, r, 0.3, 2.0) for r in final)


def test_gnc_prune_removes_a_false_loop_and_keeps_the_true_one():
    """GNC judges loops against the local chain's covariances: with honest ones (the drift fits them)
    it keeps the true loop; with overconfident ones it drops the true loop too (seen while writing this)."""
    from slam2d.backend.pose_graph import PoseGraph

    side, per = 10.0, 10
    gt = np.array([(x0 + math.cos(s * math.pi / 2) * side * i / per, y0 + math.sin(s * math.pi / 2) * side * i / per,
                    s * math.pi / 2) for s, (x0, y0) in enumerate([(0, 0), (side, 0), (side, side), (0, side)])
                   for i in range(per)])
    g = PoseGraph()
    rng = np.random.default_rng(1)
    est = [gt[0]]
    for k in range(1, len(gt)):
        est.append(compose(est[-1], between(gt[k - 1], gt[k]) + [0.0, 0.0, 0.005] + rng.normal(0, 0.003, 3)))
    for k, p in enumerate(est):
        g.add_node(k, p)
        if k:
            g.add_intra(k - 1, k, between(est[k - 1], est[k]), np.diag([1e-4, 1e-4, 1e-4]))  # honest: the drift fits it
    true, false = {"accepted": True, "in_final_graph": True}, {"accepted": True, "in_final_graph": True}
    g.add_loop(0, len(gt) - 1, between(gt[0], gt[-1]), [0.02, 0.02, 0.005], true)
    g.add_loop(5, 25, np.array([3.0, -2.0, 1.0]), [0.02, 0.02, 0.005], false)
    out = g.gnc_prune()
    assert [f.record for f in out] == [false] and false["reason"] == "GNC outlier"
    assert true["in_final_graph"] and len(g.loops) == 1


def _star_graph(seed=3, submaps=8, per=12, steps=False):
    """A pose graph shaped as slam2d builds it: node j hangs from the first node (anchor) of each of
    the one or two overlapping submaps it lies in; local constraints carry drift and noise.
    ``steps``: also local SLAM's step between consecutive nodes, left out of GNC's screen as
    ``GlobalSlam.add_node`` leaves out every step a submap spans."""
    from slam2d.backend.pose_graph import PoseGraph

    rng = np.random.default_rng(seed)
    n = submaps * per
    t = np.linspace(0, 1.7 * math.pi, n)
    gt = np.c_[8 * np.cos(t), 5 * np.sin(t), t + math.pi / 2]
    local = [gt[0]]
    for k in range(1, n):
        local.append(compose(local[-1], between(gt[k - 1], gt[k]) + rng.normal(0, [0.006, 0.006, 0.004])))
    g = PoseGraph()
    for k in range(n):
        g.add_node(k, local[k])
    anchors = list(range(0, n, per // 2))  # a submap starts every half submap: two overlap
    for k in range(n):
        for a in anchors:
            if a < k < a + per:
                cov = np.diag([1e-4, 1e-4, 5e-5]) * (k - a)  # the drift's, with room
                g.add_intra(a, k, between(local[a], local[k]), cov)
        if steps and k:
            g.add_intra(k - 1, k, between(local[k - 1], local[k]), np.diag([2e-4, 2e-4, 6e-6]), screened=False)
    return g, gt


def test_reduced_graph_keeps_the_solution_of_the_nodes_it_keeps():
    """``PoseGraph._reduced`` eliminates the nodes that only link two submaps' first nodes; the
    nodes it keeps (first nodes, loop ends, the prior's node) come out of a batch solve where the full
    graph's solve puts them, and it keeps every loop."""
    import gtsam

    from slam2d.backend.pose_graph import _key

    g, gt = _star_graph()
    n = len(gt)
    loops = [(0, n - 5), (6, n - 20), (13, 50)]
    for a, j in loops:
        g.add_loop(a, j, between(gt[a], gt[j]), [0.02, 0.02, 0.005], {"accepted": True, "in_final_graph": True})
    red, values, slots = g._reduced()
    kept = {gtsam.Symbol(k).index() for k in values.keys()}
    assert len(slots) == len(loops) and {f.node for f in slots.values()} <= kept
    assert {0, 6, 12, 13, 50, n - 5, n - 20} <= kept and len(kept) < n // 3
    full = gtsam.LevenbergMarquardtOptimizer(g.graph, g.values, gtsam.LevenbergMarquardtParams()).optimize()
    part = gtsam.LevenbergMarquardtOptimizer(red, values, gtsam.LevenbergMarquardtParams()).optimize()
    moved = max(math.hypot(full.atPose2(_key("n", j)).x() - g.node_pose(j)[0],
                           full.atPose2(_key("n", j)).y() - g.node_pose(j)[1]) for j in kept)
    assert moved > 0.05  # the loops move the kept nodes: the comparison below means something
    for j in kept:
        a, b = full.atPose2(_key("n", j)), part.atPose2(_key("n", j))
        assert math.hypot(a.x() - b.x(), a.y() - b.y()) < 2e-3 and abs(a.theta() - b.theta()) < 2e-4, j


@pytest.mark.parametrize("steps", [False, True])
def test_gnc_on_the_reduced_graph_removes_the_false_loop_only(steps):
    """GNC on the reduced graph removes the one false loop, also where the graph holds local SLAM's
    steps between consecutive nodes: the screen leaves out the steps a submap spans, so it still
    eliminates most nodes."""
    g, gt = _star_graph(seed=5, steps=steps)
    n = len(gt)
    true = [{"accepted": True, "in_final_graph": True} for _ in range(2)]
    g.add_loop(0, n - 5, between(gt[0], gt[n - 5]), [0.02, 0.02, 0.005], true[0])
    g.add_loop(6, n - 20, between(gt[6], gt[n - 20]), [0.02, 0.02, 0.005], true[1])
    false = {"accepted": True, "in_final_graph": True}
    g.add_loop(12, 40, between(gt[12], gt[40]) + [1.5, -1.0, 0.4], [0.02, 0.02, 0.005], false)
    assert g._reduced()[1].size() < n // 3
    out = g.gnc_prune()
    assert [f.record for f in out] == [false] and all(r["in_final_graph"] for r in true)


@pytest.mark.parametrize("second", ["towards", "away"])
def test_reduced_constraint_has_the_marginal_of_the_two_it_replaces(second):
    """Node 1 links 0 and 2 only: eliminated, the composed constraint 0 → 2 gives node 2 the same
    marginal covariance (and mean) the two constraints through node 1 gave it, whichever way the
    second one points."""
    import gtsam

    from slam2d.backend.pose_graph import PoseGraph, _key

    x = [np.array([0.0, 0.0, 0.3]), np.array([1.0, 0.5, 0.9]), np.array([2.0, -0.4, -0.5])]
    g = PoseGraph()
    for k, p in enumerate(x):
        g.add_node(k, p)
    g.add_intra(0, 1, between(x[0], x[1]), np.array([[1e-3, 2e-4, 1e-4], [2e-4, 3e-3, -2e-4], [1e-4, -2e-4, 2e-3]]))
    if second == "towards":
        g.add_intra(2, 1, between(x[2], x[1]), np.diag([2e-3, 1e-3, 4e-3]))
    else:
        g.add_intra(1, 2, between(x[1], x[2]), np.diag([2e-3, 1e-3, 4e-3]))
    g.add_loop(0, 2, between(x[0], x[2]), [0.1, 0.1, 0.1], {})  # keeps node 2
    red, values, slots = g._reduced()
    assert values.size() == 2 and red.size() == 3 and len(slots) == 1

    def marginal(graph, vals, skip=()):
        gg = gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            if i not in skip:
                gg.add(graph.at(i))
        return gtsam.Marginals(gg, vals).marginalCovariance(_key("n", 2))

    np.testing.assert_allclose(marginal(red, values, slots), marginal(g.graph, g.values, {3}), rtol=1e-9, atol=1e-15)


def test_fused_constraint_adds_informations_and_weights_the_means():
    import gtsam

    from slam2d.backend.pose_graph import _fuse

    z = gtsam.Pose2(1.0, 2.0, 0.3)
    c1, c2 = np.diag([1e-2, 4e-2, 1e-3]), np.diag([3e-2, 1e-2, 1e-3])
    fz, fc = _fuse([(z, c1), (z, c2)])
    np.testing.assert_allclose(fc, np.linalg.inv(np.linalg.inv(c1) + np.linalg.inv(c2)), rtol=1e-12)
    assert fz.equals(z, 1e-12)
    # two measurements 2 cm apart along the first's x, equal weights: the fused one lies halfway
    z2 = z.compose(gtsam.Pose2(0.02, 0.0, 0.0))
    fz, fc = _fuse([(z, c1), (z2, c1)])
    assert fz.equals(z.compose(gtsam.Pose2(0.01, 0.0, 0.0)), 1e-9)
    np.testing.assert_allclose(fc, c1 / 2, rtol=1e-12)
    one = _fuse([(z, c1)])
    assert one[0] is z and one[1] is c1


def test_heading_margin_equals_the_best_score_per_heading_compared_by_hand():
    """``heading_margin``: the best score within the exclusion of the window's centre heading, anywhere in
    the window, minus the best at every other heading; against a loop over every cell."""
    from slam2d.backend.loop_closure import heading_margin

    rng = np.random.default_rng(5)
    for _ in range(50):
        n_ang, w, ex = int(rng.integers(1, 6)), int(rng.integers(0, 4)), int(rng.integers(0, 3))
        scores = rng.random((2 * n_ang + 1, 2 * w + 1, 2 * w + 1))
        near = [scores[a, iy, ix] for a in range(2 * n_ang + 1) for iy in range(2 * w + 1) for ix in range(2 * w + 1)
                if abs(a - n_ang) <= ex]
        far = [scores[a, iy, ix] for a in range(2 * n_ang + 1) for iy in range(2 * w + 1) for ix in range(2 * w + 1)
               if abs(a - n_ang) > ex]
        got = heading_margin(scores, ex)
        assert (math.isnan(got) and not far) or got == pytest.approx(max(near) - max(far), abs=0.0)


@SCORE_GRIDS
def test_a_corridor_match_fixes_the_heading_where_it_cannot_fix_the_position(field_sigma):
    """Two long parallel walls: poses slid along them score alike, so the match is ambiguous and no
    loop; but only poses at its heading do, so the heading margin clears min_margin and the refined
    heading is the true one. A round room is the opposite: any heading scores alike there."""
    segs = np.array([[-30.0, 1.0, 30.0, 1.0], [-30.0, -1.0, 30.0, -1.0]])
    m = SubmapMatcher(submap(segs, [np.array([x, 0.0, 0.3]) for x in np.linspace(-3, 3, 13)]), 4, field_sigma=field_sigma)
    truth = np.array([0.4, 0.1, 0.2])
    res = m.match(scan_points(segs, truth, 8.0), truth + [0.3, 0.05, 0.02], 1.0, math.radians(5), 0.55, REFINE, 0.02)
    assert res.reason.startswith("ambiguous") and res.heading_margin >= 0.02, (res.reason, res.heading_margin)
    assert abs(math.remainder(res.pose[2] - truth[2], 2 * math.pi)) < math.radians(0.5)
    assert abs(res.pose[1] - truth[1]) < 0.05  # across the corridor it is fixed too; along it, not
    # a round room (a 48-gon of radius 3 m): every heading fits
    k = np.arange(48) * 2 * math.pi / 48
    ring = np.c_[3 * np.cos(k), 3 * np.sin(k), 3 * np.cos(k + 2 * math.pi / 48), 3 * np.sin(k + 2 * math.pi / 48)]
    m = SubmapMatcher(submap(ring, [np.array([0.0, 0.0, a]) for a in np.linspace(0, 1, 5)]), 4, field_sigma=field_sigma)
    centre = np.array([0.0, 0.0, 0.4])
    res = m.match(scan_points(ring, centre, 8.0), centre + [0.02, 0.0, 0.03], 0.3, math.radians(5), 0.3, REFINE, 0.02)
    assert res is not None and res.heading_margin < 0.02, res.heading_margin


def _corridor_with_stubs():
    """A corridor along x (walls at y = ±1) with a pair of 0.3 m stubs on both walls at x = 1.0 and 1.6."""
    walls = [[-30.0, 1.0, 30.0, 1.0], [-30.0, -1.0, 30.0, -1.0]]
    stubs = [[x, s, x, s * 0.7] for x in (1.0, 1.6) for s in (1.0, -1.0)]
    return np.array(walls + stubs)


def test_a_match_slid_back_onto_mapped_ground_is_held_against_the_estimate():
    """A scan that sees past the mapped end of a submap: the submap's scans (range 4 m, from x ≤ -2.7)
    mapped the corridor up to x ≈ 1.3, the first stub but not the second; the scan at x = 0 sees 8 m.
    Slid back 0.6 m, its second stub lands on the mapped first one and 0.6 m more of its walls on
    mapped walls: that pose scores higher than the true one, by a clear margin, and the plain
    verification accepts it. Held against the estimate (the true pose) on the points both put on
    observed cells, it loses, and verification rejects it."""
    segs = _corridor_with_stubs()
    m = SubmapMatcher(submap(segs, [np.array([x, 0.0, 0.0]) for x in np.linspace(-4, -2.7, 7)], max_range=4.0), 4,
                      field_sigma=0.1)
    truth = np.zeros(3)
    pts = scan_points(segs, truth, 8.0)
    args = (pts, truth, 0.7, math.radians(3), 0.3, REFINE, 0.02, (0.6, math.radians(2)), (0.2, math.radians(1)))
    plain = m.match(*args)
    assert plain.reason is None and plain.margin >= 0.02  # the slide passes re-score, peak and margin ...
    assert abs(plain.pose[0] + 0.6) < 0.05, plain.pose  # ... 0.6 m back
    held = m.match(*args, estimate=True)
    assert held.reason is not None and held.reason.startswith("the estimate 0.6"), held.reason
    # the check compares only where both poses read mapped ground: there the estimate scores higher
    both = observed_scores(m.submap.grid, m.prob, [held.pose, truth], pts)
    assert both is not None and both[1] > both[0]


@pytest.mark.parametrize("offset", [(0.5, 0.0, 0.0), (0.4, 0.1, 0.02), (-0.3, 0.05, 0.0), (-0.5, 0.0, -0.02)])
def test_a_true_loop_is_not_held_back_by_an_estimate_that_is_off(offset):
    """The same corridor mapped all around the scan (range 8 m, from -1 ≤ x ≤ 1): where the estimate
    is 0.3–0.5 m off, the match moves the node back to the true pose, and on the points both poses
    put on observed cells the true pose scores higher, so the loop is accepted."""
    segs = _corridor_with_stubs()
    m = SubmapMatcher(submap(segs, [np.array([x, 0.0, 0.0]) for x in np.linspace(-1, 1, 7)], max_range=8.0), 4,
                      field_sigma=0.1)
    truth = np.zeros(3)
    res = m.match(scan_points(segs, truth, 8.0), truth + offset, 0.7, math.radians(3), 0.3, REFINE, 0.02,
                  (0.6, math.radians(2)), (0.2, math.radians(1)), estimate=True)
    assert res.reason is None, res.reason
    assert np.hypot(*res.pose[:2]) < 0.05


@pytest.mark.parametrize("remote", [False, True], ids=["in_process", "solver_process"])
def test_a_heading_constraint_turns_the_map_without_pulling_it(remote):
    """A straight chain that local SLAM bent by 8° halfway: a heading constraint between its ends with a
    translation 40 m off (it says nothing there) turns the second half back, moves no node along its
    translation, and is not removed for its translation residual; a loop with the same numbers is."""
    from slam2d.backend.pose_graph import PoseGraph
    from slam2d.backend.solver_process import RemotePoseGraph

    n, kink = 40, math.radians(8.0)
    est = [np.zeros(3)]
    for k in range(1, n):
        est.append(compose(est[-1], [1.0, 0.0, kink if k == n // 2 else 0.0]))
    bad = between(est[0], est[-1]) + [40.0, -30.0, 0.0]
    bad[2] = 0.0  # the true relative heading: the chain is straight
    for heading_only, kept in ((True, True), (False, False)):
        g = (RemotePoseGraph if remote else PoseGraph)(huber_scale=5.0, max_residual_trans=0.2,
                                                      max_residual_rot=math.radians(1.0))
        for k, p in enumerate(est):
            g.add_node(k, p)
            if k:  # tight steps, but for the kinked one, which local SLAM could not vouch for
                loose = math.radians(10.0) if k == n // 2 else math.radians(0.05)
                g.add_intra(k - 1, k, between(est[k - 1], est[k]), np.diag([1e-4, 1e-4, loose ** 2]))
        rec = {}
        cov = np.diag([1e6, 1e6, math.radians(0.3) ** 2]) if heading_only else np.diag([1e-4, 1e-4, math.radians(0.3) ** 2])
        g.add_loop(0, n - 1, bad, cov, rec, heading_only=heading_only)
        g.optimize()
        if hasattr(g, "close"):
            ids, poses = g.all_node_poses()
            g.close()
        else:
            ids, poses = g.all_node_poses()
        assert (len(g.loops) == 1) is kept, (heading_only, rec)
        if heading_only:
            assert abs(math.degrees(math.remainder(poses[-1][2] - poses[0][2], 2 * math.pi))) < 0.5  # turned back
            # the second half turned about the kink, the steps kept their lengths: no pull along the 40 m
            steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
            assert np.allclose(steps, 1.0, atol=1e-3)
            assert np.max(np.abs(poses[:, 1])) < 0.05  # straight again, on the x axis


def test_confirmed_loops_close_consistent_cycles_with_enough_others_and_contradict_none():
    from slam2d.backend.consistency import PairTests, confirmed, support

    pairs = [(0, 1, True), (0, 2, True), (1, 2, True), (2, 3, False)]
    src = np.array([a for a, b, _ in pairs] + [b for a, b, _ in pairs])
    dst = np.array([b for a, b, _ in pairs] + [a for a, b, _ in pairs])
    ok = np.array([c for _, _, c in pairs] * 2)
    t = PairTests(4, src, dst, ok)
    everyone = np.ones(4, bool)
    pos, neg = support(t, everyone)
    assert pos.tolist() == [2, 2, 2, 0] and neg.tolist() == [0, 0, 1, 1]
    # 2 is contradicted by 3, 3 confirmed by nobody
    assert confirmed(t, everyone, 2).tolist() == [True, True, False, False]
    # a removed loop neither confirms nor contradicts, and is not confirmed itself
    left = np.array([True, False, True, True])  # 1 removed: 0 and 2 keep one partner each
    assert confirmed(t, left, 2).tolist() == [False, False, False, False]
    assert confirmed(t, left, 1).tolist() == [True, False, False, False]  # 2 still contradicted by 3
    left[3] = False
    assert confirmed(t, left, 1).tolist() == [True, False, True, False]
    assert not confirmed(t, everyone, 0).any()  # 0: no loop is spared the residual check


@pytest.mark.parametrize("support", [2, 0])
def test_global_slam_spares_the_loops_the_consistency_check_confirms_from_the_residual_check(support):
    cfg = SlamConfig()
    cfg.loop_closure.residual_exempt_support = support
    scans = list(McapLog(BUNDLED))
    slam = Slam(cfg)
    gs = slam.global_slam
    optimize, calls = gs.graph.optimize, []

    def watched(*args, exempt=(), **kw):
        live = {f.index for f in gs.graph.loops if not f.heading_only}
        calls.append((list(exempt), live))
        return optimize(*args, exempt=exempt, **kw)

    gs.graph.optimize = watched
    slam.run(scans)
    assert calls
    if support == 0:
        assert all(not ex for ex, _ in calls)
    else:
        assert any(ex for ex, _ in calls)
        assert all(set(ex) <= live for ex, live in calls)  # loops in the graph, and never heading constraints


def test_a_cluster_of_mutually_consistent_false_loops_is_not_spared_from_the_residual_check():
    """Three false loops with the same error on nearby nodes of one submap (the kind that can agree
    with each other): the true loops around them contradict them, so none is confirmed and spared by
    the residual check (``residual_exempt_support``, on by default), and none stays in the final graph."""

    def nearby(rec, injected):  # up to three, in the first one's submap, each within 20 scans of the last
        return len(injected) < 3 and (not injected or (rec["submap"] == injected[0]["submap"]
                                                        and rec["to_scan"] - injected[-1]["to_scan"] <= 20))

    gt, gs, injected = _run_with_false_loops(SlamConfig(), nearby)
    assert len(injected) == 3, "no three nearby true loops to copy"
    assert all(agrees(gt, f, 0.3, 2.0) is False for f in injected)
    assert all(f["in_final_graph"] is False for f in injected), [f["reason"] for f in injected]
    final = [r for r in gs.records if r.get("in_final_graph")]
    assert len(final) >= 20 and all(agrees(gt, r, 0.3, 2.0) for r in final)
