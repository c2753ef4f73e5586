"""The relations metric (Kümmerle et al. 2009, "On measuring the accuracy of SLAM algorithms", Sec. III),
as Cartographer's ``compute_relations_metrics`` reports it.

For each relation (t1, t2, δ*): error = (pose(t1)⁻¹ · pose(t2)) · δ*⁻¹; the statistics are
mean ± sample standard deviation (n − 1) of |t| [m], |t|² [m²], |θ| [deg], θ² [deg²].
Relation stamps are matched to trajectory stamps within a tolerance; between stamps the
pose is interpolated; stamps outside the trajectory are counted as unmatched, never
silently dropped. ``exact``: only relations whose two stamps are both poses of the trajectory
are scored, the others counted as ``not_exact``: a trajectory of a thinned log (``degrade.py
--keep-every``) has a pose for few relation stamps, and the interpolation across the scans it
dropped, not the SLAM, then makes most of the error.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam2d.io._text import read_numeric_table
from slam2d.geometry import between, compose, interpolate_pose, inverse


@dataclass
class Relations:
    t1: np.ndarray
    t2: np.ndarray
    delta: np.ndarray  # (R, 3)


def read_relations(path) -> Relations:
    rows, _ = read_numeric_table(path, 8, "t1 t2 x y z roll pitch yaw", "relation")
    rows = [(v[0], v[1], v[2], v[3], v[7]) for v in rows]
    a = np.array(rows)
    return Relations(a[:, 0], a[:, 1], a[:, 2:5])


class PoseLookup:
    """Pose at a timestamp: exact stamp within ``tolerance``, else interpolation between neighbours."""

    def __init__(self, times: np.ndarray, poses: np.ndarray, tolerance: float = 1e-4):
        order = np.argsort(times, kind="stable")
        self.t = np.asarray(times, dtype=float)[order]
        self.p = np.asarray(poses, dtype=float)[order]
        self.tolerance = tolerance

    def __call__(self, t: float):
        """(pose or None, how: 'exact' | 'interpolated' | 'unmatched')."""
        i = int(np.searchsorted(self.t, t))
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(self.t) and abs(self.t[j] - t) <= self.tolerance:
                if best is None or abs(self.t[j] - t) < abs(self.t[best] - t):
                    best = j
        if best is not None:
            return self.p[best], "exact"
        if 0 < i < len(self.t):
            return interpolate_pose(t, self.t[i - 1], self.p[i - 1], self.t[i], self.p[i]), "interpolated"
        return None, "unmatched"


def relation_errors(times, poses, rel: Relations, tolerance=1e-4, exact: bool = False):
    """(errors (M, 3) of matched relations, counts dict); ``exact``: of those whose two stamps are
    trajectory stamps only (module docstring)."""
    look = PoseLookup(times, poses, tolerance)
    errs = []
    counts = {"relations": int(len(rel.t1)), "exact": 0, "interpolated": 0, "unmatched": 0}
    if exact:
        counts["not_exact"] = 0
    for t1, t2, d in zip(rel.t1, rel.t2, rel.delta):
        p1, h1 = look(t1)
        p2, h2 = look(t2)
        if p1 is None or p2 is None:
            counts["unmatched"] += 1
            continue
        how = "interpolated" if "interpolated" in (h1, h2) else "exact"
        if exact and how != "exact":
            counts["not_exact"] += 1
            continue
        counts[how] += 1
        errs.append(compose(between(p1, p2), inverse(d)))
    return np.array(errs).reshape(-1, 3), counts


def _stat(v):
    v = np.asarray(v, dtype=float)
    return {"mean": float(v.mean()) if v.size else float("nan"),
            "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "max": float(v.max()) if v.size else float("nan")}


def relations_metric(times, poses, rel: Relations, tolerance=1e-4, exact: bool = False) -> dict:
    errs, counts = relation_errors(times, poses, rel, tolerance, exact)
    trans = np.hypot(errs[:, 0], errs[:, 1])
    rot = np.degrees(np.abs(errs[:, 2]))
    return {
        "abs_trans_m": _stat(trans),
        "sq_trans_m2": _stat(trans ** 2),
        "abs_rot_deg": _stat(rot),
        "sq_rot_deg2": _stat(rot ** 2),
        "counts": {**counts, "evaluated": int(len(errs))},
    }
