"""The library API: feed scans one at a time, get the best pose now; finish for the final map.

The pipeline of Hess et al. 2016 (Sec. III): every scan goes through local SLAM
(``frontend.LocalSlam``, Sec. IV); scans that pass the motion filter become nodes of the
pose graph (``backend.global_slam.GlobalSlam``, Sec. V), which closes loops against
finished submaps as they come, on a worker thread beside local SLAM (``backend.background``).
``finish`` runs the final optimization, builds the map from the optimized nodes
(``grid.map_builder``), refines every scan once in it (``backend.final_refinement``) and
assesses the run (``health``). ``slam2d run`` is a thin caller of this module::

    import slam2d
    slam = slam2d.Slam()
    for scan in slam2d.open_source("log.clf.bz2"):
        est = slam.add_scan(scan)       # est.local_pose, est.global_pose: (x, y, θ) now
    result = slam.finish()              # result.poses: (N, 3), result.map, result.summary
    result.save("runs/x")               # the files ``slam2d run`` writes
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import threading
import time
from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from slam2d import kernel_cache
from slam2d.allocator import map_large_blocks, return_freed_memory
from slam2d.config import SlamConfig, config_from_dict, load_config
from slam2d.errors import InputError, UsageError
from slam2d.gc_freeze import freeze_startup_objects
from slam2d.geometry import between, compose
from slam2d.grid.map_builder import build_map
from slam2d.grid.probability_grid import ProbabilityGrid
from slam2d.observer import Observer
from slam2d.spill import ArraySpill
from slam2d.threads import CallerCores
from slam2d.types import MAX_TIME_GAP, MAX_TIME_REVERSAL, Estimate, Node, Scan

MODES = ("global", "local", "odometry")
log = logging.getLogger(__name__)


#: bytes of local-match score volumes waiting for global SLAM's worker to compute their covariances
HANDOVER_BYTES = 16 * 1024 * 1024


class _HandedOver:
    """A local match whose covariance global SLAM's worker computes (``Slam._covariance_of``)."""

    __slots__ = ("match", "size", "taken")

    def __init__(self, match, size: int, taken):
        self.match, self.size, self.taken = match, size, taken

    @property
    def covariance(self):
        try:
            return self.match.covariance
        finally:
            self.taken(self.size)
            self.match = None


@dataclass
class SlamResult:
    """A finished run: the final pose of every scan, the map, and what the run reports about itself."""

    config: SlamConfig
    stamps: list[str]          # every scan's timestamp as the source wrote it
    times: np.ndarray          # (N,) seconds
    poses: np.ndarray          # (N, 3) final pose of every scan, in input order
    map: ProbabilityGrid
    summary: dict              # what summary.json holds (health included)
    nodes: list[Node]
    constraints: list[dict] = field(default_factory=list)  # one record per loop candidate (constraints.jsonl)
    graph: dict = field(default_factory=dict)  # nodes, node_in_submap, loops, rejected (final poses) for viewers

    def save(self, out_dir, mcap_scans=None) -> Path:
        """Write ``trajectory.txt`` (TUM), ``map.pgm`` + ``map.yaml`` + ``map.png``, ``config.yaml``,
        ``constraints.jsonl`` (global SLAM) and ``summary.json`` into ``out_dir``; with
        ``mcap_scans`` (the run's scans again, e.g. ``open_source(path)``) also ``results.mcap``.
        Files appear only when all of them are complete."""
        from slam2d.config import dump_config
        from slam2d.output import OutputDir

        if out_dir is None or str(out_dir) == "":
            raise UsageError("save needs a folder to write into")
        out = OutputDir(out_dir)
        try:
            out.write_trajectory("trajectory.txt", self.stamps, self.poses)
            out.write_map(self.map, self.config)
            out.write_text("config.yaml", dump_config(self.config))
            if self.summary.get("mode") == "global":
                out.write_text("constraints.jsonl", "".join(json.dumps(r) + "\n" for r in self.constraints))
            if mcap_scans is not None:
                from slam2d.grid.map_export import occupancy_image
                from slam2d.io.results_mcap import write_results_mcap

                img, ox, oy = occupancy_image(self.map, *self.config.map.cell_thresholds(self.config.grid))
                write_results_mcap(out.staged("results.mcap"), mcap_scans, self.poses, img, self.map.resolution, (ox, oy),
                                   self.stamps)
            out.write_json("summary.json", self.summary)
            out.commit()
        except BaseException:
            out.abort()
            raise
        return out.path


