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
corridor that looks the same along its length, or too little overlap).

Two hypotheses a few degrees apart can both put most of j's hits within the tolerance (at 3 m, 2°
moves a point by 10 cm), so the shares tie where the ground truth and the constraint differ by
little more than the loop evaluation's tolerance. There the scans are registered themselves
(``register``: point-to-line ICP, Censi 2008's metric, from each hypothesis's placement, the
correspondence distance halved down to a few times the tolerance): when both starts reach the same relative
pose, that pose is the scans' own answer, and the verdict names the hypothesis within the loop
evaluation's tolerance (``agree``, by default ``AGREE``: 0.3 m / 2°) of it while the other is not, and
``both`` when each is: the two differ by more than the tolerance but by less than the scans
resolve, so the scans call neither false. The place is built by each hypothesis's placement of
i's neighbours, and the verdict must be the same on both places. Starts that end apart (a
corridor, a symmetric room) or too little overlap leave it undecided. Nothing here
uses the run's loop search or scores: hits come from the log read again with the run's range filter.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from slam2d.eval.loops import Thresholds
from slam2d.geometry import between, transform_points

#: scans on each side of scan i whose hits make up the place j is laid onto
NEIGHBOURS = 2
#: a verdict needs this many times the other hypothesis's share ...
RATIO = 2.0
#: ... and at least this share of j's hits on the place
MIN_SHARE = 0.3

#: registration: correspondences at first up to this far [m], the distance then halved down ...
REGISTRATION_REACH = 1.0
#: ... to this many times the tolerance: a point of one scan lies up to a beam's spacing from the nearest point of
#: another on the same wall (1° at 10 m is 17 cm), while its distance to the wall's line is within the tolerance
FINEST_GATE = 2.5
#: Gauss-Newton steps at each distance, at most
REGISTRATION_ITERATIONS = 30
#: a placement agrees with the scans' own pose within the loop evaluation's tolerance [m, degrees]
AGREE = (Thresholds.ref_trans, Thresholds.ref_rot_deg)
#: the two starts reach "the same" pose when they end this close [m, rad]
SAME_POSE = (0.05, np.radians(0.25))


def overlap_share(hits: dict[int, np.ndarray], poses: np.ndarray, i: int, j: int, rel_ij: np.ndarray,
                  tolerance: float, neighbours: int = NEIGHBOURS) -> float | None:
    """Share of scan j's hits within ``tolerance`` of the hits of scans i − n … i + n (j excluded), in
    scan i's frame: j at ``rel_ij``, each neighbour m at ``between(poses[i], poses[m])``. None when
    j or the place has no hits, or a pose is unknown."""
    src = hits.get(j)
    if src is None or len(src) == 0 or not np.all(np.isfinite(rel_ij)):
        return None
    place = _place(hits, poses, i, j, neighbours)
    if place is None:
        return None
    dist, _ = cKDTree(place).query(transform_points(np.asarray(rel_ij, dtype=float), src),
                                   distance_upper_bound=tolerance)
    return float(np.isfinite(dist).mean())


def _place(hits, poses, i, j, neighbours) -> np.ndarray | None:
    """The hits of scans i − n … i + n (j excluded) in scan i's frame, placed by ``poses``."""
    place = []
    for m in range(i - neighbours, i + neighbours + 1):
        h = hits.get(m)
        if m == j or h is None or len(h) == 0 or not (0 <= m < len(poses)):
            continue
        if not (np.all(np.isfinite(poses[i])) and np.all(np.isfinite(poses[m]))):
            continue
        place.append(transform_points(between(poses[i], poses[m]), h))
    return np.concatenate(place) if place else None


def register(src: np.ndarray, place: np.ndarray, start, tolerance: float, reach: float = REGISTRATION_REACH,
             iterations: int = REGISTRATION_ITERATIONS) -> np.ndarray | None:
    """The pose of ``src`` (N, 2, its own frame) that lays it onto ``place`` (M, 2), found by point-to-line
    ICP from ``start``: each point's nearest place point within the current distance, the line
    through it along its 6 nearest place points, and a Gauss-Newton step on the distances to those
    lines; the distance starts at ``reach`` and is halved down to ``FINEST_GATE`` × ``tolerance``.
    None when fewer than ``MIN_SHARE`` of the points end within ``tolerance`` of a line."""
    src = np.asarray(src, dtype=float).reshape(-1, 2)
    place = np.asarray(place, dtype=float).reshape(-1, 2)
    if len(src) < 3 or len(place) < 6:
        return None
    tree = cKDTree(place)
    _, nb = tree.query(place, k=6)
    d = place[nb] - place[nb].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", d, d)
    normals = np.linalg.eigh(cov)[1][:, :, 0]  # the direction of least spread: across the line
    pose = np.asarray(start, dtype=float).copy()
    finest = FINEST_GATE * tolerance
    dist = max(reach, finest)
    while True:
        for _ in range(iterations):
            p = transform_points(pose, src)
            gap, at = tree.query(p, distance_upper_bound=dist)
            ok = np.isfinite(gap)
            if ok.sum() < 3:
                return None
            q, n, pp = place[at[ok]], normals[at[ok]], p[ok]
            r = np.einsum("ij,ij->i", n, pp - q)
            jac = np.c_[n, n[:, 1] * pp[:, 0] - n[:, 0] * pp[:, 1]]  # d r / d(x, y, θ) of a map-frame step
            try:
                step = np.linalg.solve(jac.T @ jac + 1e-9 * np.eye(3), -jac.T @ r)
            except np.linalg.LinAlgError:
                return None
            c, s_ = np.cos(step[2]), np.sin(step[2])
            pose = np.array([c * pose[0] - s_ * pose[1] + step[0], s_ * pose[0] + c * pose[1] + step[1],
                             pose[2] + step[2]])
            if np.hypot(step[0], step[1]) < 1e-4 and abs(step[2]) < 1e-5:
                break
        if dist <= finest:
            break
        dist = max(dist / 2.0, finest)
    p = transform_points(pose, src)
    gap, at = tree.query(p, distance_upper_bound=finest)
    ok = np.isfinite(gap)
    on_line = np.abs(np.einsum("ij,ij->i", normals[at[ok]], p[ok] - place[at[ok]])) <= tolerance
    if on_line.sum() < MIN_SHARE * len(src):
        return None
    return pose


