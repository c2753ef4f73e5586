"""Map health: is the result trustworthy, judged from the run itself (no ground truth needed).

Two kinds of evidence:

* **Free-space consistency of the scans at their final poses.** A scan's rays say which space
  was empty when it was taken. Where two scans' poses are right, neither sees a surface inside
  the space the other saw empty; where a pose is wrong, each does: a wall of one lies where the
  other's beams passed through (the consistency test of range scans behind Lu and Milios 1997's
  scan matching and of map-quality checks since). For every node we take a few other nodes
  near it, both from the same pass and from other passes over the place, project its hits into
  the other's beams (the nearer of the two neighbouring beams, which never interpolates across
  a depth edge) and count the hits lying more than ``2 cells + VIOLATION_RANGE_SHARE · range`` in
  front of the other's return. A pair is only as bad as the *better* of its two directions: a
  person who walked through one scan violates the other's free space in one direction only,
  a wrong pose in both. A node disagrees when its mean violation share exceeds
  ``MAX_VIOLATION``. Where the robot came back, the same test is also taken against the other
  passes alone (``free_space_checks``): neighbours from one pass drifted together and agree with
  each other, so a loop that was never closed shows only there. Ray tests, not a rasterised vote map: a map of 5 cm cells erases thin walls
  seen at grazing angles by sparse beams (1° at 20 m is 35 cm), which made correct maps of
  spatially sparse logs look broken. A scan's beams here are its returns and its returns beyond
  the usable range, not its no-returns: a sensor also drops returns off glass, black or shiny
  surfaces and at grazing angles, and a log writes those as no-returns, so a no-return ray
  through a wall another scan saw is no sign of a wrong pose.
* **What local and global SLAM said along the way**: matches that could not be trusted,
  recovery searches, loop constraints the optimizer had to remove, and places where local SLAM
  lost track and started afresh that no loop in the final graph spans (``fresh_starts_untied``:
  what was mapped after such a place hangs on what was mapped before by a step as loose as the
  recovery window, so a WARN, even where no revisit shows it).

``status`` is OK, WARN or BROKEN; ``reasons`` says why when it is not OK, and
``revisits_disagreeing_at`` says where: the longest stretches of the trajectory whose scans
disagree with the earlier pass, with a map position to look at.
"""
from __future__ import annotations

import numpy as np

#: a node disagrees with its neighbours when, on average over them, more than this share of its
#: hits lie inside their free space
MAX_VIOLATION = 0.1
#: shares of nodes that agree below which the map is flagged
WARN_AGREEING, BROKEN_AGREEING = 0.95, 0.8
#: shares of matched scans that were not trusted above which the map is flagged
WARN_UNTRUSTED, BROKEN_UNTRUSTED = 0.01, 0.05
#: shares of scans local SLAM never matched (too few points) above which the map is flagged
WARN_UNMATCHED, BROKEN_UNMATCHED = 0.1, 0.5
#: nodes whose sensors lie within this distance [m] are compared ...
NEIGHBOUR_RADIUS = 8.0
#: ... the nearest this many from the same pass (path distance < 2 × the radius) and as many from other passes
NEIGHBOURS_PER_PASS = 4
#: a hit violates free space when it lies 2 cells + this share of its range in front of the other's return
VIOLATION_RANGE_SHARE = 0.01
#: the health section lists this many of the longest stretches where revisits disagree
STRETCHES_REPORTED = 5


def free_space_violation(nodes, poses, resolution: float) -> np.ndarray:
    """Per node, the mean share of its hits inside its neighbours' free space (module docstring);
    NaN where no neighbour sees any of them."""
    return free_space_checks(nodes, poses, resolution)[0]


