"""Global SLAM (Cartographer's ``PoseGraph2D``; Hess et al. 2016, Sec. V).

Every node (an inserted scan) enters the pose graph tied to the submaps it was inserted
into; sampled nodes are matched against nearby finished submaps (branch-and-bound), and
each newly finished submap against earlier nearby nodes; matches that pass verification
(re-score, margin, ``loop_closure.py``) become loop-closure constraints with their own
covariance. Before each optimization, loops that contradict other loops through the local
chain are removed (``consistency.py``); after it, loops with large residuals. The graph is
optimized every ``optimize_every_n_nodes`` nodes and once at the end; submaps and nodes then
move to their global poses. Each search looks as far around the current estimate as the drift
bound between the two places reaches (``drift.py``: local SLAM's drift along what links them in
the optimized graph, plus every step local SLAM could not trust), at most the regular window;
where the bound exceeds it, a finished submap is also matched whole against older ones
(``wide_search.py``). Before the last optimization, the final search (``GlobalSlam.final_search``)
takes again the nodes a later loop moved out of the window they were searched in. Every
rejection's reason is kept in its constraints.jsonl record.
"""
from __future__ import annotations

import logging
import math
import time

import numpy as np

from slam2d.backend.consistency import ConsistencyParams, PairCache, confirmed, inconsistent
from slam2d.backend.drift import DriftBound
from slam2d.backend.loop_closure import StackCache, SubmapMatcher, loop_points, probability_self_score
from slam2d.backend.wide_search import coarse_grid, coarse_match, frame_offset, submap_content
from slam2d.geometry import between, compose, inverse, transform_points
from slam2d.matching.real_time import unmatched_covariance
from slam2d.threads import CallerCores

log = logging.getLogger(__name__)

#: bytes of branch-and-bound precomputation stacks kept, most recently searched first (``StackCache``);
#: an evicted stack is rebuilt from its submap's uint8 grid when the submap is searched again.
STACK_CACHE_BYTES = 16 * 1024 * 1024
#: the final search repeats while a round closes loops, at most this many rounds
FINAL_SEARCH_ROUNDS = 3


