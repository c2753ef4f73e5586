"""Reference trajectories for evaluation, expressed per scan of the run.

A reference is a TUM file (associated to the run's scans by timestamp), an MCAP with the
simulator's ``/ground_truth`` (one pose per scan), or a CARMEN "corrected" log such as
GMapping's ``*.gfs.log`` / ``*-corrected.log``. Those logs hold corrected poses for key
scans only and their timestamps are rounded to a few significant digits, so their scans are
associated to the run's input scans by identical range readings (in order; the SOURCE.md of
each shared dataset documents this). Scans between key scans can take the previous key
pose composed with the raw odometry increment (`Reference.dense`).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam2d.errors import InputError
from slam2d.geometry import between, compose
from slam2d.io._text import iter_lines
from slam2d.io.carmen import _parse_laser
from slam2d.io.source import open_source, source_kind
from slam2d.io.trajectory import NUDGE


@dataclass
class Reference:
    scan_indices: np.ndarray  # (K,) indices into the run's scans, increasing
    poses: np.ndarray         # (K, 3) reference poses of those scans
    kind: str
    total_reference_scans: int

    def dense(self, odom: np.ndarray | None) -> np.ndarray:
        """A reference pose for every scan: key poses, and between them the nearer key pose (before
        or after, by scan count) composed with the raw odometry increment to the scan; NaN where
        there is no key pose to start from or no odometry."""
        n = len(odom) if odom is not None else int(self.scan_indices.max()) + 1
        out = np.full((n, 3), np.nan)
        keys = self.scan_indices
        out[keys[keys < n]] = self.poses[keys < n]
        if odom is None or len(keys) == 0:
            return out
        pos = np.searchsorted(keys, np.arange(n))  # first key index >= scan
        for i in range(n):
            k = pos[i]
            if k < len(keys) and keys[k] == i:
                continue
            cands = [kk for kk in (k - 1, k) if 0 <= kk < len(keys)]
            kk = min(cands, key=lambda c: abs(keys[c] - i))
            out[i] = compose(self.poses[kk], between(odom[keys[kk]], odom[i]))
        return out


def run_input_of(traj_path: Path, given: str | None) -> str | None:
    """The log a run was made from: given, or the ``input`` in the run's summary.json."""
    if given:
        return given
    summary = Path(traj_path).parent / "summary.json"
    if summary.exists():
        try:
            data = json.loads(summary.read_text())
        except (json.JSONDecodeError, OSError):
            return None
        # the absolute path first: the one as given was relative to wherever the run was started, and
        # read from another folder it could name another log of the same name
        return data.get("input_absolute") or data.get("input")
    return None


def is_carmen(path) -> bool:
    try:
        return source_kind(path) == "carmen"
    except InputError:
        return False


def read_corrected_carmen(path):
    """[(ranges float32, pose (3,), line)] of the laser lines of a corrected log (timestamps ignored)."""
    out = []
    for lineno, line in iter_lines(path):
        parts = line.split()
        if not parts or parts[0] not in ("FLASER", "RLASER", "ROBOTLASER1"):
            continue
        p = _parse_laser(Path(path), lineno, parts)
        out.append((p.ranges.astype(np.float32), p.laser_pose.copy(), lineno))
    if not out:
        raise InputError(path, "no laser lines in the reference log")
    return out


def associate_by_ranges(run_scans, corrected) -> tuple[np.ndarray, np.ndarray, int]:
    """Match corrected key scans to run scans whose range readings are identical, in order."""
    table: dict[bytes, list[int]] = {}
    offsets = []
    for s in run_scans:
        table.setdefault(s.ranges.astype(np.float32).tobytes(), []).append(s.index)
        offsets.append(s.laser_offset)
    idx, poses = [], []
    last = -1
    for ranges, laser_pose, _ in corrected:
        cands = [i for i in table.get(ranges.tobytes(), []) if i > last]
        if not cands:
            continue
        i = cands[0]
        last = i
        idx.append(i)
        # the corrected pose is the laser's; the run's trajectory is the robot's
        poses.append(compose(laser_pose, between(offsets[i], np.zeros(3))))
    return np.array(idx, dtype=int), np.array(poses).reshape(-1, 3), len(corrected)


def load_reference(ref_path, run_stamps: np.ndarray, run_input: str | None, tolerance=1e-3) -> Reference:
    """The reference for the scans of a run (poses of scans the run did not reach are left out)."""
    ref = _load_reference(ref_path, run_stamps, run_input, tolerance)
    keep = ref.scan_indices < len(run_stamps)
    if not keep.any():
        raise InputError(ref_path, "no reference pose falls on a scan of the trajectory")
    return Reference(ref.scan_indices[keep], ref.poses[keep], ref.kind, ref.total_reference_scans)


def recording_stamps(scans, stamps: list):
    """``scans`` passed on, each one's timestamp appended to ``stamps`` (for ``check_scan_order`` after a
    pass that needs the scans anyway)."""
    for s in scans:
        stamps.append(s.timestamp)
        yield s


def check_scan_order(run_stamps: np.ndarray, input_stamps: np.ndarray, run_input, tolerance: float = 1e-3) -> None:
    """The reference is matched to the input's scans by position, so the trajectory's poses must be
    those scans in order: a trajectory re-sorted by stamp, or of another run, would be scored against
    the wrong poses. trajectory.txt may move a repeated stamp later by 1 µs a line (`slam2d.io.trajectory`)."""
    n = min(len(run_stamps), len(input_stamps))
    if n > 1 and run_stamps[1] > run_stamps[0] and np.all(
            np.abs(run_stamps - (run_stamps[1] - run_stamps[0]) * np.arange(len(run_stamps))) < 1e-6):
        return  # a run made with --scan-period: its stamps are k × period, in file order by construction
    d = run_stamps[:n] - input_stamps[:n]
    bad = np.flatnonzero((d < -tolerance) | (d > tolerance + float(NUDGE) * n))
    if bad.size:
        i = int(bad[0])
        raise InputError(run_input, f"scan {i} is stamped {input_stamps[i]:.6f} but the trajectory's pose {i} "
                         f"{run_stamps[i]:.6f}: the trajectory does not list this log's scans in order (re-sorted, "
                         "or another run's?)")