def free_space_checks(nodes, poses, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Per node: (the mean share of its hits inside its neighbours' free space, the same over its
    neighbours from *other passes* only, pooled by hits: violating over checked hits of every such
    pair, each pair in its better direction). NaN where no (other-pass) neighbour sees its hits.

    The second is the revisit test: where the robot came back, a wrong pose shows against the
    earlier pass, while its neighbours from the same pass drifted with it and agree; pooling by hits
    gives a pair that sees little of the other (a revisit in the opposite direction with a 180°
    laser) little say."""
    from slam2d import _kernels
    from slam2d.threads import in_threads

    out = np.full(len(nodes), np.nan)
    revisit = np.full(len(nodes), np.nan)
    if len(nodes) < 2:
        return out, revisit
    # every node's sensor, hits and beams in the map frame, from flat float32 copies of the nodes' rays
    # a node's free space: its returns' rays, and those of returns beyond the usable range (its first
    # ``far_misses`` misses), not its no-return rays (module docstring)
    hit_start = np.r_[0, np.cumsum([len(n.hits) for n in nodes])].astype(np.int64)
    miss_start = np.r_[0, np.cumsum([n.far_misses for n in nodes])].astype(np.int64)
    flat = [np.concatenate([np.asarray(n.hits, dtype=np.float32).reshape(-1, 2) for n in nodes]),
            np.concatenate([np.asarray(n.misses[:n.far_misses], dtype=np.float32).reshape(-1, 2) for n in nodes])]
    q = np.array([poses[n.scan_index] for n in nodes], dtype=np.float64).reshape(-1, 3)
    sensors = np.array([n.origin for n in nodes], dtype=np.float64).reshape(-1, 2)
    origins, hits, bearings, ranges, beam_start, steps = _kernels.world_beams(q, sensors, flat[0], hit_start, flat[1],
                                                                              miss_start)
    del flat
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(origins, axis=0).T))])
    # the neighbours each node is compared with: the nearest of the same pass, then of other passes
    pairs = _kernels.pick_neighbours(origins, path, NEIGHBOUR_RADIUS, 2 * NEIGHBOUR_RADIUS, NEIGHBOURS_PER_PASS)
    if not len(pairs):
        return out, revisit
    other_pass = pairs[:, 2] == 1
    pairs = np.ascontiguousarray(pairs[:, :2])
    # both directions of every pair in one kernel call
    both = np.concatenate([pairs, pairs[:, ::-1]])
    counts = np.zeros((len(both), 2), dtype=np.int64)

    def count(lo, hi):  # pair by pair: how the pairs are split between threads changes nothing
        counts[lo:hi] = _kernels.free_space_counts(hits, hit_start, origins, bearings, ranges, beam_start, steps,
                                                   both[lo:hi], float(resolution), VIOLATION_RANGE_SHARE)

    in_threads(count, len(both))
    ij, ji = counts[:len(pairs)], counts[len(pairs):]
    ok = (ij[:, 1] > 0) & (ji[:, 1] > 0)
    s_ij, s_ji = ij[:, 0] / np.maximum(ij[:, 1], 1), ji[:, 0] / np.maximum(ji[:, 1], 1)
    share = np.minimum(s_ij, s_ji)
    better = np.where((s_ij <= s_ji)[:, None], ij, ji)  # (violating, checked) hits in the better direction
    node, share = pairs[ok, 0], share[ok]  # grouped by node already (picks run in node order)
    if len(node):
        first = np.flatnonzero(np.r_[True, node[1:] != node[:-1]])
        out[node[first]] = np.add.reduceat(share, first) / np.diff(np.r_[first, len(node)])
    keep = ok & other_pass
    node, better = pairs[keep, 0], better[keep]
    if len(node):
        first = np.flatnonzero(np.r_[True, node[1:] != node[:-1]])
        bad, seen = np.add.reduceat(better[:, 0], first), np.add.reduceat(better[:, 1], first)
        revisit[node[first]] = bad / np.maximum(seen, 1)
    return out, revisit


def disagreeing_stretches(nodes, poses, violation: np.ndarray, most: int = STRETCHES_REPORTED) -> list[dict]:
    """Where the map disagrees with itself: the runs of consecutive nodes whose violation share exceeds
    ``MAX_VIOLATION`` (a node that agrees ends a run, and so does more than ``NEIGHBOUR_RADIUS`` of
    path without a checked node; nodes not checked, NaN, neither extend nor break it), longest
    first, at most ``most``: first and last scan, the number of disagreeing nodes, and the map
    position [m] of the run's middle one, so a user can find the place in map.png."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    runs, cur = [], []
    for i, x in enumerate(violation):
        if np.isnan(x):
            continue
        if cur and path[nodes[i].scan_index] - path[nodes[cur[-1]].scan_index] > NEIGHBOUR_RADIUS:
            runs.append(cur)
            cur = []
        if x > MAX_VIOLATION:
            cur.append(i)
        elif cur:
            runs.append(cur)
            cur = []
    if cur:
        runs.append(cur)
    runs.sort(key=lambda r: (-len(r), r[0]))
    out = []
    for r in runs[:most]:
        mid = poses[nodes[r[len(r) // 2]].scan_index]
        out.append({"scans": [int(nodes[r[0]].scan_index), int(nodes[r[-1]].scan_index)], "nodes": len(r),
                    "at": [round(float(mid[0]), 1), round(float(mid[1]), 1)]})
    return out


def assess(cfg, nodes, poses, local: dict | None = None, loops: dict | None = None, scans: int | None = None) -> dict:
    """The ``health`` section of summary.json. ``local``/``loops``: the ``local_slam`` and
    ``loop_closure`` sections (absent for odometry-only runs or local SLAM alone); ``scans``: how
    many scans the run took."""
    v, rv = free_space_checks(nodes, poses, cfg.grid.resolution)
    where = disagreeing_stretches(nodes, poses, rv)
    v, rv = v[~np.isnan(v)], rv[~np.isnan(rv)]
    share = float((v <= MAX_VIOLATION).mean()) if v.size else 1.0
    revisits = float((rv <= MAX_VIOLATION).mean()) if rv.size else 1.0
    out = {"scans_checked": int(v.size), "scans_agreeing_with_map": round(share, 4),
           "mean_free_space_violation": round(float(v.mean()), 4) if v.size else None,
           "revisits_checked": int(rv.size), "revisits_agreeing": round(revisits, 4),
           "revisits_disagreeing_at": where}
    reasons, level = [], 0
    if share < BROKEN_AGREEING:
        level = 2
        reasons.append(f"only {100 * share:.0f} % of scans agree with the final map (their walls lie in each other's free space: poses are wrong somewhere)")
    elif share < WARN_AGREEING:
        level = 1
        reasons.append(f"{100 * (1 - share):.0f} % of scans disagree with the final map")
    if revisits < BROKEN_AGREEING:
        level = 2
        reasons.append(f"only {100 * revisits:.0f} % of the scans where the robot came back agree with its earlier pass "
                       f"(a loop was not closed, or closed wrong){_worst(where)}")
    elif revisits < WARN_AGREEING:
        level = max(level, 1)
        reasons.append(f"{100 * (1 - revisits):.0f} % of the scans where the robot came back disagree with its earlier pass"
                       f"{_worst(where)}")
    if local:
        matched = local.get("matched_scans", 0) + local.get("untrusted", 0)
        untrusted = local.get("untrusted", 0) / matched if matched else 0.0
        out.update({"untrusted_match_share": round(untrusted, 4), "recovery_searches": local.get("recovery_searches", 0),
                    "recovered": local.get("recovered", 0), "inserted_untrusted": local.get("inserted_untrusted", 0)})
        if untrusted > BROKEN_UNTRUSTED:
            level = 2
            reasons.append(f"{100 * untrusted:.1f} % of scans could not be matched with confidence")
        elif untrusted > WARN_UNTRUSTED:
            level = max(level, 1)
            reasons.append(f"{100 * untrusted:.1f} % of scans could not be matched with confidence")
        if scans:
            # scans local SLAM never tried to match (too few points left after filtering): their poses are
            # the prediction's. Not among them: standing still (``still``), and the first scan, which
            # has no submap to be matched against (a run of 5 scans is not 20 % unmatched)
            unmatched = max(0.0, 1.0 - (matched + local.get("still", 0) + 1) / scans)
            out["unmatched_share"] = round(unmatched, 4)
            if unmatched > WARN_UNMATCHED:
                level = max(level, 2 if unmatched > BROKEN_UNMATCHED else 1)
                reasons.append(f"{100 * unmatched:.0f} % of scans were never matched (too few points in them?): their "
                               "poses are the odometry's or the prediction's")
    if loops:
        acc = loops.get("accepted", 0)
        out.update({"loop_constraints_in_final_graph": loops.get("in_final_graph", 0),
                    "loop_constraints_removed": loops.get("removed_after_optimization", 0)})
        if acc and loops.get("in_final_graph", 0) == 0:
            level = max(level, 1)
            reasons.append("every accepted loop constraint was removed by the optimizer")
        untied = loops.get("fresh_starts_untied") or []
        if untied:
            out["fresh_starts_untied"] = untied
            level = max(level, 1)
            more = f" (and at {len(untied) - 1} more)" if len(untied) > 1 else ""
            reasons.append(f"local SLAM lost track at scan {untied[0]}{more} and no loop closure tied what it mapped after "
                           f"to what it mapped before: the two may be misaligned there")
    out["status"] = ("OK", "WARN", "BROKEN")[level]
    out["reasons"] = reasons
    return out


def _worst(where: list[dict]) -> str:
    if not where:
        return ""
    w = where[0]
    return f"; the longest stretch: scans {w['scans'][0]}-{w['scans'][1]}, around ({w['at'][0]}, {w['at'][1]}) m"


__all__ = ["assess", "disagreeing_stretches", "free_space_checks", "free_space_violation"]
