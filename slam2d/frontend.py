"""Local SLAM (Cartographer's ``LocalTrajectoryBuilder2D``; Hess et al. 2016, Sec. IV).

Per scan: pose extrapolation (wheel odometry increment when present, else constant
velocity) → range filter and voxel filter → real-time correlative scan match against the
older active submap (Olson 2009) → continuous refinement → motion filter → insertion into
both active submaps. Every scan gets a matched ``local_pose``; only scans that pass the
motion filter are inserted and become nodes.

Submap size depends on whether a pose graph follows. Without one, nothing corrects the
drift between submaps, and a revisit is tied to the earlier pass only when both fall in
one submap; ``submaps.num_range_data_without_loop_closure`` (400) is therefore larger
than the 90 global SLAM uses, where small rigid submaps let the graph bend. Both sizes were
chosen on the relations metric with ``tools/spread.py`` (the world rotated by small angles, a
null change that shows the run-to-run spread); the figures are in the README, "Measurements
behind the defaults".
"""
from __future__ import annotations

import logging
import math
import statistics
import time
from collections import deque

import numpy as np

from slam2d._kernels import tangent_moments
from slam2d.config import SlamConfig
from slam2d.geometry import between, compose
from slam2d.grid.submap import ActiveSubmaps
from slam2d.types import MatchingResult
from slam2d.matching.observed import observed_scores
from slam2d.matching.real_time import RealTimeCorrelativeScanMatcher
from slam2d.matching.refine import refine
from slam2d.matching.search import SearchParameters, angular_step
from slam2d.motion_filter import MotionFilter
from slam2d.range_data import SAME_SURFACE_GAP, range_data, voxel_filter_index
from slam2d.threads import CallerCores

log = logging.getLogger(__name__)

#: the typical score is the median of this many recent trusted matches ...
RECENT_SCORES = 50
#: ... and judges matches once this many exist (before that every match is trusted)
MIN_SCORES_FOR_TRUST = 10
#: the largest real-time translation window covers this many standard deviations of the prediction's measured error
WINDOW_SIGMAS = 3.0


#: the velocity is measured over at least this share of the log's typical scan period ...
VELOCITY_MIN_SPAN = 0.5
#: ... the typical period being the mean of this many recent ones; and the poses it may reach back to
VELOCITY_HISTORY = 16


class PoseExtrapolator:
    """Predicts the next local pose from odometry increments, or from the recent velocity.

    The velocity (Cartographer's ``PoseExtrapolator`` without odometry) is the motion between the
    newest trusted pose and the most recent earlier one at least ``VELOCITY_MIN_SPAN`` of the
    typical scan period before it, over the time between them: logs carry scans stamped a
    millisecond apart (Intel: bursts, reordered and repeated stamps), and the motion between two
    such scans is matching noise divided by almost nothing, which constant-velocity prediction
    would carry metres into the next scan. Poses that are not trusted matches leave the velocity
    as it was (``add``). ``max_turn_rate`` and ``max_speed`` are the fastest turn and the fastest
    translation a velocity has measured so far, and ``measured_time`` and ``measured_pose`` the
    time and pose of the last trusted match: without odometry, what the robot can have turned
    since (``LocalSlam._recovery_rotation``) and how far it can have gone
    (``LocalSlam._reachable``)."""

    def __init__(self):
        self.last_pose = None
        self.last_time = None
        self.last_odom = None
        self.velocity = np.zeros(3)  # in the robot frame, per second
        self.max_turn_rate = 0.0  # the largest |velocity θ| so far [rad/s]
        self.max_speed = 0.0  # the largest |velocity x, y| so far [m/s]
        self._history: deque = deque(maxlen=VELOCITY_HISTORY)  # (time, pose), oldest first
        self._periods: deque = deque(maxlen=VELOCITY_HISTORY)

    def predict(self, time_s, odom):
        if self.last_pose is None:
            return np.zeros(3) if odom is None else np.asarray(odom, dtype=float).copy()
        if odom is not None and self.last_odom is not None:
            return compose(self.last_pose, between(self.last_odom, odom))
        dt = max(time_s - self.last_time, 0.0)
        return compose(self.last_pose, self.velocity * dt)

    @property
    def measured_time(self) -> float | None:
        """The time of the last trusted pose (None before the first)."""
        return self._history[-1][0] if self._history else None

    @property
    def measured_pose(self) -> np.ndarray | None:
        """The pose of the last trusted match (None before the first)."""
        return self._history[-1][1] if self._history else None

    def from_odometry(self, odom) -> bool:
        """Whether ``predict`` with this odometry reading measures the motion (odometry increments),
        rather than assuming it (constant velocity)."""
        return odom is not None and self.last_odom is not None and self.last_pose is not None

    def motion(self, predicted) -> np.ndarray:
        """The predicted motion since the last pose, in the last pose's frame."""
        if self.last_pose is None:
            return np.zeros(3)
        return between(self.last_pose, predicted)

    def add(self, time_s, pose, odom, measured: bool = True):
        """The pose of the scan at ``time_s``. ``measured`` False: the pose is not a trusted match
        (the prediction itself, or a weak or forced placement): the velocity is left as it was,
        since a prediction would only confirm it and a doubtful jump would be carried on."""
        pose = np.asarray(pose, dtype=float)
        if self.last_time is not None and time_s > self.last_time:
            self._periods.append(time_s - self.last_time)
        if measured and (not self._history or time_s > self._history[-1][0]):
            if self._history:
                # the mean period: bursts of scans stamped a millisecond apart (Intel) can make up
                # most recent periods, and would pull a median down to them
                span = VELOCITY_MIN_SPAN * sum(self._periods) / len(self._periods) if self._periods else 0.0
                # the most recent earlier pose far enough back in time (else the oldest kept)
                t0, p0 = next(((t, p) for t, p in reversed(self._history) if time_s - t >= span), self._history[0])
                # in the older pose's frame, applied from the newest: right for a constant twist
                self.velocity = between(p0, pose) / (time_s - t0)
                self.max_turn_rate = max(self.max_turn_rate, abs(float(self.velocity[2])))
                self.max_speed = max(self.max_speed, math.hypot(float(self.velocity[0]), float(self.velocity[1])))
            self._history.append((time_s, pose))
        self.last_pose, self.last_time, self.last_odom = pose, time_s, odom