class Slam:
    """Online 2D SLAM of one robot with one laser.

    ``mode``: ``"global"`` (local SLAM and loop closure; local SLAM only when the config's
    ``loop_closure.enabled`` is false), ``"local"`` (no pose graph) or ``"odometry"`` (poses are
    the wheel odometry; scans only build the map). ``observer`` hears about every step (Rerun,
    progress): see ``slam2d.observer``. ``source_name`` names the input in error messages.
    """

    def __new__(cls, *args, **kwargs):
        # before the first scan: the kernels earlier runs needed loaded (``kernel_cache``), then the
        # start-up objects out of the collector's way, before this Slam exists: a Slam (and any cycle
        # through it) is never among them (``gc_freeze``)
        kernel_cache.load_remembered()
        freeze_startup_objects()
        return super().__new__(cls)

    def __init__(self, config: SlamConfig | None = None, *, mode: str = "global", observer: Observer | None = None,
                 source_name: str = "input"):
        if mode not in MODES:
            raise UsageError(f"mode must be one of {', '.join(MODES)}, not {mode!r}")
        if isinstance(config, dict):
            config = config_from_dict(config)
        if config is not None and not isinstance(config, SlamConfig):
            hint = " (a YAML file: Slam.from_yaml(path))" if isinstance(config, (str, Path)) else ""
            raise UsageError(f"Slam takes a SlamConfig or a dict of its sections, not {config!r}{hint}")
        self.config = cfg = config if config is not None else SlamConfig()
        if mode == "global" and not cfg.loop_closure.enabled:
            mode = "local"
        self.mode = mode
        self.source_name = str(source_name)
        self.observer = observer or Observer()
        map_large_blocks()  # grids, stacks and score volumes come and go for hours (``allocator``)
        self._kernels_before = kernel_cache.loaded()  # what this run loads beyond it is remembered at finish
        if mode == "odometry":
            from slam2d.odometry import OdometryTracker

            self.tracker = OdometryTracker(cfg, self.source_name)
        else:
            from slam2d.frontend import LocalSlam

            self.tracker = LocalSlam(cfg, loop_closure=mode == "global")
        self.global_slam = None
        self._background = None
        self._handover_lock = threading.Lock()
        self._handed_over = 0  # bytes of score volumes handed to the worker and not yet taken (``_covariance_of``)
        if mode == "global":
            from slam2d.backend.global_slam import GlobalSlam

            background = cfg.loop_closure.background and os.name == "posix"  # the solver process passes pipe fds
            self.global_slam = GlobalSlam(cfg, self.observer, solver_process=background)
            if background:
                from slam2d.backend.background import Background

                self._background = Background()
                # local SLAM's parallel kernels leave the second core to the worker while it works
                self.tracker.cores.busy = lambda b=self._background: not b.idle()
                # and the worker's searches take both once the caller waits for them (``finish``)
                import numba

                self.global_slam.cores = CallerCores(lambda b=self._background: not b.caller_waits(),
                                                     most=numba.get_num_threads())
        self._stamps: list[str] = []
        # per scan, in flat arrays of float64 (a list holds a Python object per entry, several times the memory)
        self._times = array("d")
        self._latest = -math.inf  # the latest stamp so far
        self._gap_warned = False
        self._local = array("d")  # x, y, θ of every scan, one after the other
        self._ground_truth: list = []
        # what the end of the run needs of every scan goes to disk as it comes (``spill``): the range
        # data of each node (the map, the health report) and the points each scan matched (the final
        # refinement); ``nodes`` is filled from it in ``finish``, once the solver process has gone
        self._node_spill = ArraySpill(4)  # hits, misses, origin, (x, y, θ, scan index, time, far misses)
        self.nodes: list[Node] = []
        self._keep_points = self.global_slam is not None and cfg.final_refinement.enabled
        self._points = ArraySpill(1)
        self._stage_ms: dict[str, array] = {}  # per stage, its time in every call [ms]
        self._counts = {"scans": 0, "nodes": 0, "invalid_readings": 0, "no_return_readings": 0, "readings": 0,
                        "timestamp_reversals": 0, "beams_min": None, "beams_max": None}
        self._t_start = None
        self._caller_cpu = 0.0  # the calling thread's CPU time in add_scan [s]
        self._finished = False

    @classmethod
    def from_yaml(cls, path, **kwargs) -> "Slam":
        """``Slam(load_config(path), ...)``: a YAML config as ``slam2d dump-config`` writes it."""
        return cls(load_config(path), **kwargs)

    @property
    def num_scans(self) -> int:
        return len(self._times)

    def start(self, info: dict | None = None) -> None:
        """Tell observers a run begins (``add_scan`` does it on the first scan otherwise)."""
        if self._t_start is None:
            self._t_start = time.perf_counter()
            self.observer.on_start({"mode": self.mode, **(info or {})})

    def add_scan(self, scan: Scan) -> Estimate:
        """Process one scan (in time order) and return its pose estimate as of now."""
        if self._finished:
            raise UsageError("add_scan after finish: start a new Slam")
        i = len(self._times)
        if not isinstance(scan, Scan):
            raise UsageError(f"add_scan takes a slam2d.Scan (e.g. Scan.from_ranges(...)), not {type(scan).__name__}")
        scan.check(f"{self.source_name}: scan {i}")
        if self._times and scan.timestamp < self._latest - MAX_TIME_REVERSAL:
            raise UsageError(f"{self.source_name}: scan {i}: stamped {scan.timestamp:.6f}, "
                             f"{self._latest - scan.timestamp:.6g} s before an "
                             f"earlier scan: scans must come in time order")
        if self._times and scan.timestamp > self._latest + MAX_TIME_GAP and not self._gap_warned:
            self._gap_warned = True
            log.warning("%s: scan %d is stamped %s, %.6g s after the scan before it (a broken stamp, or scans of two "
                        "runs?)", self.source_name, i, scan.stamp_text, scan.timestamp - self._latest)
        self._latest = scan.timestamp if not self._times else max(self._latest, scan.timestamp)
        self.start()
        t_call, c_call = time.perf_counter(), time.thread_time()
        if scan.index != i:  # node ids are input positions
            scan = dataclasses.replace(scan, index=i)
        t0 = time.perf_counter()
        res = self.tracker.add_scan(scan)
        self._stage("frontend", (time.perf_counter() - t0) * 1e3)
        for k, v in res.timings.items():
            self._stage(k, v)
        self._count(scan)
        self._stamps.append(scan.stamp_text)
        self._times.append(scan.timestamp)
        self._ground_truth.append(scan.ground_truth)
        local = np.array(res.local_pose, dtype=float).reshape(3)
        self._local.extend(local.tolist())
        if self._keep_points:
            self._points.append(_kept_points(res))
        gs = self.global_slam
        if gs is not None:
            t1 = time.perf_counter()
            if res.inserted:  # what global SLAM keeps of the scan, so the worker shares nothing that changes
                self._global(gs.add_node, NodeStamp(scan.index, scan.timestamp, scan.stamp_text),
                             np.array(res.local_pose, dtype=float), res.range_data.hits, self._covariance_of(res),
                             list(res.inserted_into), res.doubt, res.fresh_start)
            for sub in res.finished_submaps:
                self._global(gs.add_finished_submap, sub)
            self._stage("global", (time.perf_counter() - t1) * 1e3)
        if res.inserted:
            n = Node.of(i, scan.timestamp, res.local_pose, res.range_data)
            self._node_spill.append(n.hits, n.misses, n.origin,
                                    np.array([*n.local_pose, n.scan_index, n.time, n.far_misses], dtype=np.float64))
        self.observer.on_scan(scan, res)
        glob = local.copy() if gs is None else compose(gs.correction, local)
        c_end = time.thread_time()  # read inside the wall interval, so the CPU time never exceeds it
        self._stage("add_scan", (time.perf_counter() - t_call) * 1e3)  # the latency a caller sees
        self._caller_cpu += c_end - c_call
        return Estimate(i, scan.timestamp, local.copy(), glob, bool(res.inserted), res.quality)

    def _covariance_of(self, res):
        """The local match's covariance for global SLAM, or the match itself for global SLAM's worker to
        compute it from (its arrays are not changed later): off local SLAM's thread, as long as the
        score volumes handed over and not yet taken stay within ``HANDOVER_BYTES``; a worker far
        behind (a sparse log's wide windows) gets the covariance computed here, so what waits in its
        queue stays small. The covariance is the same either way."""
        m = res.match
        if m is None or self._background is None:
            return res.covariance
        size = sum(a.nbytes for a in (m.scores, m.raw_scores) if a is not None)
        with self._handover_lock:
            if self._handed_over + size > HANDOVER_BYTES:
                return res.covariance
            self._handed_over += size
        return _HandedOver(m, size, self._taken)

    def _taken(self, size: int) -> None:
        with self._handover_lock:
            self._handed_over -= size

    def sync(self) -> None:
        """Wait until global SLAM has taken in every scan added so far (it runs behind ``add_scan`` on
        a worker thread, ``loop_closure.background``); the next estimate then carries every
        correction found up to here. Raises what global SLAM raised."""
        if self._background is not None:
            self._background.wait()

    def _global(self, fn, *args):
        """A call into global SLAM: queued for the worker thread, or made now without one."""
        if self._background is not None:
            self._background.submit(fn, *args)
        else:
            fn(*args)

    def run(self, scans) -> SlamResult:
        """``add_scan`` for every scan, then ``finish``."""
        for scan in scans:
            self.add_scan(scan)
        return self.finish()

    def finish(self) -> SlamResult:
        """Final search (``GlobalSlam.final_search``), final optimization, map, final refinement and
        health; the Slam takes no scans after this."""
        if self._finished:
            raise UsageError("finish called twice")
        if not self._times:
            raise InputError(self.source_name, "no scans")
        self._check_input()
        self._finished = True
        cfg = self.config
        self._counts["nodes"] = len(self._node_spill)
        poses = np.array(self._local, dtype=float).reshape(-1, 3)
        if self.mode == "odometry" and len(poses) > 1 and np.all(poses == poses[0]):
            log.warning("%s: the odometry never moves: every scan gets the same pose (slam2d info says whether the "
                        "log's odometry changes; run without --odometry-only to map from the scans)", self.source_name)
        gs = self.global_slam
        if self._background is not None:
            t1 = time.perf_counter()
            self._background.join()  # global SLAM catches up with the last scans
            self._stage_ms["global_catch_up"] = [(time.perf_counter() - t1) * 1e3]
        if gs is not None:
            t1 = time.perf_counter()
            gs.final_search()  # before the submaps' grids go: it searches them
            self._stage_ms["final_search"] = [(time.perf_counter() - t1) * 1e3]
        for sub in getattr(self.tracker, "all_submaps", lambda: [])():
            sub.grid.release()  # local SLAM and loop search are over: the map is built from the nodes
        if gs is not None:
            t1 = time.perf_counter()
            gs.release_search()
            return_freed_memory()  # before the last solves: the solver process's peak comes on top
            poses = globalize(poses, gs.finish())
            self._stage_ms["final_optimization"] = [(time.perf_counter() - t1) * 1e3]
        return_freed_memory()
        self.nodes = self._spilled_nodes()
        self._node_spill.close()
        t_map = time.perf_counter()
        node_poses = {n.scan_index: poses[n.scan_index] for n in self.nodes} if gs is not None else None
        grid = build_map(cfg, self.nodes, node_poses)
        map_s = time.perf_counter() - t_map
        if self._keep_points:
            from slam2d.backend.final_refinement import refine_trajectory

            t1 = time.perf_counter()
            fr = cfg.final_refinement
            points = self._refinement_points()
            self._points.close()
            poses = refine_trajectory(grid, poses, points, fr.translation_weight, fr.rotation_weight,
                                      cfg.refine.max_iterations, cfg.refine.occupied_space_weight)
            self._stage_ms["final_refinement"] = [(time.perf_counter() - t1) * 1e3]
        summary = self._summary(poses, map_s)
        result = SlamResult(cfg, self._stamps, np.array(self._times), poses, grid, summary, self.nodes,
                            list(gs.records) if gs is not None else [], graph_of(self.tracker, self.nodes, poses, gs))
        self.observer.on_finish(result)
        kernel_cache.remember(self._kernels_before)
        return result

    def _check_input(self) -> None:
        """What makes a run's output meaningless whatever SLAM does, found once every scan is in: no
        reading of any scan is a return (every beam invalid or a no-return), or every scan carries the
        same timestamp (a trajectory file would then give made-up times). Raised as an InputError, so
        nothing is written that looks like a result."""
        c = self._counts
        if c["scans"] and c["readings"] == c["invalid_readings"]:
            raise InputError(self.source_name, f"none of the {c['scans']} scans holds a usable reading (every beam is "
                             f"invalid, out of range or a no-return: {c['no_return_readings']} no-returns of "
                             f"{c['readings']} readings)")
        t = self._times
        if len(t) > 1 and min(t) == max(t):
            raise InputError(self.source_name, f"every scan is stamped {self._stamps[0]}: the timestamps are unusable "
                             "(a CARMEN log can be read with --scan-period S, its scans S seconds apart)")

    def _spilled_nodes(self) -> list[Node]:
        """The nodes so far, read back from ``_node_spill``."""
        return [Node(int(m[3]), float(m[4]), m[:3].copy(), hits, misses, origin, int(m[5]))
                for hits, misses, origin, m in self._node_spill.records()]

    def _refinement_points(self) -> list[np.ndarray | None]:
        """Every scan's matched points (float32) for the final refinement, as ``_kept_points`` kept them."""
        hits = {n.scan_index: n.hits for n in (self.nodes or self._spilled_nodes())}
        return [p if p is None or p.ndim == 2 else hits[i][p] for i, (p,) in enumerate(self._points.records())]

    # ---- bookkeeping
    def _stage(self, name, ms):
        self._stage_ms.setdefault(name, array("d")).append(ms)

    def _count(self, scan):
        c = self._counts
        n = scan.num_beams
        c["scans"] += 1
        c["readings"] += n
        c["invalid_readings"] += int(n - np.count_nonzero(scan.valid))
        if scan.no_return is not None:
            c["no_return_readings"] += int(np.count_nonzero(scan.no_return))
        c["beams_min"] = n if c["beams_min"] is None else min(c["beams_min"], n)
        c["beams_max"] = n if c["beams_max"] is None else max(c["beams_max"], n)
        if self._times and scan.timestamp < self._times[-1]:
            c["timestamp_reversals"] += 1

    def _summary(self, poses, map_s) -> dict:
        from slam2d.health import assess
        from slam2d.summary import run_summary

        timings = {k: _percentiles(v) for k, v in self._stage_ms.items()}
        if "add_scan" in timings:
            # the caller's CPU time against its wall time (total_s): the rest it waited, mostly for the
            # interpreter lock while global SLAM's worker ran Python beside it
            timings["add_scan"]["cpu_s"] = round(self._caller_cpu, 4)
        if self._background is not None:
            timings["global_worker_cpu_s"] = round(self._background.cpu_s, 3)
        times = np.array(self._times)
        s = run_summary(self.source_name, self.mode, times, self._counts, timings, map_s, self.tracker)
        gt = self._ground_truth
        if gt and all(g is not None for g in gt):
            from slam2d.eval.ate import ate

            s["ate_vs_ground_truth"] = ate(poses, np.array(gt, dtype=float))
        if self.global_slam is not None:
            s.update(self.global_slam.summary())
        t_h = time.perf_counter()
        s["health"] = assess(self.config, self.nodes, poses, s.get("local_slam"), s.get("loop_closure"), s.get("scans"))
        s["timings"]["health_s"] = round(time.perf_counter() - t_h, 3)
        wall = time.perf_counter() - self._t_start
        s["wall_time_s"] = round(wall, 3)
        duration = s["duration_s"]
        s["real_time_factor"] = round(duration / wall, 3) if wall > 0 else None
        return s


