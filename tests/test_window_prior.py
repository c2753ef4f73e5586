"""The odometry's prior in the real-time matcher (``real_time_matcher.window_sigmas``).

A scanner whose range ends inside a corridor sees, at its true pose, the newest stretch of the
walls on cells no scan has observed; slid back one step those points land on mapped wall and
score higher, while Cartographer's delta penalty costs the slide almost nothing. The prior keeps
the prediction there and still lets a clear fit move the pose.
"""
import math

import numpy as np
import pytest

from slam2d.config import RealTimeMatcherConfig
from slam2d.grid.probability_grid import ProbabilityGrid
from slam2d.io.simulator import SimConfig, raycast, simulate
from slam2d.matching import _kernels
from slam2d.matching.real_time import RealTimeCorrelativeScanMatcher
from slam2d.matching.search import MatchGrid

FOV = np.radians(np.linspace(-120.0, 120.0, 683))  # a 240°, 5.6 m scanner
MAX_RANGE = 5.6
STEP = 0.08  # 0.8 m/s at 10 Hz
#: two walls along x at y = ±1 m, their ends far out of range, with door gaps on either side
WALLS = np.array([[-50.0, 1.0, 3.0, 1.0], [3.9, 1.0, 9.0, 1.0], [9.9, 1.0, 50.0, 1.0],
                  [-50.0, -1.0, 6.0, -1.0], [6.9, -1.0, 50.0, -1.0]])


def scan_points(pose, rng):
    r = raycast(WALLS, pose[:2], FOV + pose[2], MAX_RANGE) + rng.normal(0.0, 0.01, len(FOV))
    ok = np.isfinite(r) & (r < MAX_RANGE)
    return np.stack([r[ok] * np.cos(FOV[ok]), r[ok] * np.sin(FOV[ok])], axis=1)


def corridor_submap(n_scans, rng):
    """A likelihood-field submap built from ``n_scans`` scans one step apart along the corridor."""
    g = ProbabilityGrid(0.05, field_sigma=0.1)
    for k in range(n_scans):
        origin = np.array([k * STEP, 0.0])  # heading 0: the scan's frame is the grid's, shifted
        g.insert(origin, origin + scan_points(np.array([*origin, 0.0]), rng))
    return MatchGrid(g.field, g.origin, g.resolution, 0.0)


def _match(window_sigmas, predicted, truth, seed=0):
    rng = np.random.default_rng(seed)
    grid = corridor_submap(12, rng)
    pts = scan_points(truth, rng)
    m = RealTimeCorrelativeScanMatcher(0.3, math.radians(10.0), 0, 0.1, 0.1)
    lin = 0.05 + 0.7 * STEP  # the frontend's window for this motion
    return m.match(grid, np.asarray(predicted, float), pts, linear_window=lin, angular_window=math.radians(1.0),
                   prior_sigma=lin / window_sigmas if window_sigmas else 0.0)


def test_translation_prior_matches_oracle():
    rng = np.random.default_rng(4)
    w, res, n = 4, 0.05, 120.0
    scores = rng.uniform(0.2, 0.9, (5, 2 * w + 1, 2 * w + 1)).astype(np.float32)
    got = scores.copy()
    _kernels.apply_translation_prior(got, res, 0.04, n)
    offs = np.arange(-w, w + 1) * res
    d2 = offs[None, :] ** 2 + offs[:, None] ** 2
    factor = np.exp(-d2 / (2 * 0.04 ** 2 * n))
    np.testing.assert_allclose(got, scores * factor[None], rtol=1e-6)
    np.testing.assert_array_equal(got[:, w, w], scores[:, w, w])  # the predicted position keeps its scores


def test_a_short_range_scan_in_a_corridor_slides_back_without_the_prior():
    """The bias itself: the true pose one step beyond the last mapped scan, predicted exactly.
    Without the prior the match lands about a step back; with it, within a cell of the truth."""
    truth = np.array([12 * STEP, 0.0, 0.0])
    off = _match(0.0, truth, truth)
    on = _match(3.0, truth, truth)
    assert truth[0] - off.pose[0] >= 0.05, off.pose  # slid back onto mapped ground
    assert abs(on.pose[0] - truth[0]) <= 0.05 and abs(on.pose[1]) <= 0.05, on.pose


@pytest.mark.parametrize("dy", [-0.1, 0.1])
def test_the_prior_still_lets_a_clear_fit_move_the_pose(dy):
    """A prediction 0.1 m off across the corridor (the walls decide that direction): the match
    returns to the truth with the prior on."""
    truth = np.array([12 * STEP, 0.0, 0.0])
    on = _match(3.0, truth + [0.0, dy, 0.0], truth)
    assert abs(on.pose[1] - truth[1]) <= 0.025, on.pose


def test_the_prior_needs_the_exhaustive_search():
    with pytest.raises(ValueError):
        RealTimeMatcherConfig(window_sigmas=3.0, branch_depth=2)
    with pytest.raises(ValueError, match="window_sigmas: 0 for the coarse-to-fine search"):
        RealTimeMatcherConfig(branch_depth=2)  # the prior is on by default: the error says what to set
    RealTimeMatcherConfig(window_sigmas=0.0, branch_depth=2)
    m = RealTimeCorrelativeScanMatcher(0.3, 0.1, 2)
    grid = MatchGrid(np.zeros((20, 20), np.float32), np.zeros(2), 0.05, 0.0)
    with pytest.raises(ValueError):
        m.match(grid, np.zeros(3), np.ones((5, 2)), prior_sigma=0.1)


