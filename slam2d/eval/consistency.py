"""Which trajectory do the scans support? The map-health free-space test on any trajectory of a log.

A reference made by another SLAM system (the ``.gt.txt`` of ``make_sparse.py`` is GMapping's
corrected log) has errors of its own, and the ATE against it cannot tell them from a run's. The
raw scans can: where two poses of a place are right, neither scan sees a surface inside the space
the other saw empty (the free-space consistency test of ``slam2d/health.py``, after Lu and Milios
1997). Here that test is put to a trajectory read from a file: the log is read again with the
run's range filter; the scans the motion filter would insert along the first trajectory given
(Cartographer's insertion rule, so that a robot standing still does not compare a scan with
itself) are placed at its poses and tested as ``health.free_space_checks`` tests a run's nodes.
Further trajectories are tested on the same scans, so that all are judged on the same evidence:
a lower violation share means a trajectory the scans support better, whatever its ATE says.
Where two trajectories differ, the scans also say which one they side with, scan by scan: a scan
that agrees with its neighbours at one trajectory's poses and not at the other's is disputed,
and the longest stretches of such scans show where to look (``disputes``).
"""
from __future__ import annotations

import numpy as np

from slam2d.health import MAX_VIOLATION, free_space_checks
from slam2d.motion_filter import MotionFilter
from slam2d.range_data import range_data
from slam2d.types import Node


def scan_nodes(source, cfg, poses: np.ndarray) -> list[Node]:
    """Nodes (``types.Node``) of the scans of ``source`` the motion filter passes along ``poses`` (one
    per scan, in scan order; scans without a finite pose are skipped), with the range data of
    ``cfg.range_filter``."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    mf = MotionFilter(cfg.motion_filter)
    out = []
    for i, scan in enumerate(source):
        if i >= len(poses):
            break
        p = poses[i]
        if not np.all(np.isfinite(p)) or mf.is_similar(scan.timestamp, p):
            continue
        out.append(Node.of(i, scan.timestamp, p, range_data(scan, cfg.range_filter)))
    return out


#: the disputed stretches listed per comparison
DISPUTES_REPORTED = 5


def consistency(nodes: list[Node], poses: np.ndarray, resolution: float, checks=None) -> dict:
    """The free-space test of ``nodes`` at ``poses`` (indexed by scan): how many scans were checked,
    the share agreeing with their neighbours (violation share at most ``health.MAX_VIOLATION``),
    the mean violation share, and the same over the revisits (neighbours from other passes only).
    ``checks``: ``health.free_space_checks``' result for them, when already computed."""
    v, rv = free_space_checks(nodes, np.asarray(poses, dtype=float), resolution) if checks is None else checks
    v, rv = v[~np.isnan(v)], rv[~np.isnan(rv)]

    def share(x):
        return round(float((x <= MAX_VIOLATION).mean()), 4) if x.size else None

    def mean(x):
        return round(float(x.mean()), 4) if x.size else None

    return {"scans_checked": int(v.size), "scans_agreeing": share(v), "mean_violation": mean(v),
            "revisits_checked": int(rv.size), "revisits_agreeing": share(rv), "revisit_mean_violation": mean(rv)}


def disputes(nodes: list[Node], here: np.ndarray, there: np.ndarray, names=("here", "there")) -> dict:
    """Where the scans side with one of two trajectories only. ``here``, ``there``: each node's
    violation share at either trajectory's poses (``health.free_space_checks``; NaN: not checked).
    A node is disputed when it agrees with its neighbours (share at most ``health.MAX_VIOLATION``)
    at one trajectory's poses and not at the other's. Returns how many side with each (keys
    ``agree_only_<name>``) and the longest stretches of consecutive disputed nodes siding with the
    same one (scan range, node count, the trajectory they side with), longest first."""
    ok_here, ok_there = here <= MAX_VIOLATION, there <= MAX_VIOLATION
    checked = ~np.isnan(here) & ~np.isnan(there)
    side = np.where(checked & ok_here & ~ok_there, 0, np.where(checked & ok_there & ~ok_here, 1, -1))
    runs = []
    i = 0
    while i < len(side):
        j = i
        while j + 1 < len(side) and side[j + 1] == side[i]:
            j += 1
        if side[i] >= 0:
            runs.append((j - i + 1, nodes[i].scan_index, nodes[j].scan_index, names[side[i]]))
        i = j + 1
    runs.sort(key=lambda r: (-r[0], r[1]))
    return {f"agree_only_{names[0]}": int((side == 0).sum()), f"agree_only_{names[1]}": int((side == 1).sum()),
            "stretches": [{"scans": [a, b], "nodes": n, "agree_with": who} for n, a, b, who in runs[:DISPUTES_REPORTED]]}


def compare(source, cfg, trajectories: dict[str, np.ndarray]) -> dict[str, dict]:
    """``consistency`` of each named trajectory (one pose per scan, NaN where it has none) on the same
    scans: those ``scan_nodes`` picks along the first, that every trajectory has a pose for. Every
    trajectory after the first also gets ``disputes`` with the first (``here``: this trajectory,
    ``there``: the first) under ``disputes``."""
    names = list(trajectories)
    dense = {k: np.asarray(v, dtype=float).reshape(-1, 3) for k, v in trajectories.items()}
    nodes = scan_nodes(source, cfg, dense[names[0]])
    nodes = [n for n in nodes if all(n.scan_index < len(p) and np.all(np.isfinite(p[n.scan_index]))
                                     for p in dense.values())]
    checks = {k: free_space_checks(nodes, dense[k], cfg.grid.resolution) for k in names}
    out = {k: consistency(nodes, dense[k], cfg.grid.resolution, checks[k]) for k in names}
    for k in names[1:]:
        out[k]["disputes"] = {"with": names[0], **disputes(nodes, checks[k][0], checks[names[0]][0])}
    return out


__all__ = ["compare", "consistency", "disputes", "scan_nodes"]
