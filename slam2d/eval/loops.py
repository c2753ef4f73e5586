"""Loop-closure precision and recall.

Each loop-closure constraint of a run (``constraints.jsonl``: one JSON object per line with
``from_scan``, ``to_scan``, ``relative_pose`` [x, y, θ] of the ``to`` scan in the ``from``
scan's frame, ``score``, ``accepted``, optionally ``in_final_graph``) is classified twice:

(a) against the run's own final poses: true when they agree within 0.2 m and 1° — the
    criterion of Hess et al. 2016, Table IV;
(b) against a reference trajectory: true within 0.3 m and 2° (the reference has its own
    few-centimetre error).

(c) against a ground truth independent of the run (``--ground-truth``: the simulator's, or the
    ``.gt.txt`` of ``make_sparse.py``): true within a tolerance, by default 0.3 m and 2°. A ground
    truth that is another SLAM solution has errors of its own, so each constraint of the final graph
    it calls false is also put to the raw scans (``scan_check.py``: do the two passes line up as the
    constraint places them, or as the ground truth does?), counted in ``false_by_scans``.

Recall counts revisit episodes of the reference (or ground truth) — runs of reference scans that come back
within ``revisit_distance`` of a place passed more than ``min_loop_travel`` metres of path
earlier — that at least one true accepted constraint touches.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from slam2d.errors import InputError
from slam2d.geometry import between
from slam2d.io.trajectory import NUDGE


@dataclass
class Thresholds:
    own_trans: float = 0.2
    own_rot_deg: float = 1.0
    ref_trans: float = 0.3
    ref_rot_deg: float = 2.0
    revisit_distance: float = 1.0
    min_loop_travel: float = 10.0


def read_constraints(path) -> list[dict]:
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file (global SLAM writes constraints.jsonl)")
    out = []
    with open(path) as f:
        for n, line in enumerate(f, start=1):
            if not line.strip():
                continue
            try:
                c = json.loads(line)
                c["from_scan"], c["to_scan"] = int(c["from_scan"]), int(c["to_scan"])
                rel = c.get("relative_pose")
                c["relative_pose"] = None if rel is None else [float(v) for v in rel]
                c["score"] = math.nan if c.get("score") is None else float(c["score"])
                c["accepted"] = bool(c["accepted"])
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
                raise InputError(path, f"not a constraint record ({type(e).__name__}: {e})", line=n) from None
            if c["relative_pose"] is None and c["accepted"]:
                raise InputError(path, "an accepted constraint needs a relative_pose", line=n)
            if c["relative_pose"] is not None and len(c["relative_pose"]) != 3:
                raise InputError(path, "relative_pose needs 3 values", line=n)
            c["line"] = n
            out.append(c)
    return out


def check_stamps(constraints: list[dict], run_stamps: np.ndarray, path, tolerance: float = 1e-3) -> None:
    """A constraint's ``from_stamp``/``to_stamp`` (when written) must be the run's stamps of its
    scans (``run_stamps`` in scan order, as `read_tum` gives them): otherwise constraints.jsonl
    and trajectory.txt are not from the same run. trajectory.txt may have moved a repeated stamp
    later by 1 µs per line (`slam2d.io.trajectory`), never earlier."""
    nudge = float(NUDGE) * len(run_stamps)
    for c in constraints:
        for end in ("from", "to"):
            stamp, i = c.get(f"{end}_stamp"), c[f"{end}_scan"]
            if not 0 <= i < len(run_stamps):  # stamped or not: every later step indexes the poses with it
                raise InputError(path, f"{end}_scan {i} is not a scan of trajectory.txt ({len(run_stamps)} scans)",
                                 line=c["line"])
            if stamp is None:
                continue
            try:
                d = run_stamps[i] - float(stamp)
            except (TypeError, ValueError):
                raise InputError(path, f"{end}_stamp is not a number: {stamp!r}", line=c["line"]) from None
            if not -tolerance <= d <= tolerance + nudge:
                raise InputError(path, f"{end}_stamp {stamp} is not trajectory.txt's stamp {run_stamps[i]:.6f} "
                                 f"of scan {i} (files from different runs?)", line=c["line"])


def agrees(poses: np.ndarray, c: dict, trans: float, rot_deg: float):
    """True/False, or None when a pose is unknown."""
    i, j = c["from_scan"], c["to_scan"]
    if c["relative_pose"] is None:
        return None
    if i >= len(poses) or j >= len(poses) or np.isnan(poses[i, 0]) or np.isnan(poses[j, 0]):
        return None
    e = between(between(poses[i], poses[j]), np.asarray(c["relative_pose"]))
    return bool(math.hypot(e[0], e[1]) <= trans and abs(math.degrees(e[2])) <= rot_deg)


def disagreement(c: dict, poses: np.ndarray) -> dict:
    """A constraint that ``poses`` call false, for a user to look up: its submap and scans, how far
    its measurement lies from the relative pose of ``poses`` (translation [m], rotation [deg]), its
    score and margin, and the raw scans' verdict where ``scan_check`` gave one."""
    i, j = c["from_scan"], c["to_scan"]
    e = between(between(poses[i], poses[j]), np.asarray(c["relative_pose"], dtype=float))
    out = {"submap": c.get("submap"), "from_scan": int(i), "to_scan": int(j),
           "off_m": round(math.hypot(e[0], e[1]), 3), "off_deg": round(abs(math.degrees(e[2])), 2),
           "score": c.get("score"), "margin": c.get("margin")}
    if "scan_check" in c:
        out["scan_check"] = c["scan_check"]
    return out