class GlobalSlam:
    def __init__(self, cfg, observer=None, solver_process: bool = False):
        """``solver_process``: solve the pose graph in a child process (``solver_process.py``), whose
        solves then do not hold this process's interpreter lock."""
        from slam2d.observer import Observer

        self.cfg = cfg
        self.observer = observer or Observer()
        lc = cfg.loop_closure
        self.lc = lc
        if solver_process:
            from slam2d.backend.solver_process import RemotePoseGraph as Graph
        else:
            from slam2d.backend.pose_graph import PoseGraph as Graph
        self.graph = Graph(lc.huber_scale, lc.max_residual_translation, math.radians(lc.max_residual_rotation_deg),
                           incremental=lc.incremental)
        self.matchers: dict[int, SubmapMatcher] = {}
        self.min_scores: dict[int, float] = {}  # per finished submap: the score a loop match must reach
        # one node's search (``max_submaps_per_node``) and a newly finished submap's own search
        self.stacks = StackCache(STACK_CACHE_BYTES, min_stacks=lc.max_submaps_per_node + 1)
        self.coarse = {}  # per finished submap: its coarse grid for the wide search, made on first use
        self._centres: dict[int, np.ndarray] = {}  # per finished submap: ``_centre_from_anchor``
        self._centres_at = None                      # ``_submap_centres``'s cache and when it was made
        self._centres_all = (np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
        self._tracks_at = None  # ``_submap_tracks``'s cache and when it was made
        self._tracks = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
        self._own: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # ``_submap_nodes``'s cache
        # local SLAM's last fresh start (``ActiveSubmaps.insert``'s restart): its first submap, and
        # per submap the first of the stretch it belongs to
        self._segment_start = 0
        self._segment_of: dict[int, int] = {}
        self.fresh_starts: list[int] = []  # the nodes local SLAM started afresh with
        self.heading_constraints = 0  # heading constraints added (``_search``'s heading)
        self._last_submaps: set[int] = set()  # the submaps the newest node was inserted into
        # per (node, submap) searched: the node's pose in the submap's grid frame the search started
        # from, its window (m, rad) and whether it was accepted (``final_search``)
        self._searched: dict[tuple[int, int], tuple] = {}  # (x, y, θ, lin, ang, accepted)
        # per sampled node: [its global estimate when it was searched, the smallest window (m, rad)
        # of any search of it, (first, last) submap it was inserted into and its stretch's first]
        self._sampled_at: dict[int, list] = {}
        self.final_searches = 0
        self.final_accepted = 0
        self.final_search_seconds = 0.0
        self.wide_searches = 0
        # the cores its searches may use (``Slam`` sets it when this runs on a worker beside local SLAM)
        self.cores = CallerCores()
        self.wide_accepted = 0
        self.field_submaps = 0  # finished submaps scored on their likelihood field (``add_finished_submap``)
        self.sampled: list[int] = []  # nodes matched against finished submaps (and new submaps against them)
        self.sample_distance = cfg.motion_filter.max_distance
        self._last_pose, self._since_sample, self._travel = None, 0, 0.0
        self.submap_anchor: dict[int, int] = {}  # submap -> scan index of its first node
        self.submap_local: dict[int, np.ndarray] = {}
        self.nodes: dict[int, dict] = {}  # scan index -> {local, time, stamp, points}
        # per node whose loop points are kept for its submaps: those of them not finished yet
        # (``_release_points``)
        self._unfinished_of: dict[int, set[int]] = {}
        self.node_order: list[int] = []
        self._range_sum, self._range_n, self._mean_range = 0.0, 0, 0.0  # ``_note_range``
        self.records: list[dict] = []
        self.correction = np.zeros(3)  # global <- local, from the latest optimization
        self.since_optimize = 0
        self.search_seconds = 0.0
        self.searches = 0
        self.optimize_seconds = 0.0
        self.optimizations = 0
        self.loops_at_last_optimize = 0
        self.consistency_removed = 0
        # loops the last consistency check confirmed (none when it is off): the residual check spares them
        self._confirmed: list[int] = []
        self.gnc_removed = 0
        self.drift = DriftBound(lc.consistency_drift, math.radians(lc.consistency_drift_deg))
        # loop pairs tested for consistency, each once (``consistency.PairCache``)
        self._loop_rows: dict[int, tuple] = {}  # per loop factor: ``_check_consistency``'s row of it
        self._pairs = PairCache(ConsistencyParams(lc.consistency_max_chain, lc.consistency_translation,
                                                  lc.consistency_drift, math.radians(lc.consistency_rotation_deg),
                                                  math.radians(lc.consistency_drift_deg), lc.consistency_min_support))
        rt = cfg.real_time_matcher
        self.unmatched_cov = unmatched_covariance(rt.linear_search_window, math.radians(rt.angular_search_window_deg))
        #: a matched node's covariance at its floor (isotropic, so the same in every frame)
        self.step_floor = _floored(None, self.lc.min_local_sigma_translation, math.radians(self.lc.min_local_sigma_rotation_deg))

    # ---- estimates
    def global_node(self, j) -> np.ndarray:
        if self.graph.has_node(j) and self.optimizations:
            return self.graph.node_pose(j)
        return compose(self.correction, self.nodes[j]["local"])

    def global_submap(self, k) -> np.ndarray:
        """A submap's global pose is its first node's."""
        return self.global_node(self.submap_anchor[k])

    # ---- input from local SLAM
    def add_node(self, scan, local_pose, hits, covariance, inserted_into, doubt=(0.0, 0.0), fresh_start=False):
        """``covariance``: the local match's 3×3 covariance (map axes), or the match itself (anything with
        a ``covariance``, e.g. ``MatchResult``: computed here), or None for a scan never matched.
        ``doubt``: what local SLAM could not vouch for since the last node (``MatchingResult.doubt``).
        ``fresh_start``: local SLAM lost track and started new submaps with this node
        (``MatchingResult.fresh_start``)."""
        if covariance is not None and not isinstance(covariance, np.ndarray):
            covariance = covariance.covariance
        j = scan.index
        local_pose = np.asarray(local_pose, float)
        prev = self.nodes[self.node_order[-1]] if self.node_order else None
        step = 0.0 if prev is None else float(np.hypot(*(local_pose[:2] - prev["local"][:2])))
        path = 0.0 if prev is None else prev["path"] + step
        turn = 0.0 if prev is None else abs(math.remainder(local_pose[2] - prev["local"][2], 2 * math.pi))
        self._note_range(hits)
        # how far the view moved: the metres driven, plus the radians turned times the typical range
        # of a hit (a turn sweeps the scan's content across the sensor as a drive of that length does)
        view = 0.0 if prev is None else prev["view"] + step + self._mean_range * turn
        # what local SLAM could not vouch for along its chain so far (variances summed, as the doubt
        # of independent steps): a submap built across such steps is as unsure inside
        doubted = np.zeros(2) if prev is None else prev["doubted"] + np.square(doubt)
        self.drift.add(j, step, *doubt)
        self.nodes[j] = {"local": local_pose, "time": scan.timestamp, "path": path, "view": view, "doubted": doubted,
                         "stamp": scan.timestamp_text,
                         "points": loop_points(hits, self.lc.voxel_filter_size, self.lc.adaptive_voxel_min_points,
                                                     self.lc.adaptive_voxel_max_length)}
        self.node_order.append(j)
        self.graph.add_node(j, compose(self.correction, local_pose))
        if covariance is None:  # never matched: pure prediction, trusted least
            covariance = self.unmatched_cov
        # the matcher's covariance is along the local map's x/y axes; the between-factor's noise
        # is in the node's own frame (gtsam: error = Logmap(measured⁻¹ · anchor⁻¹ · node))
        floored = _floored(covariance, self.lc.min_local_sigma_translation,
                           math.radians(self.lc.min_local_sigma_rotation_deg))
        cov = node_frame_covariance(floored, local_pose[2])
        submaps = {k for k, _ in inserted_into}
        if submaps:
            self._unfinished_of[j] = set(submaps)
        if fresh_start and submaps:
            self._segment_start = min(submaps)
            self.fresh_starts.append(j)
        if prev is not None and submaps:
            # local SLAM's step from the previous node (Cartographer's constraint on consecutive nodes'
            # local poses, Karto's sequential edge): the node-in-submap constraints below tie each node
            # to its submap's first node alone, as loosely as a weak match or the drift along the
            # submap allows, so without the step a loop could pull its end node away from the nodes
            # beside it. The two nodes were matched against the same content, so their step is known
            # to the floor of a match, plus the drift over the step and whatever local SLAM could not
            # vouch for on it (its doubt); where local SLAM started afresh, so that no submap holds
            # both, the doubt makes it as loose as the recovery was, and it is their only link.
            self.graph.add_intra(self.node_order[-2], j, between(prev["local"], local_pose),
                                 2.0 * self.step_floor + self._drift_covariance(step, view - prev["view"])
                                 + np.diag([doubt[0] ** 2, doubt[0] ** 2, doubt[1] ** 2]),
                                 screened=not submaps & self._last_submaps)
        self._last_submaps = submaps
        for k, sub_local in inserted_into:
            self._segment_of.setdefault(k, self._segment_start)
            if k not in self.submap_local:
                self.submap_local[k] = np.asarray(sub_local, float)
                self.submap_anchor[k] = j
            a = self.submap_anchor[k]
            if a != j:
                dt, dr = doubted - self.nodes[a]["doubted"]
                self.graph.add_intra(a, j, between(self.submap_local[k], local_pose),
                                     cov + self._drift_covariance(self.nodes[j]["path"] - self.nodes[a]["path"],
                                                                  self.nodes[j]["view"] - self.nodes[a]["view"])
                                     + np.diag([dt, dt, dr]))
        if self.lc.enabled and self._sample(j, local_pose):
            self._search_node(j, submaps)
        self.since_optimize += 1
        if self.since_optimize >= self.lc.optimize_every_n_nodes:
            if len(self.graph.loops) > self.loops_at_last_optimize:
                self.optimize()
            else:  # nothing new but local chains: the solution would only follow them
                self.since_optimize = 0

    def _drift_covariance(self, path: float, view: float) -> np.ndarray:
        """What the score surface cannot see: the submap was built along ``path`` metres of local SLAM
        and drifted with it, so a node's pose relative to the submap's first node is uncertain by a
        share of that path (isotropic in translation, so the same in every frame). Its heading drifts
        with how far the view moved (``view``: the path plus the turns, each radian as far as the
        typical range of a hit): a robot turning on the spot matches scans whose content sweeps past,
        and there local SLAM's heading errors arise, while it covers no path."""
        t, r = self.lc.local_drift * path, math.radians(self.lc.local_drift_deg) * view
        return np.diag([t * t, t * t, r * r])

    def _note_range(self, hits):
        """Keep ``_mean_range``: the mean over the nodes so far of each one's median hit range."""
        h = np.asarray(hits, dtype=float).reshape(-1, 2)
        if len(h):
            self._range_sum += float(np.median(np.hypot(h[:, 0], h[:, 1])))
            self._range_n += 1
            self._mean_range = self._range_sum / self._range_n

    def _sample(self, j, local_pose) -> bool:
        """Every ``sample_every_n_nodes``-th node, or sooner once the robot travelled as far as that many
        nodes span at the motion filter's distance: a sparse log (scans a metre apart) is then
        sampled as densely per metre as a dense one."""
        if self._last_pose is not None:
            self._travel += float(np.hypot(*(np.asarray(local_pose[:2]) - self._last_pose[:2])))
        self._last_pose = np.asarray(local_pose, float)
        self._since_sample += 1
        n = self.lc.sample_every_n_nodes
        if self._since_sample >= n or self._travel >= n * self.sample_distance:
            self._since_sample, self._travel = 0, 0.0
            self.sampled.append(j)
            return True
        return False

    def add_finished_submap(self, submap):
        if not self.lc.enabled:
            return
        lc = self.lc
        own = [(self.nodes[j]["points"], self.nodes[j]["local"]) for j in submap.node_indices if j in self.nodes]
        score = probability_self_score(submap, own)
        # ``loop_closure.score_grid``: auto scores a submap whose cells were each seen a few times (its
        # threshold lowered by min_relative_score) on its likelihood field (``loop_closure.py``)
        field = lc.score_grid == "likelihood_field" or (lc.score_grid == "auto" and min_score_for(lc, score) < lc.min_score)
        m = SubmapMatcher(submap, lc.branch_depth, self.stacks,
                          field_sigma=self.cfg.real_time_matcher.likelihood_field_sigma if field else None)
        self.matchers[submap.index] = m
        self.field_submaps += field
        self.min_scores[submap.index] = min_score_for(lc, m.self_score(own) if field else score)
        submap.grid.pack()  # searches read the values from the matcher's cached stack from now on
        # earlier nodes near the new submap (sampled), excluding those inside it
        first = min(submap.node_indices, default=0)
        center = compose(self.global_submap(submap.index), self._centre_from_anchor(submap.index))
        sampled = np.array(self.sampled, dtype=np.int64)
        sampled = sampled[sampled < first]  # the submap's own nodes come from ``first`` on
        xy = self._global_xy(sampled)
        d = np.hypot(xy[:, 0] - center[0], xy[:, 1] - center[1])
        near = d < self.lc.max_constraint_distance
        sampled, d = sampled[near], d[near]
        for i in np.lexsort((sampled, d))[: self.lc.max_searches_per_submap]:  # nearest first
            self._search(submap.index, int(sampled[i]))
        if self.lc.wide_search:
            self._search_wide(submap)
        self._release_points(submap)

    def _release_points(self, submap):
        """A node's loop points serve three kinds of search: its own (a sampled node's, during the run
        and in the final search), its submaps' (their self-score, the wide search of their content)
        and new submaps' against earlier sampled nodes. So once every submap a node lies in is
        finished, an unsampled node's points go: what global SLAM keeps per node then follows the
        sampled nodes, not every node."""
        for j in submap.node_indices:
            left = self._unfinished_of.get(j)
            if left is None:
                continue
            left.discard(submap.index)
            if not left:
                del self._unfinished_of[j]
                if j not in self._sampled_at:
                    del self.nodes[j]["points"]  # any later use fails loudly, never matches nothing

    # ---- searching
    def _search_node(self, j, submaps):
        g = self.global_node(j)
        own = (min(submaps), max(submaps), self._segment_start) if submaps else None
        self._sampled_at[j] = [g, 0.0, 0.0, own] if own else None
        chosen = self._candidate_submaps(g)
        # searched with the submaps whose stacks are cached first (a node's nearest submaps recur
        # at the next sampled node, and taken in one fixed order they make the cache rebuild every
        # stack it holds fewer than), committed nearest first: the searches of one node are
        # independent (windows change only at an optimization), so the outcome is the same
        done = {k: self._search(k, j, defer=True) for k in sorted(chosen, key=lambda k: not self.stacks.holds(k))}
        for k in chosen:
            rec, loop, _ = done[k]
            self._commit(rec, loop)

    def _candidate_submaps(self, node_g, own=None) -> list[int]:
        """The finished submaps a node at ``node_g`` (global) is matched against: at most
        ``max_submaps_per_node``, leaving the newest to local SLAM: those whose content centre lies
        within ``max_constraint_distance``, nearest first, or where there is none, those built from
        a pose that close, nearest pose first. A submap built along a corridor and seeing far down
        it has its centre far from where the robot stood, so a node back in that corridor finds it
        only by the second rule (fr-clinic). Where some centres are near, the second rule is not
        consulted: adding its submaps there too found more loops on the sparse logs but cost time
        and did not make them more accurate (infinite-corridor 0.506 -> 0.522 m).

        ``own``: for a node of the past (``final_search``), the (first, last) submap it was inserted
        into and the first of its stretch of local SLAM: the submaps next to its own on either side
        are left out as the newest are for a new node."""
        lc = self.lc
        n = lc.max_submaps_per_node
        newest = max(self.matchers, default=-1)

        def searchable(ks):
            if own is None:
                return self._searchable(ks, newest, self._segment_start)
            return (ks < own[0] - lc.exclude_recent_submaps) | (ks > own[1] + lc.exclude_recent_submaps) | (ks < own[2])

        ks, centres = self._submap_centres()
        d = np.hypot(node_g[0] - centres[:, 0], node_g[1] - centres[:, 1])
        near = searchable(ks) & (d < lc.max_constraint_distance)
        chosen = [k for _, k in sorted(zip(d[near].tolist(), ks[near].tolist()))[:n]]
        if not chosen:
            tk, starts, track = self._submap_tracks()
            if len(tk):
                dn = np.minimum.reduceat(np.hypot(track[:, 0] - node_g[0], track[:, 1] - node_g[1]), starts)
                ok = searchable(tk) & (dn < lc.max_constraint_distance)
                chosen = [k for _, k in sorted(zip(dn[ok].tolist(), tk[ok].tolist()))[:n]]
        return chosen

    def _searchable(self, ks: np.ndarray, newest: int, segment_start: int) -> np.ndarray:
        """Which finished submaps ``ks`` a node of the stretch of local SLAM that began with submap
        ``segment_start`` is matched against, ``newest`` being the newest finished one. The newest
        ``exclude_recent_submaps`` share scans with the active submaps and are left to local SLAM,
        except those finished before local SLAM's last fresh start: it matches nothing against
        them any more, so only loop closure can tie the new stretch to them."""
        return (ks <= newest - self.lc.exclude_recent_submaps) | (ks < segment_start)

    def _submap_tracks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, start offsets, (M, 2) global positions) of the nodes of every finished submap that
        has nodes, submap after submap; kept, like ``_submap_centres``, until the next optimization
        or the next finished submap (the estimates change only then)."""
        key = (self.optimizations, len(self.matchers))
        if self._tracks_at != key:
            own = [(k, self._submap_nodes(k)[0]) for k in self.matchers]
            own = [(k, ids) for k, ids in own if len(ids)]
            sizes = [len(ids) for _, ids in own]
            js = np.concatenate([ids for _, ids in own]) if own else np.zeros(0, dtype=np.int64)
            self._tracks = (np.array([k for k, _ in own], dtype=np.int64),
                            np.cumsum([0] + sizes[:-1]).astype(np.int64), self._global_xy(js))
            self._tracks_at = key
        return self._tracks

    def _global_xy(self, js: np.ndarray) -> np.ndarray:
        """(N, 2) global positions of nodes ``js``: ``global_node``'s, for many nodes in one pass."""
        out = np.empty((len(js), 2))
        have = np.zeros(len(js), dtype=bool)
        if self.optimizations and len(js):
            ids, poses = self.graph.all_node_poses()
            if len(ids):
                at = np.minimum(np.searchsorted(ids, js), len(ids) - 1)
                have = ids[at] == js
                out[have] = poses[at[have], :2]
        rest = np.flatnonzero(~have)
        if len(rest):
            local = np.array([self.nodes[int(j)]["local"][:2] for j in js[rest]], dtype=float).reshape(-1, 2)
            out[rest] = transform_points(self.correction, local)
        return out

    def _submap_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, (K, 3) global content centres) of the finished submaps, kept until the next
        optimization or the next finished submap (the estimates change only then)."""
        key = (self.optimizations, len(self.matchers))
        if self._centres_at != key:
            ks = list(self.matchers)
            c = [compose(self.global_submap(k), self._centre_from_anchor(k)) for k in ks]
            self._centres_all = (np.array(ks, dtype=np.int64), np.array(c, dtype=float).reshape(-1, 3))
            self._centres_at = key
        return self._centres_all

    def _centre_from_anchor(self, k) -> np.ndarray:
        """Submap ``k``'s content centre seen from its first node (fixed: both are in its grid frame)."""
        c = self._centres.get(k)
        if c is None:
            m = self.matchers[k]
            c = self._centres[k] = between(m.submap.local_pose, np.r_[m.center_local, 0.0])
        return c

    def _search(self, k, j, initial=None, defer: bool = False, window=None, heading: bool = False):
        """Match node ``j`` against submap ``k`` around ``initial`` (its pose in the submap's grid frame;
        default: from the current global estimates) within ``window`` (m, rad; default: ``_window``).
        The record is kept and an accepted match becomes a loop constraint, unless ``defer``: then
        both are returned for ``_commit``. ``heading``: a match rejected as ambiguous in position
        only becomes a heading constraint (``loop_closure.wide_heading_constraints``)."""
        m = self.matchers[k]
        node = self.nodes[j]
        estimate = initial is None and self.lc.estimate_check
        if initial is None:
            initial = self._initial(k, self.global_node(j))
        lc = self.lc
        if window is None:
            window = self._window(self._middle_node(k), j)
        lin, ang = window
        t0 = time.perf_counter()
        min_score = self.min_scores[k]
        with self.cores.share():
            res = m.match(node["points"], initial, lin, ang, min_score,
                          (lc.refine_occupied_weight, lc.refine_translation_weight, lc.refine_rotation_weight, 20),
                          lc.min_margin, (lc.margin_window, math.radians(lc.margin_window_deg)),
                          (lc.margin_exclusion, math.radians(lc.margin_exclusion_deg)), estimate=estimate)
        dt = time.perf_counter() - t0
        self.search_seconds += dt
        self.searches += 1
        # The constraint ties the node to the submap's node nearest to the match (its grid frame is
        # the local frame, so that node's local pose is its pose in the grid): the content it
        # matched was inserted there, whereas the anchor can be a whole submap of drift away.
        frm = self._nearest_submap_node(k, None if res is None else res.pose)
        rec = {"submap": int(k), "from_scan": int(frm), "to_scan": int(j),
               "from_stamp": self.nodes[frm]["stamp"], "to_stamp": node["stamp"],
               "search_ms": round(dt * 1e3, 3), "window": [round(lin, 3), round(math.degrees(ang), 2)],
               "min_score": round(min_score, 4), "score_grid": "likelihood_field" if m.scores_field else "probability"}
        loop = None
        if res is None:
            rec.update({"relative_pose": None, "score": None, "accepted": False, "reason": f"no match above {min_score:.3f}",
                        "in_final_graph": False})
        else:
            cov = node_frame_covariance(_floored(res.covariance, lc.loop_sigma_translation,
                                                 math.radians(lc.loop_sigma_rotation_deg)), res.pose[2])
            relative = between(self.nodes[frm]["local"], res.pose)
            rec.update({"relative_pose": [float(v) for v in relative], "score": round(res.score, 4),
                        "rescore": round(res.rescore, 4), "margin": round(res.margin, 4),
                        "sigma": [round(float(v), 5) for v in np.sqrt(np.diag(cov))],
                        "accepted": res.reason is None, "reason": res.reason or "accepted",
                        "in_final_graph": res.reason is None})
            if res.reason is None:
                loop = (frm, j, relative, cov)
            elif (heading and lc.wide_heading_constraints and res.reason.startswith("ambiguous")
                  and res.heading_margin >= lc.min_margin):
                # poses along a corridor score alike, but only at the refined heading: that holds
                rec["heading_constraint"] = {"in_final_graph": True, "sigma_deg": round(math.degrees(math.sqrt(cov[2, 2])), 4)}
                rec["_heading"] = (frm, j, relative, np.diag([HEADING_ONLY_SIGMA ** 2, HEADING_ONLY_SIGMA ** 2, cov[2, 2]]))
        self._searched[(j, k)] = (*map(float, initial), lin, ang, loop is not None)
        at = self._sampled_at.get(j)
        if at is not None:
            at[1] = lin if not at[1] else min(at[1], lin)
            at[2] = ang if not at[2] else min(at[2], ang)
        if defer:
            return rec, loop, res
        self._commit(rec, loop)
        return rec, loop, res

    def _initial(self, k, node_g) -> np.ndarray:
        """A node at ``node_g`` (global) in submap ``k``'s grid frame, by the current estimates."""
        return compose(self.matchers[k].submap.local_pose, between(self.global_submap(k), node_g))

    def _commit(self, rec, loop):
        if loop is not None:
            self.graph.add_loop(*loop, rec)
        h = rec.pop("_heading", None)
        if h is not None:  # its record is the one constraints.jsonl shows under heading_constraint
            self.graph.add_loop(*h, rec["heading_constraint"], heading_only=True)
            self.heading_constraints += 1
        self.records.append(rec)
        self.observer.on_loop_candidate(rec)

    def _reject(self, rec, reason):
        rec.pop("_heading", None)
        rec.pop("heading_constraint", None)
        rec.update({"accepted": False, "reason": reason, "in_final_graph": False})
        self._commit(rec, None)

    def _transform(self, k) -> np.ndarray:
        """global ← local transform of submap ``k``'s grid (from its first node)."""
        a = self.submap_anchor[k]
        return compose(self.global_node(a), inverse(self.nodes[a]["local"]))

    def _middle_node(self, k) -> int:
        """The node halfway along submap ``k``'s stretch of the trajectory."""
        ids, _ = self._submap_nodes(k)
        return int(ids[len(ids) // 2]) if len(ids) else self.submap_anchor[k]

    def _window(self, a, j) -> tuple[float, float]:
        """The regular search window between nodes ``a`` and ``j``: the drift bound of their estimates
        (``drift.py``), at least the margin window (whose exhaustive search verifies the peak) and
        at most the regular window (beyond it the wide search takes over)."""
        lc = self.lc
        t, r = self.drift.between(a, j)
        return (min(max(t, lc.margin_window), lc.linear_search_window),
                min(max(r, math.radians(lc.margin_window_deg)), math.radians(lc.angular_search_window_deg)))

    def _search_wide(self, submap):
        """A finished submap against older ones the drift may have carried beyond the regular window
        (``wide_search.py``)."""
        lc = self.lc
        s = submap.index
        own = self._submap_nodes(s)[0].tolist()
        ks = np.array(list(self.matchers), dtype=np.int64)
        targets = ks[self._searchable(ks, s - 1, self._segment_of.get(s, 0))].tolist()
        if not own or not targets:
            return
        windows = {}
        middle = self._middle_node(s)
        for k in targets:
            lin, ang = self.drift.between(self._middle_node(k), middle)
            lin, ang = min(lin, lc.max_constraint_distance), min(ang, math.pi)
            if lin > lc.linear_search_window or ang > math.radians(lc.angular_search_window_deg):
                windows[k] = (lin, ang)  # beyond the regular search's reach
        if not windows:
            return
        content = submap_content(submap.grid, lc.adaptive_voxel_min_points, lc.adaptive_voxel_max_length)
        if len(content) < 3:
            return
        centre = np.r_[content.mean(axis=0), 0.0]
        t_s = self._transform(s)
        centre_g = compose(t_s, centre)
        cands = []
        for k, (lin, ang) in windows.items():
            m = self.matchers[k]
            c_k = compose(self._transform(k), np.r_[m.center_local, 0.0])
            dc = float(np.hypot(*(c_k[:2] - centre_g[:2])))
            if dc < lc.max_constraint_distance + lin:
                cands.append((dc, k, lin, ang))
        for _, k, lin, ang in sorted(cands)[: lc.max_submaps_per_node]:
            self._wide_pair(own, content, centre, t_s, k, lin, ang)

    def _wide_pair(self, own, content, centre, t_s, k, lin, ang):
        """The content of a finished submap (``own`` nodes, ``t_s`` its global ← local transform) against
        submap ``k`` with the windows ``lin`` / ``ang``; a pair of agreeing node matches becomes two loops."""
        lc = self.lc
        t0 = time.perf_counter()
        if k not in self.coarse:
            self.coarse[k] = coarse_grid(self.matchers[k].submap.grid)
        initial = compose(inverse(self._transform(k)), compose(t_s, centre))
        with self.cores.share():
            found = coarse_match(content, centre, initial, self.coarse[k], lin, ang)
        self.wide_searches += 1
        self.search_seconds += time.perf_counter() - t0
        if found is None:
            return
        x = compose(found[0], inverse(centre))  # submap s's local frame -> submap k's grid frame
        # the two of the submap's nodes whose points land on most of k's observed cells there
        grid = self.matchers[k].submap.grid
        counts = []
        for j in own:
            pts = self.nodes[j]["points"]
            if len(pts):
                cells = self.matchers[k].grid.cells(pts, compose(x, self.nodes[j]["local"]), np.zeros(1))[0]
                counts.append((int(grid.observed_at(cells).sum()), j))
        pair = [j for n, j in sorted(counts, reverse=True)[:2] if n > 0]
        if len(pair) < 2:
            return
        found_by = []
        for j in pair:
            rec, loop, res = self._search(k, j, initial=compose(x, self.nodes[j]["local"]), defer=True,
                                          window=(lc.linear_search_window, math.radians(lc.angular_search_window_deg)),
                                          heading=True)
            rec["search"] = f"wide ±{lin:.1f} m ±{math.degrees(ang):.0f}°, coarse score {found[1]:.3f}"
            found_by.append((rec, loop, res, j))
        if any(loop is None for _, loop, _, _ in found_by):
            for rec, loop, _, _ in found_by:
                if loop is None:
                    self._commit(rec, None)
                else:
                    self._reject(rec, "wide search: its partner node failed verification")
            return
        (_, _, r1, j1), (_, _, r2, j2) = found_by
        dt, dr = frame_offset(compose(r1.pose, inverse(self.nodes[j1]["local"])),
                              compose(r2.pose, inverse(self.nodes[j2]["local"])), centre)
        if dt > lc.consistency_translation or dr > math.radians(lc.consistency_rotation_deg):
            for rec, _, _, _ in found_by:
                self._reject(rec, f"wide search: its two nodes disagree by {dt:.2f} m, {math.degrees(dr):.1f}°")
            return
        for rec, loop, _, _ in found_by:
            self._commit(rec, loop)
        self.wide_accepted += 2
        self.optimize()  # later searches start from the corrected estimates

    # ---- the final search
    def final_search(self):
        """Search again the nodes a later loop moved (``loop_closure.final_search``).

        A node is searched around its estimate of the moment, within the drift bound of the moment.
        A loop closed later, elsewhere, can move a whole stretch of the trajectory by more than that
        window (fr-clinic: a hall passed a third time was searched 17 m and 9° from where the loops
        closed after it put it, against the submaps near that wrong place), and nothing searches
        it again. So once the run is over, every sampled node whose estimate has left the window of
        its searches (where it had none, no submap being near, the smallest window a search has:
        ``margin_window``) is matched against the submaps now near it, except those it was matched
        with before successfully, or from an estimate whose window holds its current one. The
        graph is then optimized, and the round repeats while it closes loops, at most
        ``FINAL_SEARCH_ROUNDS`` times. The new records say ``"search": "final"``.

        Its cost is bounded by the run's own: it makes at most as many searches as the run made
        before it, the nodes that moved farthest beyond their window first (a long log whose every
        stretch a late loop moved would otherwise be searched all over again at the end)."""
        if not (self.lc.enabled and self.lc.final_search and self.matchers):
            return
        t0 = time.perf_counter()
        budget = self.searches
        for _ in range(FINAL_SEARCH_ROUNDS):
            if len(self.graph.loops) != self.loops_at_last_optimize:
                self.optimize()
            before = len(self.graph.loops)
            todo = self._stale_pairs()
            left = budget - self.final_searches
            if len(todo) > left:  # the most stale, searched in the order they came
                log.info("final search: %d stale node-submap pairs, searching the %d most stale", len(todo), left)
                keep = sorted(range(len(todo)), key=lambda i: (-todo[i][0], todo[i][1], todo[i][2]))[:left]
                todo = [todo[i] for i in sorted(keep)]
            for _, j, k in todo:
                rec, loop, _ = self._search(k, j, defer=True)
                rec["search"] = "final"
                self._commit(rec, loop)
            self.final_searches += len(todo)
            self.final_accepted += len(self.graph.loops) - before
            log.info("final search: %d node-submap pairs, %d loops", len(todo), len(self.graph.loops) - before)
            if len(self.graph.loops) == before:
                break
        self.final_search_seconds += time.perf_counter() - t0

    def _stale_pairs(self) -> list[tuple[float, int, int]]:
        """(staleness, node, submap) of the pairs whose search the estimates have outdated
        (``final_search``), node after node, each node's nearest submap first; staleness: how many
        times its window the node's estimate moved."""
        out = []
        for j, at in self._sampled_at.items():
            if at is None:
                continue
            g0, lin, ang, own = at
            # never searched (no submap was near): the smallest window any search has
            lin, ang = lin or self.lc.margin_window, ang or math.radians(self.lc.margin_window_deg)
            g = self.global_node(j)
            dxy, dth = math.hypot(g[0] - g0[0], g[1] - g0[1]), abs(math.remainder(g[2] - g0[2], 2 * math.pi))
            if dxy <= lin and dth <= ang:
                continue  # still inside the window it was searched in
            moved = max(dxy / lin, dth / ang)
            for k in self._candidate_submaps(g, own):
                prev = self._searched.get((j, k))
                if prev is not None:
                    x, y, th, w_lin, w_ang, accepted = prev
                    now = self._initial(k, g)
                    if accepted or (max(abs(now[0] - x), abs(now[1] - y)) <= w_lin
                                    and abs(math.remainder(now[2] - th, 2 * math.pi)) <= w_ang):
                        continue
                out.append((moved, j, k))
        return out

    # ---- optimization
    def optimize(self, final: bool = False):
        if not self.node_order:
            return
        t0 = time.perf_counter()
        if self.lc.consistency_check:
            self._check_consistency()
        dropped = self.graph.optimize(batch=final and self.lc.final_batch,
                                      error=final or getattr(self.observer, "wants_graph_error", False),
                                      exempt=self._confirmed)
        self.optimize_seconds += time.perf_counter() - t0
        self.optimizations += 1
        self.loops_at_last_optimize = len(self.graph.loops)
        # the loops the estimates now reflect (a heading constraint ties no position)
        self.drift.update([(f.anchor, f.node) for f in self._position_loops()])
        self.since_optimize = 0
        last = self.node_order[-1]
        self.correction = compose(self.graph.node_pose(last), inverse(self.nodes[last]["local"]))
        self.last_optimize_seconds = time.perf_counter() - t0
        self.observer.on_optimized(self)
        if dropped:
            log.info("dropped %d loop constraints with large residuals", len(dropped))

    def _nearest_submap_node(self, k, pose) -> int:
        """The node of submap ``k`` whose local pose lies nearest to ``pose`` (grid frame); the anchor without one."""
        ids, xy = self._submap_nodes(k)
        if pose is None or not len(ids):
            return self.submap_anchor[k]
        return int(ids[int(np.argmin(np.hypot(xy[:, 0] - pose[0], xy[:, 1] - pose[1])))])

    def _submap_nodes(self, k) -> tuple[np.ndarray, np.ndarray]:
        """(ids, (N, 2) local positions) of finished submap ``k``'s nodes, in insertion order. Kept once
        every node is known: a finished submap takes no more nodes and local poses never change."""
        got = self._own.get(k)
        if got is not None:
            return got
        node_indices = self.matchers[k].submap.node_indices
        ids = [i for i in node_indices if i in self.nodes]
        got = (np.array(ids, dtype=np.int64),
               np.array([self.nodes[i]["local"][:2] for i in ids], dtype=float).reshape(-1, 2))
        if len(ids) == len(node_indices):
            self._own[k] = got
        return got

    def _check_consistency(self):
        """Remove loops that contradict other loops through the local chain, and note those the others
        confirm, which the residual check then spares (``consistency.py``)."""
        loops = self._position_loops()
        self._confirmed = []
        if len(loops) < 2 and self.lc.consistency_min_support == 0:
            return
        p = self._pairs.p
        rows = self._loop_rows  # what the test reads of a loop never changes: one row per loop, made once
        budget = self.drift.budget()
        for f in loops:
            if f.index not in rows:
                a, j = self.nodes[f.anchor], self.nodes[f.node]
                rows[f.index] = (*map(float, f.relative), *map(float, a["local"]), *map(float, j["local"]),
                                 a["path"], j["path"], f.record.get("score") or 0.0,
                                 *budget[self.drift.order[f.anchor]], *budget[self.drift.order[f.node]])
        m = np.array([rows[f.index] for f in loops], dtype=float).reshape(-1, 16)
        rel, la, lj, pa, pj, scores = m[:, 0:3], m[:, 3:6], m[:, 6:9], m[:, 9], m[:, 10], m[:, 11]
        ba, bj = m[:, 12:14], m[:, 14:16]
        ids = np.array([f.index for f in loops], dtype=np.int64)
        tests = self._pairs.tests(ids, rel, la, lj, pa, pj, ba, bj)
        alive = np.ones(len(loops), bool)
        for i, reason in inconsistent(tests, scores, p.min_support):
            self.graph.remove_loop(loops[i], reason)
            self.consistency_removed += 1
            alive[i] = False
        self._confirmed = [loops[i].index for i in np.flatnonzero(confirmed(tests, alive, self.lc.residual_exempt_support))]

    def submap_transforms(self) -> dict[int, np.ndarray]:
        """global ← local transform of every finished submap's grid (from its first node)."""
        return {k: self._transform(k) for k in self.matchers}

    def release_search(self):
        """No more searches: the precomputation stacks and search grids go (Slam.finish releases the
        submaps' own grids)."""
        self.coarse.clear()
        self.stacks.clear()

    def finish(self) -> dict[int, np.ndarray]:
        self.release_search()
        if self.lc.gnc_final and self.graph.loops:
            t0 = time.perf_counter()
            self.gnc_removed = len(self.graph.gnc_prune())
            self.optimize_seconds += time.perf_counter() - t0
        self.optimize(final=True)
        if hasattr(self.graph, "close"):  # a solver process: no more solves
            self.graph.close()
        return {j: self.graph.node_pose(j) for j in self.node_order}

    def summary(self) -> dict:
        acc = sum(1 for r in self.records if r["accepted"])
        final = sum(1 for r in self.records if r.get("in_final_graph"))
        found = sum(1 for r in self.records if r["relative_pose"] is not None)
        return {"loop_closure": {
            "candidates_searched": self.searches, "accepted": acc, "rejected_score": self.searches - found,
            "rejected_verification": found - acc, "removed_inconsistent": self.consistency_removed,
            "removed_gnc": self.gnc_removed,
            "removed_after_optimization": len(self.graph.removed) - self.consistency_removed - self.gnc_removed,
            "in_final_graph": final, "wide_searches": self.wide_searches, "wide_accepted": self.wide_accepted,
            "final_searches": self.final_searches, "final_accepted": self.final_accepted,
            "final_search_s": round(self.final_search_seconds, 3),
            "search_total_s": round(self.search_seconds, 3), "stack_builds": self.stacks.builds,
            "search_mean_ms": round(1e3 * self.search_seconds / self.searches, 3) if self.searches else None,
            "optimizations": self.optimizations, "optimize_total_s": round(self.optimize_seconds, 3),
            "final_error": self.graph.last_error[1], "submaps": len(self.submap_local), "nodes": len(self.node_order),
            "submaps_scored_on_field": self.field_submaps,
            "solver_process_peak_rss_mb": getattr(self.graph, "peak_rss_mb", None),
            "fresh_starts": list(self.fresh_starts), "fresh_starts_untied": self.untied_fresh_starts(),
            "heading_constraints": self.heading_constraints,
            "heading_constraints_in_final_graph": sum(1 for f in self.graph.loops if f.heading_only),
        }}

    def _position_loops(self) -> list:
        """The loops in the graph that tie positions: all but the heading constraints, which the
        consistency check, the drift bound and the fresh-start ties leave out."""
        return [f for f in self.graph.loops if not f.heading_only]

    def untied_fresh_starts(self) -> list[int]:
        """The nodes where local SLAM started afresh (``add_node``) that no loop in the graph spans: what
        was mapped after such a node hangs on what was mapped before only by the loose step between
        them, so the two may be misaligned by as much as local SLAM's doubt."""
        ends = np.array([(min(f.anchor, f.node), max(f.anchor, f.node)) for f in self._position_loops()],
                        dtype=np.int64).reshape(-1, 2)
        return [int(h) for h in self.fresh_starts if not np.any((ends[:, 0] < h) & (ends[:, 1] >= h))]


#: the translation sigma of a heading constraint [m]: no information (its rotation sigma is the match's)
HEADING_ONLY_SIGMA = 1e3


def min_score_for(lc, self_score: float) -> float:
    """The score a loop match against a submap must reach: ``min_score``, or ``min_relative_score``
    of the submap's self-score when that is lower (a sparsely observed submap)."""
    if not math.isfinite(self_score):
        return lc.min_score
    return min(lc.min_score, lc.min_relative_score * self_score)


def node_frame_covariance(cov, theta) -> np.ndarray:
    """A covariance of (x, y, θ) along the map's axes, expressed in the frame of a pose with heading
    ``theta`` in that map: J Σ Jᵀ with J = diag(R(θ)ᵀ, 1). A BetweenFactorPose2's error lives in the
    tangent space at the measured relative pose, i.e. its translation is along the node's own axes;
    the rotation is the node's heading in the map frame the covariance was computed in (the anchor's
    heading plus the relative heading), not the relative heading alone."""
    c, s = math.cos(theta), math.sin(theta)
    j = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    out = j @ np.asarray(cov, dtype=float) @ j.T
    return 0.5 * (out + out.T)


def _floored(cov, sigma_t, sigma_r) -> np.ndarray:
    """``cov`` made symmetric, its variances raised to the floor's and its eigenvalues to the smallest
    floor (``None``: the floor itself)."""
    t2, r2 = sigma_t * sigma_t, sigma_r * sigma_r
    if cov is None:
        return np.diag([t2, t2, r2])
    a = np.asarray(cov, dtype=float).tolist()
    xx, yy, tt = max(a[0][0], t2), max(a[1][1], t2), max(a[2][2], r2)
    xy, xt, yt = 0.5 * (a[0][1] + a[1][0]), 0.5 * (a[0][2] + a[2][0]), 0.5 * (a[1][2] + a[2][1])
    c = np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]])
    m = min(t2, r2)
    p, q, r = xx - m, yy - m, tt - m
    # every eigenvalue above the floor already (c - m·I positive definite, Sylvester's criterion):
    # nothing to raise, and the decomposition below would give ``c`` back up to rounding
    if p > 0 and p * q - xy * xy > 0 and p * (q * r - yt * yt) - xy * (xy * r - yt * xt) + xt * (xy * yt - q * xt) > 0:
        return c
    w, v = np.linalg.eigh(c)
    return (v * np.maximum(w, m)) @ v.T