#: a translation direction is degenerate when the scan's information along it is below this share of the other's
DEGENERATE_RATIO = 0.01
#: a point's tangent runs between its k-th neighbours on either side (the smallest k of these)
#: that lie between NORMAL_MIN_BASELINE (shorter baselines are dominated by range noise) and
#: NORMAL_NEIGHBOUR_GAP (farther apart they lie on different surfaces) [m]
NORMAL_NEIGHBOURS = (1, 2, 4, 8)
NORMAL_MIN_BASELINE = 0.15
NORMAL_NEIGHBOUR_GAP = SAME_SURFACE_GAP
_NEIGHBOURS = np.array(NORMAL_NEIGHBOURS)  # as the kernel takes them, made once


def degenerate_direction(points: np.ndarray) -> np.ndarray | None:
    """The unit x/y direction (tracking frame) along which the scan's geometry does not constrain
    its translation, else None.

    Point-to-line information of the scan (Zhang, Kaess, Singh 2016, "On degeneracy of
    optimization-based state estimation problems"): each point's surface normal, from its
    neighbours in beam order, constrains translation along that normal; Σ n nᵀ with one
    eigenvalue far below the other means a corridor without visible ends, where matching can
    only slide along the walls.
    """
    if len(points) < 10:
        return None
    # per point, the nearest neighbours far enough apart (numba kernel; its numpy oracle is in the tests)
    n, sxx, sxy, syy = tangent_moments(np.ascontiguousarray(points, dtype=np.float64), _NEIGHBOURS,
                                       NORMAL_MIN_BASELINE, NORMAL_NEIGHBOUR_GAP)
    if n < 10:
        return None
    # the information [[Σ ty², −Σ tx·ty], [−Σ tx·ty, Σ tx²]] / n and its eigen-decomposition in closed form
    a, b, c = syy / n, -sxy / n, sxx / n
    mid, half = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    low, high = mid - half, mid + half
    if low >= DEGENERATE_RATIO * high:
        return None
    # (A − low·I) v = 0: v ∥ (b, low − a) and ∥ (low − c, b); the longer of the two is the stabler
    v = (b, low - a) if abs(a - low) >= abs(c - low) else (low - c, b)
    norm = math.hypot(*v)
    return np.array([v[0] / norm, v[1] / norm]) if norm > 0.0 else None