def _load_reference(ref_path, run_stamps, run_input, tolerance) -> Reference:
    ref_path = Path(ref_path)
    if not ref_path.exists():
        raise InputError(ref_path, "no such file")
    name = ref_path.name.lower()
    if name.endswith(".mcap"):
        src = open_source(ref_path)
        idx, poses = [], []
        for s in src:
            if s.ground_truth is not None:
                idx.append(s.index)
                poses.append(s.ground_truth)
        if not idx:
            raise InputError(ref_path, "no ground-truth poses (/ground_truth) in the MCAP file")
        return Reference(np.array(idx), np.array(poses), "ground_truth", len(idx))
    if is_carmen(ref_path) or name.endswith(".gfs.log"):
        if run_input is None:
            raise InputError(ref_path, "a corrected CARMEN reference is matched to the run's input scans: "
                             "give --run-input LOG (or keep summary.json beside the trajectory)")
        if not Path(run_input).exists():
            raise InputError(run_input, "no such file: the log the run read (the input in summary.json beside the "
                             "trajectory, a path from where the run was made; or --run-input): give --run-input LOG")
        corrected = read_corrected_carmen(ref_path)
        stamps = []
        idx, poses, total = associate_by_ranges(recording_stamps(open_source(run_input), stamps), corrected)
        if len(idx) == 0:
            raise InputError(ref_path, f"none of its scans has the same range readings as a scan of {run_input}")
        check_scan_order(run_stamps, np.array(stamps), run_input, tolerance)
        return Reference(idx, poses, "corrected_carmen", total)
    from slam2d.io.trajectory import read_tum

    t, poses, _ = read_tum(ref_path)
    order = np.argsort(run_stamps, kind="stable")
    st = run_stamps[order]
    pos = np.clip(np.searchsorted(st, t), 1, len(st) - 1)
    near = np.where(np.abs(st[pos - 1] - t) <= np.abs(st[pos] - t), pos - 1, pos)
    ok = np.abs(st[near] - t) <= tolerance
    if not ok.any():
        raise InputError(ref_path, f"no reference timestamp within {tolerance} s of a trajectory timestamp")
    idx = order[near[ok]]
    keep = np.argsort(idx, kind="stable")
    return Reference(idx[keep], poses[ok][keep], "tum", len(t))


@dataclass
class GroundTruth:
    """One ground-truth pose per scan of a run (NaN where the ground truth has none)."""

    poses: np.ndarray         # (N, 3), N = the run's scans
    scan_indices: np.ndarray  # (K,) scans that have a pose, increasing
    matching: str             # "scan_order" | "timestamp" | "mcap_scan_index"
    total_ground_truth_poses: int


def load_ground_truth(path, run_stamps: np.ndarray, tolerance: float = 1e-3) -> GroundTruth:
    """A ground truth independent of the run: a TUM file with one pose per scan, matched to the
    run's scans in scan order when the counts are equal, else by nearest timestamp (within
    ``tolerance`` s); or an MCAP with the simulator's ``/ground_truth`` (one pose per scan)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    n = len(run_stamps)
    dense = np.full((n, 3), np.nan)
    if path.name.lower().endswith(".mcap"):
        ref = _load_reference(path, run_stamps, None, tolerance)
        idx = ref.scan_indices[ref.scan_indices < n]
        if len(idx) == 0:
            raise InputError(path, f"no ground-truth pose falls on one of the run's {n} scans")
        dense[idx] = ref.poses[ref.scan_indices < n]
        return GroundTruth(dense, idx, "mcap_scan_index", ref.total_reference_scans)
    from slam2d.io.trajectory import read_tum

    t, poses, _ = read_tum(path)
    if len(t) == n:
        # by position: a ground truth on another clock (make_sparse.py's) can only be matched so. On the
        # run's own clock, its stamps must then be the run's in the same order, or the file was re-sorted
        same_clock = np.abs(np.sort(t) - np.sort(run_stamps)) <= tolerance + float(NUDGE) * n
        in_order = np.all(np.abs(t - run_stamps) <= tolerance + float(NUDGE) * n)
        if not same_clock.all() or in_order:
            return GroundTruth(poses.copy(), np.arange(n), "scan_order", len(t))
        # on the run's clock but in another order (sorted by time, or reversed): matched by stamp below
    order = np.argsort(run_stamps, kind="stable")
    st = run_stamps[order]
    if n == 1:
        near = np.zeros(len(t), int)
    else:
        pos = np.clip(np.searchsorted(st, t), 1, n - 1)
        near = np.where(np.abs(st[pos - 1] - t) <= np.abs(st[pos] - t), pos - 1, pos)
    ok = np.abs(st[near] - t) <= tolerance
    if not ok.any():
        raise InputError(path, f"{len(t)} poses for the run's {n} scans, and no timestamp within {tolerance} s "
                         "of a scan's timestamp (trajectory.txt)")
    idx = order[near[ok]]
    dense[idx] = poses[ok]
    return GroundTruth(dense, np.unique(idx), "timestamp", len(t))
