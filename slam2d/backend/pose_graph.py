"""The pose graph (Hess et al. 2016, Sec. V; Cartographer's sparse pose adjustment), solved with GTSAM.

Variables are node poses in the map frame; a submap's pose is the pose of its first node
(the node whose local pose started it), so a submap needs no variable of its own. Factors:
a prior on the first node; node-in-submap constraints from local SLAM between a submap's
first node and each node inserted into it (their noise from the real-time matcher's
covariance, in the node's frame, plus the submap's drift and what local SLAM could not vouch for
since its first node); local SLAM's step between consecutive nodes, known to a
match's floor plus what local SLAM could not vouch for (``GlobalSlam.add_node``; where local SLAM
started afresh, the only link); loop-closure constraints with their own covariance from the match,
under a Huber robust noise model. ``optimize`` solves from the current estimate, either by batch
Levenberg-Marquardt over the whole graph or, with ``incremental``, by iSAM2 (Kaess et al. 2012),
which takes only the factors and nodes added since its last update, re-eliminates the part of
the Bayes tree they touch, and drops removed loop constraints from its own factors too
(``update(new factors, new values, removed indices)``); ``optimize(batch=True)`` is the
batch solve in either mode. Loop constraints whose residual stays large afterwards are removed
and the graph solved again (a second judge: the first is ``consistency``, which does not use
the solution).
This is the only module that imports gtsam.
"""
from __future__ import annotations

import logging
import math

import gtsam
import numpy as np

from slam2d.geometry import between
from slam2d.types import LoopFactor

log = logging.getLogger(__name__)


def _key(kind: str, i: int) -> int:
    return gtsam.symbol(kind, i)


def _pose(p) -> gtsam.Pose2:
    return gtsam.Pose2(float(p[0]), float(p[1]), float(p[2]))