def disagreeing(constraints: list[dict], poses: np.ndarray) -> list[dict]:
    """``disagreement`` of every accepted constraint of the final graph that ``classify_ground_truth``
    called false, in constraint order (with the raw scans' verdict once ``scan_check`` has run)."""
    return [disagreement(c, poses) for c in constraints
            if c["accepted"] and c.get("in_final_graph", True) and c.get("true_gt") is False]


def revisit_episodes(ref_idx: np.ndarray, ref_poses: np.ndarray, th: Thresholds) -> list[tuple[int, int]]:
    """(first scan, last scan) of each run of reference scans that revisit an earlier place."""
    if len(ref_idx) < 2:
        return []
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref_poses[:, :2], axis=0).T))])
    tree = cKDTree(ref_poses[:, :2])
    revisit = np.zeros(len(ref_idx), bool)
    for k, near in enumerate(tree.query_ball_point(ref_poses[:, :2], th.revisit_distance)):
        revisit[k] = any(travelled[k] - travelled[m] > th.min_loop_travel for m in near)
    episodes, start = [], None
    for k in range(len(ref_idx)):
        if revisit[k] and start is None:
            start = k
        if start is not None and (not revisit[k] or k == len(ref_idx) - 1):
            end = k if revisit[k] else k - 1
            episodes.append((int(ref_idx[start]), int(ref_idx[end])))
            start = None
    return episodes


def _precision(cs, key) -> dict:
    known = [c[key] for c in cs if c[key] is not None]
    return {"true": int(sum(known)), "false": int(len(known) - sum(known)), "unknown": len(cs) - len(known),
            "precision": (sum(known) / len(known)) if known else None}


def _recall(final: list[dict], key: str, episodes: list[tuple[int, int]]) -> dict:
    """Episodes touched (at either end) by at least one true constraint of the final graph."""
    hit = sum(1 for a, b in episodes
              if any(c[key] and (a <= c["to_scan"] <= b or a <= c["from_scan"] <= b) for c in final))
    return {"episodes": len(episodes), "closed": hit, "recall": hit / len(episodes) if episodes else None}


def classify_ground_truth(constraints: list[dict], gt_poses: np.ndarray, gt_scans: np.ndarray,
                          trans: float = 0.3, rot_deg: float = 2.0, th: Thresholds = Thresholds()) -> dict:
    """Precision and recall of loop constraints against a ground truth (one pose per scan, NaN where
    unknown; ``gt_scans`` the scans that have one). Sets ``c["true_gt"]`` on every constraint.

    Precision is over the accepted constraints that are in the final graph (the headline) and over
    all accepted ones; recall is over the ground truth's revisit episodes."""
    for c in constraints:
        c["true_gt"] = agrees(gt_poses, c, trans, rot_deg)
    accepted = [c for c in constraints if c["accepted"]]
    final = [c for c in accepted if c.get("in_final_graph", True)]
    return {"tolerance": {"trans_m": trans, "rot_deg": rot_deg},
            "disagreeing": disagreeing(constraints, gt_poses),
            "final_graph": _precision(final, "true_gt"), "accepted": _precision(accepted, "true_gt"),
            "recall": _recall(final, "true_gt", revisit_episodes(gt_scans, gt_poses[gt_scans], th))}


def classify(constraints: list[dict], own_poses: np.ndarray, ref_dense: np.ndarray | None,
             ref_key: tuple[np.ndarray, np.ndarray] | None, th: Thresholds = Thresholds()) -> dict:
    for c in constraints:
        c["true_own"] = agrees(own_poses, c, th.own_trans, th.own_rot_deg)
        c["true_ref"] = agrees(ref_dense, c, th.ref_trans, th.ref_rot_deg) if ref_dense is not None else None
    accepted = [c for c in constraints if c["accepted"]]
    final = [c for c in accepted if c.get("in_final_graph", True)]

    out = {
        "constraints": len(constraints),
        "accepted": len(accepted),
        "in_final_graph": len(final),
        "own": {"accepted": _precision(accepted, "true_own"), "final_graph": _precision(final, "true_own")},
    }
    if ref_dense is not None:
        out["reference"] = {"accepted": _precision(accepted, "true_ref"), "final_graph": _precision(final, "true_ref"),
                            "rejected": _precision([c for c in constraints if not c["accepted"]], "true_ref")}
        if ref_key is not None:
            out["reference"]["recall"] = _recall(final, "true_ref", revisit_episodes(ref_key[0], ref_key[1], th))
    key = "true_ref" if ref_dense is not None else "true_own"
    out["score_histogram"] = score_histogram(constraints, key)
    return out


def score_histogram(constraints: list[dict], key: str) -> dict:
    """Scores of the constraints judged true / false by ``key``, in 20 bins over [0, 1]."""
    bins = np.linspace(0.0, 1.0, 21)
    hist = {"bins": bins.tolist(), "true": [0] * 20, "false": [0] * 20}
    for c in constraints:
        if c[key] is None or not np.isfinite(c["score"]):
            continue
        b = int(np.clip(np.searchsorted(bins, c["score"], side="right") - 1, 0, 19))
        hist["true" if c[key] else "false"][b] += 1
    return hist
