"""The raw-scan check of loop constraints the ground truth calls false (slam2d/eval/scan_check.py)."""
import math

import numpy as np
import pytest

from slam2d.eval.scan_check import MIN_SHARE, check_disagreements, overlap_share, register, registered_verdict, verdict
from slam2d.geometry import between, compose, transform_points


def _segments_points(segments, step=0.02):
    pts = []
    for (x0, y0), (x1, y1) in segments:
        n = max(2, int(math.hypot(x1 - x0, y1 - y0) / step))
        t = np.linspace(0.0, 1.0, n)
        pts.append(np.c_[x0 + t * (x1 - x0), y0 + t * (y1 - y0)])
    return np.concatenate(pts)


def _scan(world, pose, reach=8.0, rng=None):
    """The world points within ``reach`` of ``pose``, in its frame (with 1 cm noise)."""
    d = np.hypot(world[:, 0] - pose[0], world[:, 1] - pose[1])
    w = world[d < reach]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx, dy = w[:, 0] - pose[0], w[:, 1] - pose[1]
    local = np.c_[c * dx + s * dy, -s * dx + c * dy]
    return local + (rng.normal(0, 0.01, local.shape) if rng is not None else 0.0)


ROOM = [((-6, -4), (6, -4)), ((6, -4), (6, 4)), ((6, 4), (-6, 4)), ((-6, 4), (-6, -4)),
        ((-2, -1), (-1, -1)), ((-1, -1), (-1, 0)), ((2, 1), (3, 2)), ((0, 2), (0, 3.2)), ((-4, -2), (-3, -3))]
CORRIDOR = [((-60, -1), (60, -1)), ((-60, 1), (60, 1))]


def _place(world, rng):
    """Scans 0..20 along a path, then scan 21 back near scan 10: (hits by scan, true poses)."""
    poses = np.array([[-4.0 + 0.4 * k, 0.3 * math.sin(k / 3), 0.05 * k] for k in range(21)]
                     + [[0.15, 0.4, 2.5]])
    return {k: _scan(world, p, rng=rng) for k, p in enumerate(poses)}, poses


@pytest.mark.parametrize("shift", [(0.5, 0.0, 0.0), (0.0, 0.0, math.radians(5.0)), (0.3, -0.3, math.radians(2))])
def test_the_scans_side_with_the_hypothesis_that_lines_them_up(shift):
    """Scan 21 comes back to scan 10's place. The true relative pose lines the scans up; one that is
    off by 0.5 m or 5° does not. Whichever side (constraint or ground truth) holds the true pose, the
    verdict names it; the check has no favourite."""
    rng = np.random.default_rng(1)
    hits, truth = _place(_segments_points(ROOM), rng)
    wrong = truth.copy()
    wrong[21] = compose(truth[21], np.array(shift))
    rel_true, rel_wrong = between(truth[10], truth[21]), between(wrong[10], wrong[21])
    good = overlap_share(hits, truth, 10, 21, rel_true, 0.1)
    bad = overlap_share(hits, wrong, 10, 21, rel_wrong, 0.1)
    assert good > 0.9 and bad < 0.5 * good
    assert verdict(good, bad) == "constraint" and verdict(bad, good) == "ground_truth"


def test_a_small_rotation_seen_at_short_range_is_undecided():
    """1° moves points 8 m away by 14 cm and near ones by less: part of the scan still lines up, so
    the scans do not take a side (a verdict needs twice the other's share)."""
    rng = np.random.default_rng(5)
    hits, truth = _place(_segments_points(ROOM), rng)
    wrong = truth.copy()
    wrong[21] = compose(truth[21], np.array([0.0, 0.0, math.radians(1.0)]))
    a = overlap_share(hits, truth, 10, 21, between(truth[10], truth[21]), 0.1)
    b = overlap_share(hits, wrong, 10, 21, between(wrong[10], wrong[21]), 0.1)
    assert a > b and verdict(a, b) == "undecided"


def test_a_featureless_corridor_leaves_it_undecided():
    """Along a corridor without features, a pose 0.5 m further along lines the walls up as well: the
    scans cannot tell, and the verdict says so instead of taking a side."""
    rng = np.random.default_rng(2)
    hits, truth = _place(_segments_points(CORRIDOR), rng)
    truth[:, 1] = 0.0
    truth[:, 2] = 0.0
    hits = {k: _scan(_segments_points(CORRIDOR), p, rng=rng) for k, p in enumerate(truth)}
    along = truth.copy()
    along[21, 0] += 0.5
    a = overlap_share(hits, truth, 10, 21, between(truth[10], truth[21]), 0.1)
    b = overlap_share(hits, along, 10, 21, between(along[10], along[21]), 0.1)
    assert a > 0.9 and b > 0.9
    assert verdict(a, b) == "undecided" and verdict(b, a) == "undecided"


def test_too_little_overlap_or_unknown_poses_decide_nothing():
    assert verdict(0.25, 0.0) == "undecided"  # below MIN_SHARE, however far ahead
    assert verdict(MIN_SHARE, 0.1) == "constraint" and verdict(0.1, MIN_SHARE) == "ground_truth"
    assert verdict(None, 0.9) == "undecided" and verdict(0.9, None) == "undecided"
    rng = np.random.default_rng(3)
    hits, truth = _place(_segments_points(ROOM), rng)
    gone = truth.copy()
    gone[8:13] = np.nan  # the place's poses unknown
    assert overlap_share(hits, gone, 10, 21, between(truth[10], truth[21]), 0.1) is None
    assert overlap_share({}, truth, 10, 21, between(truth[10], truth[21]), 0.1) is None