class LocalSlam:
    name = "local"

    def __init__(self, cfg: SlamConfig, observer=None, loop_closure: bool | None = None):
        """``loop_closure``: whether a pose graph follows (default: ``cfg.loop_closure.enabled``); it picks the submap size."""
        self.cfg = cfg
        self.extrapolator = PoseExtrapolator()
        rt = cfg.real_time_matcher
        sigma = rt.likelihood_field_sigma if rt.score_grid == "likelihood_field" else None
        if loop_closure is None:
            loop_closure = cfg.loop_closure.enabled
        sm = cfg.submaps
        size = sm.num_range_data if loop_closure else sm.num_range_data_without_loop_closure
        self.submaps = ActiveSubmaps(cfg.grid, size, field_sigma=sigma, max_travel=sm.max_travel * size / sm.num_range_data)
        self.filter = MotionFilter(cfg.motion_filter)
        self.matcher = RealTimeCorrelativeScanMatcher(rt.linear_search_window, math.radians(rt.angular_search_window_deg),
                                                      rt.branch_depth, rt.translation_delta_cost_weight,
                                                      rt.rotation_delta_cost_weight)
        self.finished_submaps = []
        self.observer = observer
        self.num_matched = 0
        self.num_inserted = 0
        self.num_escalated = 0
        self.num_recovery_searches = 0
        self.num_recovered = 0
        self.num_untrusted = 0
        self.cores = CallerCores()  # who else wants the cores (``Slam`` sets it when global SLAM runs beside)
        self.num_forced = 0
        self.num_degenerate = 0
        self.num_weak = 0
        self.num_still = 0
        self._still_ref = None  # the last scan matched and trusted (``_still``): odometry, pose, match, score
        self.still_matcher = RealTimeCorrelativeScanMatcher(cfg.grid.resolution, 0.0, 0, rt.translation_delta_cost_weight,
                                                            rt.rotation_delta_cost_weight)
        self._vain_search_at = None  # where a recovery for a low-scoring peak found nothing (``_searched_in_vain``)
        self.num_recovery_skipped = 0
        self.num_unsupported_jumps = 0
        self._stalled_at = None  # the odometry reading at which the stream stalled (``_odometry_reading``)
        self.num_odometry_stalls = 0
        self.num_odometry_stalled_scans = 0
        self.untrusted_in_a_row = 0
        self._doubt = np.zeros(2)  # MatchingResult.doubt, gathered until the next insertion
        self._carried = np.zeros(2)  # distance, |rotation| of the motion since the last pose that was not carried from a prediction
        self.scores: list[float] = []
        self.recent_scores: deque[float] = deque(maxlen=RECENT_SCORES)
        # how far trusted matches lay from their prediction [m]: the prediction's measured error
        self.recent_errors: deque[float] = deque(maxlen=RECENT_SCORES)
        w = rt.recovery_linear_window
        depth = min(6, max(1, math.ceil(math.log2(2 * math.ceil(w / cfg.grid.resolution) + 1)) - 1))
        # the recovery's precomputation pools the whole submap each time: over uint8 it moves a quarter
        # of the memory (its peak is then scored on the float grid by the fine search around it)
        self.wide_matcher = RealTimeCorrelativeScanMatcher(w, math.radians(rt.recovery_angular_window_deg), depth,
                                                           rt.translation_delta_cost_weight, rt.rotation_delta_cost_weight,
                                                           quantize=True)

    def windows(self, motion) -> tuple[float, float]:
        """Search half-widths (m, rad) from the predicted motion: the prediction's error grows with
        the distance and the angle travelled since the last scan."""
        rt = self.cfg.real_time_matcher
        d = math.hypot(motion[0], motion[1])
        lin = rt.min_linear_search_window + rt.window_motion_fraction * d
        ang = (math.radians(rt.min_angular_search_window_deg) + rt.window_motion_fraction * abs(motion[2])
               + math.radians(rt.window_angle_per_metre_deg) * d)
        return lin, ang

    def largest_windows(self) -> tuple[float, float]:
        """The largest real-time windows (m, rad). The translation window is the configured one, or
        ``WINDOW_SIGMAS`` times the RMS distance of recent trusted matches from their prediction
        where that is larger: with scans a metre apart and noisy odometry, true poses lie beyond
        the configured window, and each such scan would go to the recovery search, whose wide
        window also reaches look-alike places far away. (Recovered matches are not counted: they
        are the events the error model does not cover.) The rotation window stays the configured
        one: without odometry, constant velocity misjudges every fast turn, and a window grown to
        cover those matched worse than the recovery search does."""
        rt = self.cfg.real_time_matcher
        lin, ang = rt.linear_search_window, math.radians(rt.angular_search_window_deg)
        if len(self.recent_errors) >= MIN_SCORES_FOR_TRUST:
            rms = math.sqrt(sum(e * e for e in self.recent_errors) / len(self.recent_errors))
            lin = max(lin, WINDOW_SIGMAS * rms)
        return lin, ang

    def _typical_score(self) -> float | None:
        # statistics.median: numpy's value for a few dozen floats, without its per-call overhead
        return statistics.median(self.recent_scores) if len(self.recent_scores) >= MIN_SCORES_FOR_TRUST else None

    def _least_recovered_score(self, limit: float, params: SearchParameters) -> float:
        """``limit`` (the lowest score a recovered peak is taken at: the trust limit, or below it the
        score of a real-time search that ended on its rotation window's edge) under the largest delta penalty
        of the recovery lattice ``params``: no pose scoring less reaches ``limit`` once the penalty
        is taken off, and no recovered peak scoring less is taken (``_takes_recovered``)."""
        return limit * self.wide_matcher.penalty.smallest_factor(params)

    def _recovery_floor(self, limit: float, params: SearchParameters) -> float:
        """Below this, no pose of the recovery lattice ``params`` can score ``limit`` once the delta
        penalty is taken off, and none is taken (``_least_recovered_score``)."""
        return float(np.nextafter(self._least_recovered_score(limit, params), -np.inf))

    @staticmethod
    def _better_where_observed(submap, grid, wide, m, points) -> bool:
        if m.on_edge:  # not a peak: nothing to compare with
            return True
        return LocalSlam._scores_higher_where_observed(submap, grid, wide.pose, m.pose, points)

    @staticmethod
    def _scores_higher_where_observed(submap, grid, pose, other, points) -> bool:
        """Whether ``points`` at ``pose`` score higher than at ``other`` on the points both put on
        observed cells of ``submap`` (``observed_scores``)."""
        common = observed_scores(submap.grid, grid, [pose, other], points)
        return common is not None and common[0] > common[1]

    def _unsupported_jump(self, wide, m, predicted, odometry: bool) -> bool:
        """Whether the recovered match ``wide``, which ``_takes_recovered`` would take over ``m``, is a
        jump the evidence does not carry: ``m`` is a peak inside the real-time window, ``wide`` lies
        farther than the wheel odometry's own translation error bound (``_error_bound``) both from
        the prediction and from ``m`` (another place, not the same one placed better), and it scores
        below the lower quartile of the recent trusted matches. Two explanations of the scan
        conflict there: the odometry failed beyond its error model, or the recovered place only
        looks like the right one (a door further along a corridor, a room like the last one) and
        outscores the right pose, which sees new ground. The trust limit is set for poses the
        odometry supports; a place it rules out stands on the scan alone and must fit it as well as
        three in four trusted matches do. Short of that, neither is taken: the scan carries the
        prediction and stays out of the submaps (``add_scan``), and the next scan, searched again,
        decides. A heading beyond the bound at the predicted place is no such conflict: look-alike
        places lie elsewhere, and a wheel slipping in a fast turn is the failure the recovery is
        for. Without odometry (no error bound) or before ``MIN_SCORES_FOR_TRUST`` trusted matches,
        never."""
        if m is None or m.on_edge or not odometry:
            return False
        bound = self._error_bound(predicted)[0]
        if min(math.hypot(*(wide.pose[:2] - predicted[:2])), math.hypot(*(wide.pose[:2] - m.pose[:2]))) <= bound:
            return False
        if len(self.recent_scores) < MIN_SCORES_FOR_TRUST:
            return False
        return wide.score < float(np.percentile(np.asarray(self.recent_scores), 25.0))

    def _plausible_jump(self, pose, predicted) -> bool:
        """Whether ``pose`` lies within the prediction's own error bound: the real-time windows of the
        motion since the last pose that was not carried from a prediction (``windows``, without the
        largest windows' cap, which bounds the search, not the error), i.e. grown by this scan's
        motion and by that of every untrusted scan before it, whose pose was the prediction."""
        lin, ang = self._error_bound(predicted)
        return (math.hypot(pose[0] - predicted[0], pose[1] - predicted[1]) <= lin
                and abs(math.remainder(pose[2] - predicted[2], 2 * math.pi)) <= ang)

    def _predicted_by_either(self, pose, predicted, time_s) -> bool:
        """Whether ``pose`` lies within the error bound (``_plausible_jump``) of the odometry's
        prediction ``predicted`` or of constant velocity's, the recovery's second prediction, at
        ``time_s``. The odometry's bound grows with the motion it read: where the wheels stop
        registering a turn the robot goes on making (they slip in a fast turn), it stays as small as
        that reading while the pose turns away from it. The turn's own pace, from the last trusted
        matches, predicts the pose then, and its bound grows with that turn."""
        if self._plausible_jump(pose, predicted):
            return True
        ex = self.extrapolator
        return ex.last_pose is not None and time_s is not None and self._plausible_jump(pose, ex.predict(time_s, None))

    def _reachable(self, pose, time_s) -> bool:
        """Whether the robot can have got to ``pose`` by ``time_s``: within the distance its fastest
        translation measured so far (``PoseExtrapolator.max_speed``) covers since the last trusted
        match, plus the regular real-time window (what a trusted pose and a velocity measured from two
        of them may be off by). Without odometry nothing else bounds a recovered peak that is no
        trusted match: a scan that fits nowhere well (a person in front of the laser) peaks weakly
        somewhere in the recovery window, metres from where the robot is, and inserted there it
        corrupts the submap for the scans after it (fr079 with ``--no-odometry``, README). True
        before the first trusted match."""
        e = self.extrapolator
        p0, t0 = e.measured_pose, e.measured_time
        if time_s is None or p0 is None:
            return True
        reach = e.max_speed * max(time_s - t0, 0.0) + self.cfg.real_time_matcher.linear_search_window
        return math.hypot(pose[0] - p0[0], pose[1] - p0[1]) <= reach

    def _error_bound(self, predicted) -> tuple[float, float]:
        """The prediction's error bound (m, rad) of ``_plausible_jump``."""
        motion = self.extrapolator.motion(predicted)
        d = self._carried[0] + math.hypot(motion[0], motion[1])
        r = self._carried[1] + abs(math.remainder(motion[2], 2 * math.pi))
        lin, ang = self.windows(np.array([d, 0.0, r]))
        return lin + self.cfg.grid.resolution, ang  # the searches place poses on a lattice of cells

    def _takes_recovered(self, wide, m, predicted, limit, submap, grid, points, least: float = 0.0,
                         odometry: bool = True, time_s: float | None = None) -> bool:
        """Whether the recovered match ``wide`` replaces ``m``, the real-time window's match around
        ``predicted`` (None: there is none). It must be trusted where ``m`` was not (``limit``; a
        wide window always holds some pose that scores a little higher, often a wrong one), beat
        ``m`` with both scores under the same delta penalty, i.e. the one around ``predicted``
        that ``m`` carries (the recovered score is that of its own peak: where a scene repeats,
        a place a door further scores as well as the right one, and the prediction must decide,
        as it does within the window), and beat ``m`` on the points both put on observed cells
        (a wide window holds poses that score higher only by laying new ground onto mapped cells).
        Where ``m`` is no peak (on its window's edge), a clear recovered peak that fails this also
        replaces the prediction, within the error bound of the odometry's prediction or of constant
        velocity's (``_predicted_by_either``), if it
        beats the prediction itself on the points both put on observed cells and scores at least
        ``least`` (``_least_recovered_score``: the recovery search prunes below it, so pruning still
        changes no result). ``odometry`` False: ``predicted`` is the constant-velocity model's, an
        assumption rather than a measurement, with no error bound of its own (a robot that stopped
        turning and drove off has left it behind by whatever it did since): such a peak need not
        lie near the prediction, only where the robot can have got to by ``time_s``
        (``_reachable``)."""
        if wide is None:
            return False
        if m is None:
            return True
        if (wide.score * self.matcher.penalty.factor(wide.pose, predicted) > m.score
                and (limit is None or wide.score >= limit)
                and self._better_where_observed(submap, grid, wide, m, points)):
            return True
        # no peak around the prediction (the real-time search ended on its edge): the prediction is
        # off, typically a fast turn whose odometry slipped beyond the largest rotation window, and a
        # turn shows new ground, so its right pose scores below ``limit`` (the slope ``m`` climbed
        # can also outscore it). A clear peak there replaces the prediction (a weak match below
        # ``limit``) where the error bound of the odometry's prediction or of constant velocity's
        # holds it and it explains the scan better than the prediction on the points both put on
        # observed cells
        return (m.on_edge and not wide.on_edge and wide.score >= least
                and (self._predicted_by_either(wide.pose, predicted, time_s) if odometry
                     else self._reachable(wide.pose, time_s))
                and self._scores_higher_where_observed(submap, grid, wide.pose, predicted, points))

    def _recovery_rotation(self, time_s: float, odometry: bool) -> float:
        """The recovery search's rotation half-width [rad]. With odometry, the configured one. Without,
        at least what the robot can have turned since the last trusted pose, at the fastest turn
        measured so far (``PoseExtrapolator.max_turn_rate``), up to the full circle: after a gap in
        the data (scans lost, a logger that paused) a robot may have turned round in place, which
        constant velocity cannot know."""
        w = self.wide_matcher.angular_window
        t = self.extrapolator.measured_time
        if odometry or t is None:
            return w
        return max(w, min(math.pi, self.extrapolator.max_turn_rate * max(time_s - t, 0.0)))

    def _recover(self, grid, scan, predicted, points, limit, floor=0.0, angular_window=None):
        """Branch-and-bound over the recovery windows around each distinct prediction, in the order the
        motion model believes them (odometry, constant velocity, no motion): the first whose best
        match scores ``limit`` (None: any) off the window's edge wins; without one, the best of all.
        In a corridor or a row of equal doors several predictions find a good match at different
        poses; the scene cannot tell them apart, so the likelier prediction decides.

        ``floor``: the caller takes a recovered match only if the fine search around its peak scores
        ``limit``, and no pose of the recovery lattice scoring below ``_recovery_floor`` (its
        score times the smallest delta penalty) can reach that; nor, where the real-time search
        found no peak, one scoring below that floor (``_least_recovered_score``), which is then
        made from that search's own score on its rotation window's edge where that lies below
        ``limit`` (``add_scan``). So branch-and-bound may cut every
        subtree whose bound is not above the floor: the best match above it is the same one, and a
        prediction whose best lies below it yields nothing instead of a match the caller would
        reject. (The fine search may step two cells past the window's edge; a match found there was
        on the edge, never trusted, and is the one case the floor can change.) Most recoveries
        find nothing trusted, and without a floor the search cannot prune before it has met the
        best pose of a weak scan. ``angular_window``: the rotation half-width (``_recovery_rotation``;
        default the configured one)."""
        hyps = [predicted]
        ex = self.extrapolator
        if ex.last_pose is not None:
            hyps += [ex.predict(scan.timestamp, None), ex.last_pose]  # constant velocity, no motion
        best = None
        tried = []
        for h in hyps:
            if not any(math.hypot(h[0] - t[0], h[1] - t[1]) < grid.resolution
                       and abs(math.remainder(h[2] - t[2], 2 * math.pi)) < 1e-3 for t in tried):
                tried.append(h)
        wide = self.wide_matcher
        reach = float(np.sqrt((points ** 2).sum(axis=1)).max())
        # built once, searched from every prediction; it pools only the cells those searches can reach
        stack = wide.stack_for(grid, around=tried, reach=reach)
        for h in tried:
            m = wide._match(grid, h, points, floor, wide.linear_window,
                            wide.angular_window if angular_window is None else angular_window, stack=stack)
            if m is None:
                continue
            if not m.on_edge and (limit is None or m.score >= limit):
                best = m
                break
            if best is None or m.score > best.score:
                best = m
        if best is None:
            return None
        # the score surface around the recovered peak: margin and covariance, as for a normal match
        step = angular_step(grid.resolution, reach)
        around = self.matcher._match(grid, best.pose, points, 0.0, 2 * grid.resolution, 2 * step)
        around.escalated = True
        around.on_edge = best.on_edge  # on the edge of the recovery window: the true pose may lie beyond
        return around

    def add_scan(self, scan) -> MatchingResult:
        timings = {}
        t0 = time.perf_counter()
        rd = range_data(scan, self.cfg.range_filter)
        kept = voxel_filter_index(rd.hits, self.cfg.range_filter.voxel_filter_size)
        points = rd.hits[kept]
        odom = self._odometry_reading(scan.odom_pose if self.cfg.real_time_matcher.use_odometry else None)
        submap = self.submaps.matching_submap
        grid = None if submap is None else submap.match_grid()
        ref = self._still(odom, grid, points)
        if self._stalled_at is not None:  # stalled (``_still`` may have found it at this scan)
            odom = None
            self.num_odometry_stalled_scans += 1
        from_odometry = self.extrapolator.from_odometry(odom)  # else constant velocity: an assumption
        predicted = self.extrapolator.predict(scan.timestamp, odom)
        pose = predicted
        score = None
        kept_match = None
        match = None
        quality = "unmatched"
        still_ref = False  # this scan becomes the reference of ``_still``
        recovered = None  # the pose a recovered match replaced
        bound = (0.0, 0.0)  # the prediction's error bound (m, rad): the real-time windows before their caps
        if ref is not None:
            # the robot stood still since a scan that was matched and trusted: that scan's pose
            pose, score, match = ref[1], ref[3], ref[2]
            quality = "trusted"
            self.num_still += 1
        elif submap is not None and len(points) >= 3:
            t1 = time.perf_counter()
            rt = self.cfg.real_time_matcher
            lin, ang = bound = self.windows(self.extrapolator.motion(predicted))
            lin_max, ang_max = self.largest_windows()
            # the wheel odometry's translation error as a prior, its motion window at ``window_sigmas`` σ
            # (a constant-velocity prediction is an assumption, not a measurement: no prior). A reading
            # identical to the last scan's is no measurement of motion either: the robot stood still
            # (``_still`` takes those scans that score best where the last one lay) or the odometry stream
            # stalled while it drove, and a prior that tight would hold the pose where the stream stopped
            fresh = from_odometry and not np.array_equal(odom, self.extrapolator.last_odom)
            prior = lin / rt.window_sigmas if rt.window_sigmas > 0 and fresh else 0.0
            m = self.matcher.match(grid, predicted, points, linear_window=lin, angular_window=ang,
                                   largest=(lin_max, ang_max), prior_sigma=prior)
            typical = self._typical_score()
            limit = None if typical is None else rt.min_relative_score * typical
            if m is not None and m.scan_on_edge and not m.on_edge and (limit is None or m.score < limit):
                # the prior made a peak of scores that still rise at the window's edge; a fit below
                # the trust limit is no evidence of a pose inside the window: as without the prior
                m.on_edge = True
            if m is not None and not from_odometry and lin > lin_max:
                # constant velocity carried over a gap (or from a noisy velocity) predicts a translation
                # whose error the largest window cannot hold: a peak inside it is no evidence of the
                # pose (a corridor holds one wherever the window lies); the recovery searches around
                # every prediction, no motion included
                m.on_edge = True
            low = m is not None and not m.on_edge and limit is not None and m.score < limit
            skipped = low and self._searched_in_vain(predicted)
            self.num_recovery_skipped += skipped
            if m is None or m.on_edge or (low and not skipped):
                # not trusted: search wide around every prediction (Olson 2009's exhaustive search made
                # cheap by branch-and-bound, Hess et al. 2016 Sec. V-C)
                t_rec = time.perf_counter()
                # with a match in hand, a recovered one is taken when trusted, or where that match is no peak (below)
                w = self.wide_matcher
                floor = least = 0.0
                rotation = self._recovery_rotation(scan.timestamp, from_odometry)
                if m is not None and limit is not None:
                    params = SearchParameters.make(w.linear_window, rotation, grid.resolution, points)
                    # the lowest score a recovered peak is taken at (``_takes_recovered``): the trust
                    # limit; where the real-time search ended on its rotation window's edge below it
                    # (a fast turn whose odometry slipped beyond it), the scores still rise there,
                    # toward a heading beyond the edge that may score below the limit (a turn shows
                    # new ground), and that edge's score is the least such a peak can be expected to
                    # reach
                    least_taken = m.score if m.score < limit and _on_rotation_edge(m, predicted) else limit
                    floor = self._recovery_floor(least_taken, params)
                    least = self._least_recovered_score(least_taken, params)
                with self.cores.share():
                    wide = self._recover(grid, scan, predicted, points, limit, floor, rotation)
                timings["recovery"] = (time.perf_counter() - t_rec) * 1e3
                self.num_recovery_searches += 1
                if self._takes_recovered(wide, m, predicted, limit, submap, grid, points, least,
                                         odometry=from_odometry, time_s=scan.timestamp):
                    if self._unsupported_jump(wide, m, predicted, from_odometry):
                        # two explanations, neither decided: untrusted (the prediction, not inserted)
                        m.on_edge = True
                        self.num_unsupported_jumps += 1
                    else:
                        # had the recovery chosen wrong, the pose it replaced was the right one
                        recovered = predicted if m is None else m.pose
                        m = wide
                        self.num_recovered += 1
                elif low:
                    self._vain_search_at = predicted
            t2 = time.perf_counter()
            timings["match"] = (t2 - t1) * 1e3
            if m is not None:
                trusted = not m.on_edge and (limit is None or m.score >= limit)
                pose, score, match = m.pose, m.score, m
                if self.cfg.refine.enabled:
                    r = self.cfg.refine
                    pose, _ = refine(submap.refinement_grid(r.unobserved), pose, points, r.occupied_space_weight, r.translation_weight,
                                     r.rotation_weight, r.max_iterations)
                    timings["refine"] = (time.perf_counter() - t2) * 1e3
                along = degenerate_direction(points)
                if along is not None:  # the scan cannot tell poses apart along it: keep the prediction's
                    c, s_ = math.cos(pose[2]), math.sin(pose[2])
                    along = np.array([c * along[0] - s_ * along[1], s_ * along[0] + c * along[1]])
                    pose = np.array(pose, dtype=float)
                    pose[:2] -= along * float(along @ (pose[:2] - predicted[:2]))
                    self.num_degenerate += 1
                self.num_escalated += m.escalated
                self.scores.append(score)
                if trusted:
                    self._vain_search_at = None
                    quality = "trusted"
                    self.num_matched += 1
                    still_ref = True
                    self.recent_scores.append(score)
                    if recovered is None:  # a recovery is the event the error model does not cover
                        self.recent_errors.append(math.hypot(m.pose[0] - predicted[0], m.pose[1] - predicted[1]))
                    self.untrusted_in_a_row = 0
                elif not m.on_edge and lin <= rt.recovery_linear_window:
                    # a clear peak inside the window that scores low: the scan sees new ground or little
                    # of the submap; mapped, counted, and loose in the pose graph (no covariance; its
                    # step as loose as its score surface: ``_step_doubt``)
                    quality = "weak"
                    self.num_matched += 1
                    self.num_weak += 1
                elif not m.on_edge or self.untrusted_in_a_row >= rt.max_untrusted_in_a_row:
                    # local SLAM lost track; the scan is mapped in new submaps (``ActiveSubmaps.insert``:
                    # what was mapped before stays as it was), its step as loose as the recovery window
                    # or the prediction's error (``_step_doubt``). Either a low peak where the
                    # prediction's own error (a long gap in time, a long drive between scans) exceeds
                    # even the recovery window: nothing searched could hold the pose, and the peak is no
                    # evidence of it; or on the edge several times in a row: the robot did move that way
                    quality = "forced"
                    self.num_matched += 1
                    self.num_forced += 1
                    self.untrusted_in_a_row = 0
                else:
                    quality = "untrusted"
            else:
                quality = "untrusted"
            if quality == "untrusted":
                # the best pose lies on the edge of every window searched, so the true one lies beyond
                # it: carry on from the prediction and keep the scan out of the submaps
                pose, match = predicted, None
                self.num_untrusted += 1
                self.untrusted_in_a_row += 1
        pose = np.array([pose[0], pose[1], math.remainder(pose[2], 2 * math.pi)])
        if still_ref:
            self._still_ref = (odom, pose, match, score)
        elif ref is None:
            self._still_ref = None
        self._doubt += self._step_doubt(quality, pose, recovered, submap is not None, bound, match)
        if quality == "untrusted":  # the pose is the prediction: its error carries into the next one
            motion = self.extrapolator.motion(pose)
            self._carried += (math.hypot(motion[0], motion[1]), abs(math.remainder(motion[2], 2 * math.pi)))
        else:
            self._carried[:] = 0.0
        self.extrapolator.add(scan.timestamp, pose, odom, measured=quality in ("trusted", "unmatched"))
        # a scan with too few points to match, once there is a submap to match against, carries the
        # prediction: its free space inserted there would carve the map where the pose is only a guess
        # (a glitch scan whose every beam is a no-return cleared a half-disc outside the building)
        guessed = quality == "unmatched" and submap is not None
        inserted = quality != "untrusted" and not guessed and not self.filter.is_similar(scan.timestamp, pose, odom)
        finished = []
        inserted_into = []
        if inserted:
            t3 = time.perf_counter()
            local = rd.transformed(pose)
            with self.cores.share():
                finished = self.submaps.insert(pose, local.origin, local.hits, local.misses, scan.index,
                                               restart=quality == "forced")
            inserted_into = self.submaps.last_inserted_into
            if quality == "trusted":
                kept_match = match
            self.finished_submaps.extend(finished)
            self.num_inserted += 1
            timings["insert"] = (time.perf_counter() - t3) * 1e3
        timings["total"] = (time.perf_counter() - t0) * 1e3
        doubt = (0.0, 0.0)
        if inserted:
            doubt, self._doubt = (float(self._doubt[0]), float(self._doubt[1])), np.zeros(2)
        return MatchingResult(scan.timestamp, pose, rd, inserted, score, timings,
                              active_submap=self.submaps.matching_submap, finished_submaps=finished,
                              inserted_into=inserted_into, match=kept_match, points=points, point_index=kept,
                              quality=quality, doubt=doubt,
                              replaced=None if recovered is None else np.array(recovered, dtype=float),
                              fresh_start=inserted and quality == "forced")

    def _still(self, odom, grid, points):
        """The reference scan (``_still_ref``: the last scan matched and trusted) when the robot has
        not moved since it: the wheel odometry reads exactly what it read there, and on the
        matcher's own lattice one step around the reference's pose (a cell each way, an angular
        step each way) the scan scores best at that pose itself. Such a scan gets the reference's
        pose without a search and without refinement, as Karto and slam_toolbox skip scans until
        the robot moved. The lattice check is what tells a robot standing still from odometry
        frozen while it drives (a stalled odometry stream): once the robot has moved, the scan
        scores better a step away and is matched as usual (tests/test_frontend.py freezes the
        odometry of a drive); a range-by-range comparison would not see a drive along a corridor,
        whose side walls return the same ranges. None otherwise."""
        ref = self._still_ref
        if ref is None or odom is None or grid is None or len(points) < 3 or not np.array_equal(odom, ref[0]):
            return None
        m = self.still_matcher._match(grid, ref[1], points, 0.0, grid.resolution, 1e-9)
        if m is not None and m.on_edge:
            # the robot moved while the odometry read the same: the stream has stalled (``_odometry_reading``)
            self._stalled_at = np.array(odom, dtype=float)
            self.num_odometry_stalls += 1
        return None if m is None or m.on_edge else ref

    def _odometry_reading(self, odom):
        """The scan's wheel odometry, or None while the stream is stalled: from a scan at which the
        robot moved while the reading stayed what it was (``_still``'s lattice check) until the
        reading changes. A stalled reading says the robot stands still while it drives; taken as a
        measurement it would hold scans at the last pose (``_still``) and size every window for no
        motion. Logs written without wheel odometry often fill its fields with one constant pose
        (zeros), which stalls at the first scan that shows motion and never resumes. Meanwhile the
        scans are predicted as without odometry (constant velocity); ``odometry_stalled_scans`` in
        the summary counts them."""
        if odom is not None and self._stalled_at is not None:
            if not np.array_equal(odom, self._stalled_at):
                self._stalled_at = None  # the stream moves again
                return odom
            return None
        return odom

    def _searched_in_vain(self, predicted) -> bool:
        """Whether a low-scoring peak inside the window skips the recovery search: one made for such a
        peak, since the last trusted match, found no pose to take within the recovery windows around
        a prediction that ``predicted`` still lies within. Those windows held every pose the search
        would try again (shifted by the travel since), so it is tried again once the robot has left
        them or a match was trusted. A peak on the window's edge, or no peak, is always searched: the
        true pose lies beyond the window then. A long stretch of new ground (long-range beams past
        the submap's extent) would otherwise run the wide search at every scan and find nothing."""
        at = self._vain_search_at
        if at is None:
            return False
        rt = self.cfg.real_time_matcher
        if (math.hypot(predicted[0] - at[0], predicted[1] - at[1]) >= rt.recovery_linear_window
                or abs(math.remainder(predicted[2] - at[2], 2 * math.pi)) >= math.radians(rt.recovery_angular_window_deg)):
            return False
        return True

    def _step_doubt(self, quality, pose, replaced, had_submap, bound=(0.0, 0.0), match=None) -> np.ndarray:
        """What a step adds to ``MatchingResult.doubt``. A recovered pose and the pose it replaced (the
        in-window match, or the prediction) cannot both be right: if the recovery chose wrong, the
        step is off by the distance between them. A pose forced in may lie anywhere in the recovery
        window, or anywhere within ``bound`` (the prediction's error bound, m and rad) where that is
        larger; a scan with too few points to match carries the prediction, off by up to the regular
        window. A weak match (``match``: a clear peak that scores below the trust limit: the scan sees
        little of the submap) is off by what its score surface allows: the standard deviations of its
        covariance (the larger of its translation axes, and its heading), so a run of weak matches
        along which local SLAM's heading wandered is as loose in the pose graph as the matches were,
        and loops that see it can bend it back. An untrusted scan adds nothing: it is not inserted,
        and the next scan is matched against the same submap."""
        rt = self.cfg.real_time_matcher
        if quality == "forced":
            return np.maximum([rt.recovery_linear_window, math.radians(rt.recovery_angular_window_deg)], bound)
        if replaced is not None and quality != "untrusted":
            return np.array([math.hypot(pose[0] - replaced[0], pose[1] - replaced[1]),
                             abs(math.remainder(pose[2] - replaced[2], 2 * math.pi))])
        if quality == "unmatched" and had_submap:
            return np.array([rt.linear_search_window, math.radians(rt.angular_search_window_deg)])
        if quality == "weak" and match is not None:
            cov = match.covariance
            if cov is not None:
                return np.sqrt([max(np.linalg.eigvalsh(cov[:2, :2])[-1], 0.0), max(cov[2, 2], 0.0)])
        return np.zeros(2)

    def all_submaps(self):
        return list(self.finished_submaps) + list(self.submaps.submaps)

    def summary(self) -> dict:
        s = np.asarray(self.scores) if self.scores else np.zeros(1)
        n = self.num_matched + self.num_untrusted + self.num_still
        if n and self.num_odometry_stalled_scans > n / 2:
            log.warning("the wheel odometry read the same pose at %d of %d scans while the scans showed the robot "
                        "moving: those were predicted without it (is the log's odometry empty?)",
                        self.num_odometry_stalled_scans, n)
        return {"local_slam": {"matched_scans": self.num_matched, "inserted_scans": self.num_inserted,
                               "wide_searches": self.num_escalated,
                               "recovery_searches": self.num_recovery_searches, "recovered": self.num_recovered,
                               "recovery_skipped": self.num_recovery_skipped,
                               "unsupported_jumps": self.num_unsupported_jumps,
                               "odometry_stalls": self.num_odometry_stalls,
                               "odometry_stalled_scans": self.num_odometry_stalled_scans,
                               "untrusted": self.num_untrusted, "inserted_untrusted": self.num_forced, "weak": self.num_weak,
                               "degenerate": self.num_degenerate, "still": self.num_still,
                               "submaps": self.submaps.count, "finished_submaps": len(self.finished_submaps),
                               "score_mean": round(float(s.mean()), 4), "score_p5": round(float(np.percentile(s, 5)), 4)}}


def _on_rotation_edge(m, predicted) -> bool:
    """Whether the real-time match ``m`` around ``predicted`` lies on an edge of its rotation window
    (its lattice's first or last angle)."""
    if not m.on_edge or m.params is None:
        return False
    return abs(math.remainder(m.pose[2] - predicted[2], 2 * math.pi)) >= float(np.abs(m.params.angles).max()) - 1e-9


__all__ = ["LocalSlam", "PoseExtrapolator"]