def test_simulator_field_of_view():
    full = next(simulate(SimConfig(seed=1)))
    assert full.angle_min == pytest.approx(-math.pi) and full.angle_increment == pytest.approx(2 * math.pi / 360)
    part = next(simulate(SimConfig(seed=1, beams=683, fov_deg=240.0)))
    last = part.angle_min + part.angle_increment * (len(part.ranges) - 1)
    assert len(part.ranges) == 683
    assert part.angle_min == pytest.approx(-math.radians(120.0)) and last == pytest.approx(math.radians(120.0))


def _local_run(window_sigmas, use_odometry=True, n=150):
    """Local SLAM alone over the simulator's first ``n`` scans with a 240°, 5.6 m scanner at 5 Hz:
    (error of the net motion along x, summed translation error of the steps) against the truth."""
    from slam2d.config import config_from_dict
    from slam2d.frontend import LocalSlam
    from slam2d.geometry import between

    scans = list(simulate(SimConfig(seed=3, beams=667, fov_deg=240.0, max_range=MAX_RANGE, rate_hz=5.0,
                                    range_sigma=0.02)))[:n]
    cfg = config_from_dict({"real_time_matcher": {"window_sigmas": window_sigmas, "use_odometry": use_odometry}})
    tracker = LocalSlam(cfg, loop_closure=True)
    poses = [tracker.add_scan(s).local_pose for s in scans]
    truth = [s.ground_truth for s in scans]
    steps = sum(math.hypot(*between(between(truth[i - 1], truth[i]), between(poses[i - 1], poses[i]))[:2])
                for i in range(1, n))
    net = between(between(truth[0], truth[-1]), between(poses[0], poses[-1]))
    return float(net[0]), steps, np.array(poses)


def test_local_slam_keeps_up_along_corridors_with_a_short_range_scanner():
    """The simulator's office with a 240°, 5.6 m scanner: without the prior local SLAM loses metres
    of travel along its corridors (matched a step short, scan after scan); with it most of that
    goes."""
    off_net, off_steps, _ = _local_run(0.0)
    on_net, on_steps, _ = _local_run(3.0)
    assert off_net < -5.0, off_net
    assert abs(on_net) < 0.25 * abs(off_net) and on_steps < 0.35 * off_steps, (on_net, on_steps, off_net, off_steps)


def test_a_prediction_without_odometry_gets_no_prior():
    *_, a = _local_run(0.0, use_odometry=False, n=60)
    *_, b = _local_run(3.0, use_odometry=False, n=60)
    np.testing.assert_array_equal(a, b)


def test_the_prior_makes_no_peak_of_scores_rising_to_the_edge():
    """Scores that rise all the way to the window's edge (the true pose lies beyond it) peak
    inside the window once the prior multiplies them; ``scan_on_edge`` keeps what the scan said."""
    values = np.tile(np.linspace(0.2, 0.9, 60, dtype=np.float32), (60, 1))  # rises along +x
    grid = MatchGrid(values, np.zeros(2), 0.05, 0.0)
    pts = np.c_[np.zeros(5), np.linspace(-0.1, 0.1, 5)]
    m = RealTimeCorrelativeScanMatcher(0.5, 0.0, 0)
    predicted = np.array([1.5, 1.5, 0.0])
    plain = m.match(grid, predicted, pts, linear_window=0.5, angular_window=0.0)
    assert plain.on_edge and plain.scan_on_edge and plain.pose[0] == pytest.approx(2.0)
    prior = m.match(grid, predicted, pts, linear_window=0.5, angular_window=0.0, prior_sigma=0.3)
    assert 1.5 < prior.pose[0] < 1.99  # the posterior peaks inside the window (in x) ...
    assert prior.scan_on_edge  # ... which the scan's own scores do not


def test_a_low_fit_the_prior_pulled_off_the_edge_goes_to_the_recovery_search(monkeypatch):
    """Local SLAM treats such a peak as on the edge when its score is below the trust limit (as
    it would without the prior: a recovery search, not a weak match at the peak)."""
    from slam2d.config import config_from_dict
    from slam2d.frontend import LocalSlam
    from slam2d.io.source import open_source
    from conftest import BUNDLED

    scans = []
    for s in open_source(BUNDLED):
        scans.append(s)
        if len(scans) == 40:
            break
    tracker = LocalSlam(config_from_dict({"real_time_matcher": {"window_sigmas": 3.0}}), loop_closure=True)
    for s in scans[:39]:
        tracker.add_scan(s)
    assert tracker._typical_score() is not None
    real = tracker.matcher.match

    def pulled_off_the_edge(*args, **kwargs):
        r = real(*args, **kwargs)
        r.score, r.on_edge, r.scan_on_edge = 0.1, False, True  # a low fit the prior made a peak of
        return r

    monkeypatch.setattr(tracker.matcher, "match", pulled_off_the_edge)
    before = tracker.num_recovery_searches
    res = tracker.add_scan(scans[39])
    assert tracker.num_recovery_searches == before + 1
    assert res.quality != "weak"