def test_only_final_graph_constraints_the_ground_truth_calls_false_are_checked():
    rng = np.random.default_rng(4)
    hits, truth = _place(_segments_points(ROOM), rng)
    off = truth.copy()
    off[21] = compose(truth[21], np.array([0.6, 0.0, 0.0]))  # the "ground truth" is wrong at the revisit
    rel = [float(v) for v in between(truth[10], truth[21])]

    def c(**kw):
        base = {"from_scan": 10, "to_scan": 21, "relative_pose": rel, "accepted": True, "in_final_graph": True,
                "true_gt": False}
        return {**base, **kw}

    cs = [c(), c(true_gt=True), c(in_final_graph=False), c(accepted=False), c(true_gt=None)]
    counts = check_disagreements(cs, hits, truth, off, 0.1)
    assert counts == {"constraint": 1, "ground_truth": 0, "both": 0, "undecided": 0}
    assert cs[0]["scan_check"]["verdict"] == "constraint" and cs[0]["scan_check"]["share_constraint"] > 0.9
    assert all("scan_check" not in x for x in cs[1:])
    # the other way round: a constraint that is off, against a right ground truth
    wrong = [c(relative_pose=[float(v) for v in between(off[10], off[21])])]
    assert check_disagreements(wrong, hits, off, truth, 0.1) == {"constraint": 0, "ground_truth": 1, "both": 0,
                                                                 "undecided": 0}


@pytest.mark.parametrize("offset", [(0.3, -0.2, math.radians(3.0)), (-0.4, 0.1, math.radians(-4.0)), (0.0, 0.0, 0.0)])
def test_registration_lays_the_revisit_onto_the_place(offset):
    """Point-to-line ICP from a start 0.3-0.4 m and 3-4° off ends at the true relative pose of scan 21
    to scan 10 (within 2 cm and 0.2°: 1 cm range noise), and stays there when started on it."""
    rng = np.random.default_rng(6)
    hits, truth = _place(_segments_points(ROOM), rng)
    rel = between(truth[10], truth[21])
    place = np.concatenate([transform_points(between(truth[10], truth[m]), hits[m]) for m in range(8, 13)])
    got = register(hits[21], place, compose(rel, np.array(offset)), 0.1)
    err = between(rel, got)
    assert math.hypot(err[0], err[1]) < 0.02 and abs(math.degrees(err[2])) < 0.2, err
    assert register(hits[21], place[:3], rel, 0.1) is None  # nothing to lay it onto


def _revisit_hypotheses(constraint_deg, truth_deg):
    """The room revisit with a constraint and a ground truth that turn scan 21 by the given angles
    about its true pose: (hits, run poses, ground-truth poses, the constraint's relative pose)."""
    rng = np.random.default_rng(7)
    hits, truth = _place(_segments_points(ROOM), rng)
    run, gt = truth.copy(), truth.copy()
    run[21] = compose(truth[21], np.array([0.0, 0.0, math.radians(constraint_deg)]))
    gt[21] = compose(truth[21], np.array([0.0, 0.0, math.radians(truth_deg)]))
    return hits, run, gt, between(run[10], run[21])


def test_registration_names_the_hypothesis_the_scans_support():
    """The loop evaluation's tolerance is 2°. A constraint on the true pose against a ground truth 4°
    off: the scans' registration sides with the constraint; the other way round, with the ground
    truth; 1.2° either side of the truth (2.4° apart, "false" by the tolerance): both fit."""
    hits, run, gt, rel = _revisit_hypotheses(0.0, 4.0)
    v, scans = registered_verdict(hits, run, gt, 10, 21, rel, 0.1, (0.3, 2.0))
    assert v == "constraint" and scans is not None
    hits, run, gt, rel = _revisit_hypotheses(4.0, 0.0)
    assert registered_verdict(hits, run, gt, 10, 21, rel, 0.1, (0.3, 2.0))[0] == "ground_truth"
    hits, run, gt, rel = _revisit_hypotheses(1.2, -1.2)
    assert registered_verdict(hits, run, gt, 10, 21, rel, 0.1, (0.3, 2.0))[0] == "both"
    # a tighter tolerance than the hypotheses' distance to the truth: neither fits
    assert registered_verdict(hits, run, gt, 10, 21, rel, 0.1, (0.3, 0.5))[0] == "undecided"


def test_registration_along_a_featureless_corridor_decides_nothing():
    """Along the corridor the registration stays where each start put it (nothing pulls along the
    walls), so the two starts end 0.5 m apart and the verdict is undecided, not a side."""
    rng = np.random.default_rng(8)
    world = _segments_points(CORRIDOR)
    truth = np.array([[-4.0 + 0.4 * k, 0.0, 0.0] for k in range(21)] + [[0.15, 0.0, 0.0]])
    hits = {k: _scan(world, p, rng=rng) for k, p in enumerate(truth)}
    along = truth.copy()
    along[21, 0] += 0.5
    v, scans = registered_verdict(hits, truth, along, 10, 21, between(truth[10], truth[21]), 0.1, (0.3, 2.0))
    assert v == "undecided" and scans is None


def test_an_undecided_share_goes_to_the_registration():
    """1° at short range ties the shares (``test_a_small_rotation_seen_at_short_range_is_undecided``);
    4° against the truth in a room does not need the registration, 2.4° apart around it does: the
    check then records the registration's verdict and pose."""
    hits, run, gt, rel = _revisit_hypotheses(1.2, -1.2)
    c = {"from_scan": 10, "to_scan": 21, "relative_pose": [float(v) for v in rel], "accepted": True,
         "in_final_graph": True, "true_gt": False}
    counts = check_disagreements([c], hits, run, gt, 0.1)
    assert counts == {"constraint": 0, "ground_truth": 0, "both": 1, "undecided": 0}
    assert c["scan_check"]["by"] == "registration" and len(c["scan_check"]["registered"]) == 3