def registered_verdict(hits, run_poses, gt_poses, i: int, j: int, rel_constraint, tolerance: float,
                       agree: tuple[float, float]) -> tuple[str, np.ndarray | None]:
    """(``constraint``, ``ground_truth``, ``both`` or ``undecided``; the scans' own relative pose i → j or None)
    by registration (module docstring); ``agree``: (m, degrees) within which a hypothesis matches it. The place is built twice, by each
    hypothesis's placement of i's neighbours; on each, both starts must reach the same pose, and
    both places must give the same verdict (the pose returned is the one on the run's place)."""
    src = hits.get(j)
    rel_gt = between(gt_poses[i], gt_poses[j])
    rel_constraint = np.asarray(rel_constraint, dtype=float)
    if src is None or not (np.all(np.isfinite(rel_constraint)) and np.all(np.isfinite(rel_gt))):
        return "undecided", None

    def near(scans, rel):
        e = between(scans, rel)
        return np.hypot(e[0], e[1]) <= agree[0] and abs(np.degrees(e[2])) <= agree[1]

    said, first = set(), None
    for poses in (run_poses, gt_poses):
        place = _place(hits, poses, i, j, NEIGHBOURS)
        ends = [None if place is None else register(src, place, rel, tolerance) for rel in (rel_constraint, rel_gt)]
        if any(e is None for e in ends):
            return "undecided", None
        gap = between(ends[0], ends[1])
        if np.hypot(gap[0], gap[1]) > SAME_POSE[0] or abs(gap[2]) > SAME_POSE[1]:
            return "undecided", None  # where the registration ends depends on where it starts
        c_ok, g_ok = near(ends[0], rel_constraint), near(ends[0], rel_gt)
        said.add("both" if c_ok and g_ok else "constraint" if c_ok else "ground_truth" if g_ok else "undecided")
        first = ends[0] if first is None else first
    return (said.pop() if len(said) == 1 else "undecided"), first


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
                        gt_poses: np.ndarray, tolerance: float, agree: tuple[float, float] = AGREE) -> dict:
    """For every constraint of the final graph that the ground truth calls false (``true_gt`` is
    False, set by ``classify_ground_truth``): both shares and the verdict, stored in
    ``c["scan_check"]``; where the shares leave it undecided, the registration's verdict
    (``registered_verdict``, with ``agree`` the loop evaluation's tolerance: m, degrees), marked
    ``"by": "registration"`` with the registered pose. Returns the count of each verdict."""
    counts = {"constraint": 0, "ground_truth": 0, "both": 0, "undecided": 0}
    for c in constraints:
        if not (c["accepted"] and c.get("in_final_graph", True)) or c.get("true_gt") is not False:
            continue
        i, j = c["from_scan"], c["to_scan"]
        own = overlap_share(hits, run_poses, i, j, np.asarray(c["relative_pose"], dtype=float), tolerance)
        gt = overlap_share(hits, gt_poses, i, j, between(gt_poses[i], gt_poses[j]), tolerance)
        v = verdict(own, gt)
        c["scan_check"] = {"share_constraint": None if own is None else round(own, 3),
                           "share_ground_truth": None if gt is None else round(gt, 3), "verdict": v}
        if v == "undecided" and own is not None and gt is not None:
            v, scans = registered_verdict(hits, run_poses, gt_poses, i, j, np.asarray(c["relative_pose"], dtype=float),
                                          tolerance, agree)
            if scans is not None:
                c["scan_check"].update({"verdict": v, "by": "registration",
                                        "registered": [round(float(x), 4) for x in scans]})
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
              run_input: str | None = None, agree: tuple[float, float] = AGREE) -> dict | None:
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
    return check_disagreements(constraints, hits, run_poses, gt_poses, 2.0 * cfg.grid.resolution, agree)


__all__ = ["check_disagreements", "check_run", "overlap_share", "register", "registered_verdict", "scan_hits",
           "scans_to_read", "verdict"]