class NodeStamp(NamedTuple):
    """What global SLAM reads of a node's scan."""

    index: int
    timestamp: float
    timestamp_text: str | None


def _kept_points(res) -> np.ndarray | None:
    """What the final refinement needs of a scan: its matched points (float32), or, for a scan that
    became a node, which of the node's hits (kept as float32 anyway) they are (the same numbers in
    a quarter of the memory)."""
    if res.points is None:
        return None
    if res.inserted and res.point_index is not None:
        return res.point_index.astype(np.uint16 if len(res.range_data.hits) <= 1 << 16 else np.int64)
    return res.points.astype(np.float32)


def globalize(local_poses: np.ndarray, node_global: dict[int, np.ndarray]) -> np.ndarray:
    """Every scan's global pose: its latest node's global pose composed with the local motion since that node."""
    out = local_poses.copy()
    anchor = None
    for i in range(len(local_poses)):
        if i in node_global:
            anchor = i
        if anchor is not None:
            out[i] = compose(node_global[anchor], between(local_poses[anchor], local_poses[i]))
    return out


def graph_of(tracker, nodes, poses, global_slam=None) -> dict:
    """Node positions (N, 2), node-in-submap segments, final and rejected loop constraints ((M, 2, 2) each) at the final poses."""
    pose_of = {n.scan_index: poses[n.scan_index] for n in nodes}
    xy = np.array([p[:2] for p in pose_of.values()]).reshape(-1, 2)
    segs, loops, rejected = [], [], []
    for sub in getattr(tracker, "all_submaps", lambda: [])():
        anchor = sub.node_indices[0] if sub.node_indices else None
        for i in sub.node_indices:
            if i in pose_of and anchor in pose_of:
                segs.append((pose_of[i][:2], pose_of[anchor][:2]))
    for r in (global_slam.records if global_slam else []):
        a, b = pose_of.get(r["from_scan"]), pose_of.get(r["to_scan"])
        if a is not None and b is not None:
            (loops if r.get("in_final_graph") else rejected).append((a[:2], b[:2]))
    return {"nodes": xy, "node_in_submap": np.array(segs).reshape(-1, 2, 2), "loops": np.array(loops).reshape(-1, 2, 2),
            "rejected": np.array(rejected).reshape(-1, 2, 2)}


def _percentiles(v: list[float]) -> dict:
    a = np.asarray(v)
    return {"p50_ms": round(float(np.percentile(a, 50)), 4), "p99_ms": round(float(np.percentile(a, 99)), 4),
            "max_ms": round(float(a.max()), 4), "total_s": round(float(a.sum()) / 1e3, 4), "count": int(a.size)}


__all__ = ["Slam", "SlamResult", "globalize", "MODES"]
