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


def consistency(nodes: list[Node], poses: np.ndarray, resolution: float) -> dict:
    """The free-space test of ``nodes`` at ``poses`` (indexed by scan): how many scans were checked,
    the share agreeing with their neighbours (violation share at most ``health.MAX_VIOLATION``),
    the mean violation share, and the same over the revisits (neighbours from other passes only)."""
    v, rv = free_space_checks(nodes, np.asarray(poses, dtype=float), resolution)
    v, rv = v[~np.isnan(v)], rv[~np.isnan(rv)]

    def share(x):
        return round(float((x <= MAX_VIOLATION).mean()), 4) if x.size else None

    def mean(x):
        return round(float(x.mean()), 4) if x.size else None

    return {"scans_checked": int(v.size), "scans_agreeing": share(v), "mean_violation": mean(v),
            "revisits_checked": int(rv.size), "revisits_agreeing": share(rv), "revisit_mean_violation": mean(rv)}


def compare(source, cfg, trajectories: dict[str, np.ndarray]) -> dict[str, dict]:
    """``consistency`` of each named trajectory (one pose per scan, NaN where it has none) on the same
    scans: those ``scan_nodes`` picks along the first, that every trajectory has a pose for."""
    names = list(trajectories)
    dense = {k: np.asarray(v, dtype=float).reshape(-1, 3) for k, v in trajectories.items()}
    nodes = scan_nodes(source, cfg, dense[names[0]])
    nodes = [n for n in nodes if all(n.scan_index < len(p) and np.all(np.isfinite(p[n.scan_index]))
                                     for p in dense.values())]
    return {k: consistency(nodes, dense[k], cfg.grid.resolution) for k in names}


__all__ = ["compare", "consistency", "scan_nodes"]
