"""Where a loop constraint and the ground truth disagree, the raw scans decide which one is wrong.

A ground truth that is itself a SLAM solution (the ``.gt.txt`` of ``make_sparse.py`` is GMapping's
corrected log) has errors of its own, and a loop constraint can only be as "false" as the
ground truth is right. So, for a constraint the ground truth calls false, the scans are asked:
scan j's hits are laid onto the hits of scan i and of the scans recorded just before and after it
(``NEIGHBOURS`` on each side), once as the constraint places them and once as the ground truth
does (each hypothesis places i's neighbours by its own trajectory: the run's final poses, the
ground truth's poses). The share of j's hits that land within ``2 × resolution`` of one of theirs
is how well the two passes over the place agree under each hypothesis (the point-overlap
test of scan registration, e.g. the inlier share of ICP; Besl and McKay 1992).

The verdict is ``constraint`` when the constraint's share is at least ``RATIO`` times the ground
truth's and at least ``MIN_SHARE`` (the scans line up as the constraint says, and do not as the
ground truth says), ``ground_truth`` the other way round, and ``undecided`` otherwise (a
corridor that looks the same along its length, or too little overlap). Nothing here uses the
run's loop search or scores: hits come from the log read again with the run's range filter.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from slam2d.geometry import between, transform_points

#: scans on each side of scan i whose hits make up the place j is laid onto
NEIGHBOURS = 2
#: a verdict needs this many times the other hypothesis's share ...
RATIO = 2.0
#: ... and at least this share of j's hits on the place
MIN_SHARE = 0.3


def overlap_share(hits: dict[int, np.ndarray], poses: np.ndarray, i: int, j: int, rel_ij: np.ndarray,
                  tolerance: float, neighbours: int = NEIGHBOURS) -> float | None:
    """Share of scan j's hits within ``tolerance`` of the hits of scans i − n … i + n (j excluded), in
    scan i's frame: j at ``rel_ij``, each neighbour m at ``between(poses[i], poses[m])``. None when
    j or the place has no hits, or a pose is unknown."""
    src = hits.get(j)
    if src is None or len(src) == 0 or not np.all(np.isfinite(rel_ij)):
        return None
    place = []
    for m in range(i - neighbours, i + neighbours + 1):
        h = hits.get(m)
        if m == j or h is None or len(h) == 0 or not (0 <= m < len(poses)):
            continue
        if not (np.all(np.isfinite(poses[i])) and np.all(np.isfinite(poses[m]))):
            continue
        place.append(transform_points(between(poses[i], poses[m]), h))
    if not place:
        return None
    dist, _ = cKDTree(np.concatenate(place)).query(transform_points(np.asarray(rel_ij, dtype=float), src),
                                                   distance_upper_bound=tolerance)
    return float(np.isfinite(dist).mean())


def verdict(share_constraint: float | None, share_ground_truth: float | None) -> str:
    """``constraint``, ``ground_truth`` or ``undecided`` (module docstring)."""
    if share_constraint is None or share_ground_truth is None:
        return "undecided"
    if share_constraint >= MIN_SHARE and share_constraint >= RATIO * share_ground_truth:
        return "constraint"
    if share_ground_truth >= MIN_SHARE and share_ground_truth >= RATIO * share_constraint:
        return "ground_truth"
    return "undecided"


def check_disagreements(constraints: list[dict], hits: dict[int, np.ndarray], run_poses: np.ndarray,
                        gt_poses: np.ndarray, tolerance: float) -> dict:
    """For every constraint of the final graph that the ground truth calls false (``true_gt`` is
    False, set by ``classify_ground_truth``): both shares and the verdict, stored in
    ``c["scan_check"]``; returns the count of each verdict."""
    counts = {"constraint": 0, "ground_truth": 0, "undecided": 0}
    for c in constraints:
        if not (c["accepted"] and c.get("in_final_graph", True)) or c.get("true_gt") is not False:
            continue
        i, j = c["from_scan"], c["to_scan"]
        own = overlap_share(hits, run_poses, i, j, np.asarray(c["relative_pose"], dtype=float), tolerance)
        gt = overlap_share(hits, gt_poses, i, j, between(gt_poses[i], gt_poses[j]), tolerance)
        v = verdict(own, gt)
        c["scan_check"] = {"share_constraint": None if own is None else round(own, 3),
                           "share_ground_truth": None if gt is None else round(gt, 3), "verdict": v}
        counts[v] += 1
    return counts


def scan_hits(source, cfg, wanted: set[int]) -> dict[int, np.ndarray]:
    """Hits (tracking frame, the run's range filter) of the scans in ``wanted``, read from ``source``."""
    from slam2d.range_data import range_data

    out = {}
    last = max(wanted, default=-1)
    for k, scan in enumerate(source):
        if k > last:
            break
        if k in wanted:
            out[k] = np.asarray(range_data(scan, cfg.range_filter).hits, dtype=float)
    return out


def scans_to_read(constraints: list[dict], neighbours: int = NEIGHBOURS) -> set[int]:
    """The scans ``check_disagreements`` needs: both ends of each disagreeing constraint and the
    neighbours of its ``from`` scan."""
    out = set()
    for c in constraints:
        if c["accepted"] and c.get("in_final_graph", True) and c.get("true_gt") is False:
            out.add(c["to_scan"])
            out.update(range(max(c["from_scan"] - neighbours, 0), c["from_scan"] + neighbours + 1))
    return out


def check_run(run_dir, constraints: list[dict], run_poses: np.ndarray, gt_poses: np.ndarray,
              run_input: str | None = None) -> dict | None:
    """``check_disagreements`` for a run folder: its log (``run_input``, default summary.json's
    ``input``) read again with its ``config.yaml``'s range filter, at 2 cells of its grid. None when
    the log or the config cannot be found (the check is then left out)."""
    from pathlib import Path

    from slam2d.config import load_config
    from slam2d.eval.reference import run_input_of
    from slam2d.io.source import open_source

    run_dir = Path(run_dir)
    log = run_input_of(run_dir / "trajectory.txt", run_input)
    if log is None or not Path(log).exists() or not (run_dir / "config.yaml").exists():
        return None
    cfg = load_config(run_dir / "config.yaml")
    hits = scan_hits(open_source(log), cfg, scans_to_read(constraints))
    return check_disagreements(constraints, hits, run_poses, gt_poses, 2.0 * cfg.grid.resolution)


__all__ = ["check_disagreements", "check_run", "overlap_share", "scan_hits", "scans_to_read", "verdict"]
