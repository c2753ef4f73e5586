"""The pipeline: scans → local SLAM (or odometry) → trajectory, nodes, map.

Later stages (global SLAM) hang off the same loop; observers hear about every step.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from slam2d.config import SlamConfig
from slam2d.errors import InputError
from slam2d.grid.probability_grid import ProbabilityGrid
from slam2d.motion_filter import MotionFilter
from slam2d.observer import Observer
from slam2d.range_data import RangeData, range_data

log = logging.getLogger(__name__)


@dataclass
class MatchingResult:
    """What local SLAM (or odometry) made of one scan."""

    time: float
    local_pose: np.ndarray
    range_data: RangeData  # tracking frame
    inserted: bool
    score: float | None = None
    timings: dict = field(default_factory=dict)
    active_submap: object = None          # the submap this scan was matched against (local SLAM)
    finished_submaps: list = field(default_factory=list)  # submaps this insertion finished
    inserted_into: list = field(default_factory=list)     # (submap index, submap local pose) it went into
    match: object = None                  # the correlative match of an inserted scan
    points: np.ndarray | None = None      # the filtered points that were matched (tracking frame)
    quality: str = "unmatched"            # trusted | forced (inserted after several untrusted) | untrusted | unmatched

    @property
    def covariance(self) -> np.ndarray | None:
        """Covariance of the local match (Olson 2009, Sec. IV), computed on demand: only global SLAM uses it."""
        return None if self.match is None else self.match.covariance


class OdometryTracker:
    """``--odometry-only``: the local pose is the wheel odometry pose; the motion filter picks nodes."""

    name = "odometry"

    def __init__(self, cfg: SlamConfig, source_path="input"):
        self.cfg = cfg
        self.source_path = source_path
        self.filter = MotionFilter(cfg.motion_filter)

    def add_scan(self, scan) -> MatchingResult:
        if scan.odom_pose is None:
            raise InputError(self.source_path, "scan has no odometry; run without --odometry-only", record=scan.index)
        rd = range_data(scan, self.cfg.range_filter)
        pose = np.asarray(scan.odom_pose, dtype=float)
        inserted = not self.filter.is_similar(scan.timestamp, pose)
        return MatchingResult(scan.timestamp, pose, rd, inserted)


@dataclass
class Node:
    """A scan kept by the motion filter: its local pose and range data (tracking frame, float32)."""

    scan_index: int
    time: float
    local_pose: np.ndarray
    hits: np.ndarray
    misses: np.ndarray
    origin: np.ndarray


@dataclass
class RunResult:
    stamps: list[str]
    times: np.ndarray
    poses: np.ndarray  # (N, 3) final pose of every scan
    nodes: list[Node]
    counts: dict
    timings: dict
    ground_truth_ate: dict | None = None  # when the source carries ground truth (the simulator)
    map: ProbabilityGrid | None = None    # built from the final node poses when the run built it already


class Mapper:
    def __init__(self, cfg: SlamConfig, tracker, observer: Observer | None = None, global_slam=None):
        self.cfg = cfg
        self.tracker = tracker
        self.observer = observer or Observer()
        self.global_slam = global_slam
        if global_slam is not None:
            global_slam.observer = self.observer

    def run(self, source, progress=None, info: dict | None = None) -> RunResult:
        stamps, times, poses, nodes = [], [], [], []
        ground_truth = []
        counts = {"scans": 0, "nodes": 0, "invalid_readings": 0, "no_return_readings": 0, "readings": 0,
                  "timestamp_reversals": 0, "beams_min": None, "beams_max": None}
        stage_ms: dict[str, list[float]] = {}
        last_t = None
        final = self.cfg.final_refinement
        keep_points = self.global_slam is not None and final.enabled
        scan_points: list[np.ndarray | None] = []
        self.observer.on_start(info or {})
        for scan in source:
            t0 = time.perf_counter()
            res = self.tracker.add_scan(scan)
            dt_ms = (time.perf_counter() - t0) * 1e3
            stage_ms.setdefault("frontend", []).append(dt_ms)
            for k, v in res.timings.items():
                stage_ms.setdefault(k, []).append(v)
            n = scan.num_beams
            counts["scans"] += 1
            counts["readings"] += n
            counts["invalid_readings"] += int(n - np.count_nonzero(scan.valid))
            if scan.no_return is not None:
                counts["no_return_readings"] += int(np.count_nonzero(scan.no_return))
            counts["beams_min"] = n if counts["beams_min"] is None else min(counts["beams_min"], n)
            counts["beams_max"] = n if counts["beams_max"] is None else max(counts["beams_max"], n)
            if last_t is not None and scan.timestamp < last_t:
                counts["timestamp_reversals"] += 1
            last_t = scan.timestamp
            stamps.append(scan.timestamp_text or f"{scan.timestamp:.9f}")
            ground_truth.append(scan.ground_truth)
            times.append(scan.timestamp)
            poses.append(res.local_pose)
            if keep_points:
                scan_points.append(None if res.points is None else res.points.astype(np.float32))
            if self.global_slam is not None:
                t1 = time.perf_counter()
                if res.inserted:
                    self.global_slam.add_node(scan, res.local_pose, res.range_data.hits, res.covariance, res.inserted_into)
                for sub in res.finished_submaps:
                    self.global_slam.add_finished_submap(sub)
                stage_ms.setdefault("global", []).append((time.perf_counter() - t1) * 1e3)
            if res.inserted:
                rd = res.range_data
                nodes.append(Node(scan.index, scan.timestamp, np.asarray(res.local_pose, dtype=float),
                                  rd.hits.astype(np.float32), rd.misses.astype(np.float32), rd.origin.astype(np.float32)))
            self.observer.on_scan(scan, res)
            if progress is not None:
                progress.update(1)
        if not stamps:
            raise InputError(getattr(source, "path", "input"), "no scans")
        counts["nodes"] = len(nodes)
        poses = np.array(poses, dtype=float).reshape(-1, 3)
        if self.global_slam is not None:
            t1 = time.perf_counter()
            node_global = self.global_slam.finish()
            poses = globalize(poses, node_global)
            stage_ms["final_optimization"] = [(time.perf_counter() - t1) * 1e3]
        grid = None
        if keep_points:
            from slam2d.backend.final_refinement import refine_trajectory

            t1 = time.perf_counter()
            grid = build_map(self.cfg, nodes, {n.scan_index: poses[n.scan_index] for n in nodes})
            stage_ms["map_build"] = [(time.perf_counter() - t1) * 1e3]
            t1 = time.perf_counter()
            poses = refine_trajectory(grid, poses, scan_points, final.translation_weight, final.rotation_weight,
                                      self.cfg.refine.max_iterations, self.cfg.refine.occupied_space_weight)
            stage_ms["final_refinement"] = [(time.perf_counter() - t1) * 1e3]
        timings = {k: _percentiles(v) for k, v in stage_ms.items()}
        result = RunResult(stamps, np.array(times), poses, nodes, counts, timings, map=grid)
        if ground_truth and all(g is not None for g in ground_truth):
            from slam2d.eval.ate import ate

            result.ground_truth_ate = ate(poses, np.array(ground_truth, dtype=float))
        self.observer.on_finish(self)
        return result


def globalize(local_poses: np.ndarray, node_global: dict[int, np.ndarray]) -> np.ndarray:
    """Every scan's global pose: its latest node's global pose composed with the local motion since that node."""
    from slam2d.geometry import between, compose

    out = local_poses.copy()
    anchor = None
    for i in range(len(local_poses)):
        if i in node_global:
            anchor = i
        if anchor is not None:
            out[i] = compose(node_global[anchor], between(local_poses[anchor], local_poses[i]))
    return out


def _percentiles(v: list[float]) -> dict:
    a = np.asarray(v)
    return {"p50_ms": round(float(np.percentile(a, 50)), 4), "p99_ms": round(float(np.percentile(a, 99)), 4),
            "max_ms": round(float(a.max()), 4), "total_s": round(float(a.sum()) / 1e3, 4), "count": int(a.size)}


def build_map(cfg: SlamConfig, nodes: list[Node], poses: dict[int, np.ndarray] | None = None) -> ProbabilityGrid:
    """Insert every node's range data at its pose (``poses`` by scan index overrides the node's own)."""
    grid = ProbabilityGrid.from_config(cfg.grid, resolution=cfg.map.resolution)
    if not nodes:
        return grid
    # every node's origin, hits and misses moved to its pose in one vectorized transform
    parts = [np.concatenate([n.origin[None, :], n.hits, n.misses]) for n in nodes]
    sizes = np.array([len(p) for p in parts])
    pts = np.concatenate(parts).astype(np.float64)
    pose = np.array([poses[n.scan_index] if poses is not None else n.local_pose for n in nodes], dtype=np.float64)
    per_point = np.repeat(pose, sizes, axis=0)
    c, s = np.cos(per_point[:, 2]), np.sin(per_point[:, 2])
    world = np.empty_like(pts)
    world[:, 0] = per_point[:, 0] + c * pts[:, 0] - s * pts[:, 1]
    world[:, 1] = per_point[:, 1] + s * pts[:, 0] + c * pts[:, 1]
    scans, at = [], 0
    for n, size in zip(nodes, sizes):
        h = len(n.hits)
        scans.append((world[at], world[at + 1:at + 1 + h], world[at + 1 + h:at + size]))
        at += size
    grid.insert_scans(scans)  # in order, rows split among threads: equal to inserting one at a time
    return grid


__all__ = ["Mapper", "OdometryTracker", "MatchingResult", "RunResult", "Node", "build_map"]