def _arr(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


#: loops whose residual, screened in numpy, comes within this share of a limit are measured by gtsam
RESIDUAL_SCREEN = 0.9
#: iSAM2 relinearization steps after an update at most (they stop once no variable moved past the threshold)
ISAM_EXTRA_STEPS = 5
#: iSAM2 relinearizes a node whose linear update exceeds this in x [m], y [m] or θ [rad]. Rotation is what
#: makes a pose graph nonlinear (a between factor's Jacobians turn with the heading), so θ keeps a tight
#: threshold; x and y take GTSAM's default, 0.1: relinearizing every node a loop moved by a centimetre
#: re-eliminated most of the graph after each loop, half the solver's time
RELINEARIZE_THRESHOLD = (0.1, 0.1, 0.01)


def _fuse(parts) -> tuple[gtsam.Pose2, np.ndarray]:
    """One constraint for several between the same two nodes (measurement, covariance), to first
    order: informations added, measurement their information-weighted mean in the tangent space
    of the first (the parts differ by little: the same two submaps' first nodes through different
    nodes)."""
    if len(parts) == 1:
        return parts[0]
    z0 = parts[0][0]
    info = np.zeros((3, 3))
    rhs = np.zeros(3)
    for z, cov in parts:
        lam = np.linalg.inv(cov)
        info += lam
        rhs += lam @ np.asarray(gtsam.Pose2.Logmap(z0.between(z)), dtype=float)
    cov = np.linalg.inv(info)
    return z0.compose(gtsam.Pose2.Expmap(cov @ rhs)), 0.5 * (cov + cov.T)


class PoseGraph:
    def __init__(self, huber_scale: float = 1.0, max_residual_trans: float = 0.3, max_residual_rot: float = 0.05,
                 incremental: bool = False):
        self.graph = gtsam.NonlinearFactorGraph()
        self.incremental = incremental
        self.isam = None
        if incremental:
            params = gtsam.ISAM2Params()
            thresholds = gtsam.ISAM2ThresholdMap()
            thresholds.insert(("n", np.array(RELINEARIZE_THRESHOLD, dtype=float)))  # node keys: _key("n", j)
            params.setRelinearizeThreshold(thresholds)
            params.relinearizeSkip = 1
            self.isam = gtsam.ISAM2(params)
        self._pending: list[int] = []      # graph indices of factors iSAM2 has not seen
        self._new_values = gtsam.Values()  # nodes iSAM2 has not seen
        self._isam_index: dict[int, int] = {}  # graph index -> iSAM2's index of the same factor
        self._removals: list[int] = []     # iSAM2 indices of factors removed since its last update
        self.values = gtsam.Values()
        self._node_ids: list[int] = []       # every node's id, as added
        self._ids: np.ndarray | None = None  # the same ascending, while no node is added
        self.huber_scale = huber_scale
        self.max_residual_trans = max_residual_trans
        self.max_residual_rot = max_residual_rot
        self.loops: list[LoopFactor] = []
        self.removed: list[LoopFactor] = []
        self._unscreened: set[int] = set()  # graph indices of local factors ``_reduced`` leaves out
        self.has_prior = False
        self.iterations = 0
        self.last_error = (math.nan, math.nan)
        self.isam_failed_at: str | None = None  # where iSAM2 gave up (``_leave_isam``), if it did

    # ---- variables
    def add_node(self, j: int, pose):
        if not self.values.exists(_key("n", j)):
            self.values.insert(_key("n", j), _pose(pose))
            self._node_ids.append(int(j))
            if self.incremental:
                self._new_values.insert(_key("n", j), _pose(pose))
            if not self.has_prior:
                self._add(gtsam.PriorFactorPose2(_key("n", j), _pose(pose),
                                                 gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, 1e-4]))))
                self.has_prior = True

    def _add(self, factor) -> int:
        self.graph.add(factor)
        i = self.graph.size() - 1
        if self.incremental:
            self._pending.append(i)
        return i

    def node_pose(self, j) -> np.ndarray:
        return _arr(self.values.atPose2(_key("n", j)))

    def has_node(self, j) -> bool:
        return self.values.exists(_key("n", j))

    def all_node_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(node ids ascending, (N, 3) poses) of every node, in one call (gtsam's values are in key
        order, which is node id order)."""
        if self._ids is None or len(self._ids) != len(self._node_ids):
            self._ids = np.array(sorted(self._node_ids), dtype=np.int64)
        return self._ids, np.asarray(gtsam.utilities.extractPose2(self.values), dtype=float).reshape(-1, 3)

    # ---- factors
    def add_intra(self, anchor: int, j: int, relative, covariance: np.ndarray, screened: bool = True):
        """Node ``j`` in the submap whose first node is ``anchor``, or local SLAM's step from node
        ``anchor`` to ``j``. ``screened``: the factor is part of the graph ``gnc_prune`` screens the
        loops on (``_reduced``); False for a step that another path of local constraints already spans."""
        noise = gtsam.noiseModel.Gaussian.Covariance(np.asarray(covariance, dtype=float))
        i = self._add(gtsam.BetweenFactorPose2(_key("n", anchor), _key("n", j), _pose(relative), noise))
        if not screened:
            self._unscreened.add(i)

    def add_loop(self, anchor: int, j: int, relative, covariance, record: dict, heading_only: bool = False) -> LoopFactor:
        """``covariance``: 3×3 in the node's frame, or 3 sigmas. ``heading_only``: a heading constraint
        (its translation σ uninformative): the residual check judges its rotation alone."""
        c = np.asarray(covariance, dtype=float)
        base = gtsam.noiseModel.Diagonal.Sigmas(c) if c.ndim == 1 else gtsam.noiseModel.Gaussian.Covariance(c)
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.huber_scale), base)
        i = self._add(gtsam.BetweenFactorPose2(_key("n", anchor), _key("n", j), _pose(relative), noise))
        f = LoopFactor(i, anchor, j, np.asarray(relative, dtype=float), record, base, heading_only)
        self.loops.append(f)
        return f

    def remove_loop(self, f: LoopFactor, reason: str):
        self.graph.remove(f.index)
        if f.index in self._isam_index:
            self._removals.append(self._isam_index.pop(f.index))
        elif f.index in self._pending:
            self._pending.remove(f.index)
        self.loops.remove(f)
        f.record["in_final_graph"] = False
        f.record["reason"] = reason
        self.removed.append(f)

    def residual(self, f: LoopFactor) -> np.ndarray:
        """(x, y, θ) of the loop's measurement against the solution; a heading constraint's is its
        rotation alone (it claims no translation)."""
        a = self.values.atPose2(_key("n", f.anchor))
        n = self.values.atPose2(_key("n", f.node))
        r = _arr(a.between(n).between(_pose(f.relative)))
        return np.array([0.0, 0.0, r[2]]) if f.heading_only else r

    # ---- solve
    def _solve(self, batch: bool = False):
        if self.incremental and not batch:
            try:
                self._update_isam()
                return
            except RuntimeError as e:  # gtsam's IndeterminateLinearSystemException
                if "Indeterminate linear system" not in str(e):
                    raise
                self._leave_isam(e)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(50)
        opt = gtsam.LevenbergMarquardtOptimizer(self.graph, self.values, params)
        before = self.graph.error(self.values)
        self.values = opt.optimize()
        self.iterations += opt.iterations()
        self.last_error = (before, self.graph.error(self.values))

    def _leave_isam(self, error: Exception):
        """iSAM2 eliminates without damping, and a graph whose information spans more orders of magnitude
        than floating point keeps (a nearly free stretch of nodes; a constraint far tighter than the
        rest) breaks its elimination: 'indeterminate linear system'. Levenberg-Marquardt damps each
        step and solves the same graph, so the graph is solved in batch from here on (every factor and
        node is in ``graph`` and ``values`` already)."""
        where = str(error).split("(Symbol:", 1)[-1].split(")", 1)[0].strip() if "(Symbol:" in str(error) else "?"
        log.warning("pose graph: iSAM2 found the system indeterminate near %s; solving in batch from here on", where)
        self.incremental = False
        self.isam = None
        self.isam_failed_at = where
        self._pending, self._new_values, self._isam_index, self._removals = [], gtsam.Values(), {}, []

    def _update_isam(self):
        new = gtsam.NonlinearFactorGraph()
        for i in self._pending:
            new.add(self.graph.at(i))
        r = self.isam.update(new, self._new_values, self._removals)
        for i, k in zip(self._pending, r.getNewFactorsIndices()):
            self._isam_index[i] = int(k)
        self._pending, self._new_values, self._removals = [], gtsam.Values(), []
        self.iterations += 1
        # a loop moves nodes far from where they were linearized: relinearize until none moves enough
        for _ in range(ISAM_EXTRA_STEPS):
            r = self.isam.update()
            self.iterations += 1
            if r.getVariablesRelinearized() == 0:
                break
        self.values = self.isam.calculateEstimate()
        self.last_error = (math.nan, math.nan)  # ``optimize`` computes the error after, when asked

    def gnc_prune(self) -> list[LoopFactor]:
        """Graduated non-convexity (Yang et al. 2020; ``gtsam.GncLMOptimizer``, truncated least squares)
        over the loops as plain Gaussians, every other factor a known inlier; loops it weighs below
        0.5 are removed. Returns them. It runs on ``_reduced``'s graph: the same loops over fewer
        variables, without the steps between consecutive nodes that a submap already links (they
        stiffen the chain between its nodes but tie no new places together; with them, hardly any
        node could be eliminated and the screen cost several times as much). The solves after it
        have every factor, and the residual check removes what the steps contradict."""
        g, values, slots = self._reduced()
        if not slots:
            return []
        params = gtsam.GncLMParams()
        params.setKnownInliers([k for k in range(g.size()) if k not in slots])
        opt = gtsam.GncLMOptimizer(g, values, params)
        opt.optimize()
        w = opt.getWeights()
        out = [f for k, f in slots.items() if w[k] < 0.5]
        for f in out:
            self.remove_loop(f, "GNC outlier")
        return out

    def _reduced(self):
        """The graph with every node that only links two others through local constraints
        eliminated: its two constraints (a → j, b → j) become one, a → b, whose measurement is their
        composition and whose covariance is exactly what marginalizing j out of the two gives to
        first order (Ad_z_b (Σ_a + Σ_b) Ad_z_bᵀ, both in j's frame). Nodes with one local constraint
        go with it (a leaf changes no other node's solution); a node is only eliminated when both
        its neighbours stay. In slam2d's graph, where a node hangs from the first nodes of the one or
        two submaps it lies in (the steps between consecutive nodes that a submap also links are left
        out: ``gnc_prune``), what stays is those first nodes, the loops' ends and the prior's node.
        The composed constraints between the same two nodes are fused into one (``_fuse``). Loops go
        in as plain Gaussians. Returns (graph, values, {graph index: LoopFactor})."""
        by_index = {f.index: f for f in self.loops}
        locals_of: dict[int, list[int]] = {}
        fixed = set()
        for i in range(self.graph.size()):
            if not self.graph.exists(i) or i in self._unscreened:
                continue
            keys = list(self.graph.at(i).keys()) if i not in by_index else []
            if i in by_index:
                fixed.update((_key("n", by_index[i].anchor), _key("n", by_index[i].node)))
            elif len(keys) != 2:
                fixed.update(keys)
            else:
                for k in keys:
                    locals_of.setdefault(k, []).append(i)
        candidates = {k for k, fs in locals_of.items() if k not in fixed and len(fs) <= 2}

        def other(i, k):
            a, b = self.graph.at(i).keys()
            return b if a == k else a

        gone = set()
        for k in candidates:
            ends = [other(i, k) for i in locals_of[k]]
            if len(set(ends)) == len(ends) and not any(e in candidates for e in ends):
                gone.add(k)
        g = gtsam.NonlinearFactorGraph()
        slots = {}
        values = gtsam.Values()
        for k in self.values.keys():
            if k not in gone:
                values.insert(k, self.values.atPose2(k))
        for i in range(self.graph.size()):
            if not self.graph.exists(i) or i in self._unscreened:
                continue
            f = by_index.get(i)
            if f is not None:
                slots[g.size()] = f
                g.add(gtsam.BetweenFactorPose2(_key("n", f.anchor), _key("n", f.node), _pose(f.relative), f.base))
            elif not any(k in gone for k in self.graph.at(i).keys()):
                g.add(self.graph.at(i))
        fused: dict[tuple[int, int], list] = {}
        for k in sorted(gone):
            fs = locals_of[k]
            if len(fs) < 2:
                continue
            (a, za, ca), (b, zb, cb) = (self._towards(i, k) for i in fs)
            if a > b:
                (a, za, ca), (b, zb, cb) = (b, zb, cb), (a, za, ca)
            adj = zb.AdjointMap()
            cov = adj @ (ca + cb) @ adj.T
            fused.setdefault((a, b), []).append((za.compose(zb.inverse()), 0.5 * (cov + cov.T)))
        for (a, b), parts in fused.items():
            z, cov = _fuse(parts)
            g.add(gtsam.BetweenFactorPose2(a, b, z, gtsam.noiseModel.Gaussian.Covariance(cov)))
        return g, values, slots

    def _towards(self, i: int, k: int):
        """Local constraint ``i`` as (other node, measured other⁻¹ ∘ k, covariance in k's frame)."""
        f = self.graph.at(i)
        a, b = f.keys()
        z, cov = f.measured(), f.noiseModel().covariance()
        if b == k:
            return a, z, cov
        adj = z.AdjointMap()  # k⁻¹ ∘ a = z, so a⁻¹ ∘ k = z⁻¹ with the noise carried by Ad_z
        return b, z.inverse(), adj @ cov @ adj.T

    def _excess(self, r) -> float:
        return max(math.hypot(r[0], r[1]) / self.max_residual_trans, abs(r[2]) / self.max_residual_rot)

    def _offenders(self) -> list[tuple[float, LoopFactor]]:
        """(excess, loop) of every loop whose residual exceeds the limits (excess: by how many times),
        in loop order. All loops are screened at once in numpy; those within ``RESIDUAL_SCREEN`` of
        a limit or over it are measured again by gtsam, so every verdict and excess is gtsam's."""
        if not self.loops:
            return []
        ids, poses = self.all_node_poses()
        a = poses[np.searchsorted(ids, [f.anchor for f in self.loops])]
        n = poses[np.searchsorted(ids, [f.node for f in self.loops])]
        r = between(between(a, n), np.array([f.relative for f in self.loops]).reshape(-1, 3))
        r[[f.heading_only for f in self.loops], :2] = 0.0  # as ``residual``: a heading constraint's is its rotation
        screen = np.maximum(np.hypot(r[:, 0], r[:, 1]) / self.max_residual_trans, np.abs(r[:, 2]) / self.max_residual_rot)
        out = []
        for k in np.flatnonzero(screen > RESIDUAL_SCREEN):
            f = self.loops[int(k)]
            excess = self._excess(self.residual(f))
            if excess > 1.0:
                out.append((excess, f))
        return out

    def optimize(self, max_rounds: int = 20, batch: bool = False, error: bool = True, exempt=()) -> list[LoopFactor]:
        """Solve; then repeatedly drop the worst loop constraints whose residual stays large and
        solve again. Only the worst quarter of the offenders goes per round, so that a few false
        constraints that bend the graph do not take the true ones with them. Returns the dropped.
        ``batch``: Levenberg-Marquardt over the whole graph even when incremental (iSAM2 is not
        updated afterwards: for the last solve). ``error``: leave the graph's error at the solution
        in ``last_error`` (else NaN after an iSAM2 solve). ``exempt``: ids of loops this check leaves
        in place whatever their residual (those other loops confirm: ``consistency.confirmed``); a
        loop's id is ``record["id"]`` where its record has one (``solver_process``), else its index."""
        self._solve(batch)
        dropped = []
        spared = set(exempt)
        for rnd in range(max_rounds + 1):
            bad = [b for b in self._offenders() if b[1].record.get("id", b[1].index) not in spared]
            if not bad:
                break
            bad.sort(key=lambda b: -b[0])
            # the worst quarter per round; in the last round every remaining offender
            worst = [f for _, f in (bad if rnd == max_rounds else bad[: max(1, len(bad) // 4)])]
            for f in worst:
                self.remove_loop(f, "residual after optimization")
            dropped.extend(worst)
            self._solve(batch)
        if error and math.isnan(self.last_error[1]):  # iSAM2 solves leave it to here: a pass over every factor
            self.last_error = (self.last_error[0], self.graph.error(self.values))
        return dropped
