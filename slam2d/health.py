"""Map health: is the result trustworthy, judged from the run itself (no ground truth needed).

Two kinds of evidence:

* **Agreement with the final map.** A consistent map holds each wall where every scan that
  saw it puts it. Where poses are wrong, one scan's wall lies where other scans' rays passed.
  The map is built once more from every node at its final pose with *symmetric* votes (a
  hit and a pass-through count the same, unlike the mapping grid's 0.55 / 0.49, which keeps
  a wall that a few scans hit however many rays cross it), and each node's hits are looked
  up in it: a hit agrees when its cell or one of the 8 neighbours has more hits than
  pass-throughs; a scan agrees when ``SCAN_AGREEMENT`` of its hits do.
* **What local and global SLAM said along the way**: matches that could not be trusted,
  recovery searches, loop constraints the optimizer had to remove.

``status`` is OK, WARN or BROKEN; ``reasons`` says why when it is not OK.
"""
from __future__ import annotations

import numpy as np

#: a scan agrees with the map when at least this share of its hits lies on occupied cells
SCAN_AGREEMENT = 0.7
#: shares of scans that agree below which the map is flagged
WARN_AGREEING, BROKEN_AGREEING = 0.95, 0.8
#: shares of matched scans that were not trusted above which the map is flagged
WARN_UNTRUSTED, BROKEN_UNTRUSTED = 0.01, 0.05


def point_agreement(grid, nodes, poses) -> np.ndarray:
    """Per node, the share of its hits (at ``poses[scan_index]``) on occupied map cells (3 × 3 neighbourhood)."""
    from scipy.ndimage import maximum_filter

    if not nodes or grid.prob.size == 0:
        return np.zeros(0)
    occ = maximum_filter(grid.probability(unknown_value=0.0) > 0.5, size=3, mode="constant", cval=False)
    rows, cols = occ.shape
    sizes = np.array([len(n.hits) for n in nodes])
    if sizes.sum() == 0:
        return np.ones(len(nodes))
    # every node's hits moved to its pose in one vectorized transform (as build_map does)
    hits = np.concatenate([n.hits for n in nodes]).astype(np.float64)
    pose = np.repeat(np.array([poses[n.scan_index] for n in nodes], dtype=np.float64), sizes, axis=0)
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    inv = 1.0 / grid.resolution
    ci = np.floor((pose[:, 0] + c * hits[:, 0] - s * hits[:, 1] - grid.origin[0]) * inv).astype(np.int64)
    ri = np.floor((pose[:, 1] + s * hits[:, 0] + c * hits[:, 1] - grid.origin[1]) * inv).astype(np.int64)
    inside = (ci >= 0) & (ci < cols) & (ri >= 0) & (ri < rows)
    ok = np.zeros(len(hits))
    ok[inside] = occ[ri[inside], ci[inside]]
    out = np.ones(len(nodes))
    has = sizes > 0
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])[has]
    out[has] = np.add.reduceat(ok, starts) / sizes[has]
    return out


def vote_map(cfg, nodes, poses):
    """Every node's range data at its final pose, hits and pass-throughs weighted alike."""
    from slam2d.mapper import build_map

    votes = cfg.model_copy(deep=True)
    votes.grid.miss_probability = 1.0 - votes.grid.hit_probability
    return build_map(votes, nodes, {n.scan_index: poses[n.scan_index] for n in nodes})


def assess(cfg, nodes, poses, local: dict | None = None, loops: dict | None = None) -> dict:
    """The ``health`` section of summary.json. ``local``/``loops``: the ``local_slam`` and
    ``loop_closure`` sections (absent for odometry-only runs or local SLAM alone)."""
    agree = point_agreement(vote_map(cfg, nodes, poses), nodes, poses)
    share = float((agree >= SCAN_AGREEMENT).mean()) if agree.size else 1.0
    out = {"scans_checked": int(agree.size), "scans_agreeing_with_map": round(share, 4),
           "mean_point_agreement": round(float(agree.mean()), 4) if agree.size else None}
    reasons, level = [], 0
    if share < BROKEN_AGREEING:
        level = 2
        reasons.append(f"only {100 * share:.0f} % of scans agree with the final map (double walls: poses are wrong somewhere)")
    elif share < WARN_AGREEING:
        level = 1
        reasons.append(f"{100 * (1 - share):.0f} % of scans disagree with the final map")
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
    if loops:
        acc = loops.get("accepted", 0)
        out.update({"loop_constraints_in_final_graph": loops.get("in_final_graph", 0),
                    "loop_constraints_removed": loops.get("removed_after_optimization", 0)})
        if acc and loops.get("in_final_graph", 0) == 0:
            level = max(level, 1)
            reasons.append("every accepted loop constraint was removed by the optimizer")
    out["status"] = ("OK", "WARN", "BROKEN")[level]
    out["reasons"] = reasons
    return out


__all__ = ["assess", "point_agreement"]
