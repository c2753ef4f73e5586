"""Rerun logging of a slam2d run (rerun-sdk 0.41), attached as an `Observer`.

Entities (all in the ``/world`` frame, metres, drawn in one 3D view seen from above: the map is a
``GridMap``, which only 3D views draw, so scans, robot and graph are 3D archetypes on the z = 0
plane too; a 2D view cannot show a GridMap, and an Image in it would put y downwards):

* ``/world/scan/hits``, ``/world/scan/no_return`` — each scan's points and the ends of its
  free-space rays (no-return beams and readings beyond the range filter), per scan;
* ``/world/robot`` (arrow), ``/world/trajectory`` (line strip, throttled);
* ``/world/submaps/active`` (GridMap, throttled) and ``/world/submaps/<k>`` (finished ones,
  re-logged at new poses after each optimization);
* ``/world/graph/nodes``, ``/world/graph/node_in_submap``, ``/world/graph/loops``,
  ``/world/graph/rejected`` — the pose graph, in distinct colours (node-in-submap links are
  hidden in the view by default, as are rejected loop candidates: each a dense web over the map;
  the blueprint panel switches them on);
* ``/world/map`` — the final occupancy map;
* ``/metrics/timing/*``, ``/metrics/score/*`` — Scalars (a series' first call, which compiles or
  loads numba kernels, goes to ``/metrics/first_call/*`` so the plot keeps its scale);
  ``/events`` — TextLog.

Timelines: ``scan`` (sequence) and ``time`` (sensor time). Per-scan data is buffered and
sent with ``send_columns`` in blocks, so logging costs little per scan.
"""
from __future__ import annotations


import math
import os

import numpy as np

from slam2d.geometry import compose, transform_points
from slam2d.observer import Observer

os.environ.setdefault("RERUN_ANALYTICS", "0")

import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402

HIT = (230, 80, 40, 255)
NO_RETURN = (90, 140, 255, 160)
TRAJ = (40, 170, 90, 255)
INTRA = (160, 160, 160, 120)
LOOP = (40, 200, 60, 255)
REJECTED = (220, 40, 40, 200)


#: where each layer is drawn [m above the map plane], lowest first: the final map covers the submaps
#: it was made from; the graph and the scans lie on top
Z_SUBMAP, Z_MAP, Z_GRAPH, Z_SCAN = -0.02, -0.01, 0.01, 0.02
#: submaps are drawn translucent: a submap's unknown cells would otherwise hide its neighbours
SUBMAP_OPACITY = 0.6


def xyz(points, z=0.0) -> np.ndarray:
    """(N, 2) → (N, 3) float32 on the plane z."""
    p = np.asarray(points, dtype=np.float32).reshape(-1, 2)
    return np.column_stack([p, np.full(len(p), z, np.float32)])


def blueprint(center=None, extent: float = 40.0):
    """The layout; ``center`` (x, y) and ``extent`` [m] place the camera above the map, looking down."""
    eye = None
    if center is not None:
        cx, cy = float(center[0]), float(center[1])
        eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=[cx, cy - 0.01 * extent, 1.1 * extent],
                                look_target=[cx, cy, 0.0], eye_up=[0.0, 0.0, 1.0])
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="map", origin="/world", eye_controls=eye, line_grid=rrb.LineGrid3D(visible=False),
                              overrides={"/world/graph/node_in_submap": rrb.EntityBehavior(visible=False),
                                         "/world/graph/rejected": rrb.EntityBehavior(visible=False)}),
            rrb.Vertical(
                rrb.TimeSeriesView(name="timings [ms]", origin="/metrics/timing"),
                rrb.TimeSeriesView(name="match scores", origin="/metrics/score"),
                rrb.TimeSeriesView(name="pose graph", origin="/metrics/optimization"),
                rrb.TextLogView(name="events", origin="/events"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=False,
    )


def occupancy_bytes(grid) -> tuple[bytes, int, int]:
    """ROS OccupancyGrid convention (0 free … 100 occupied, 255 unknown), row 0 at the bottom."""
    p = grid.probability(unknown_value=np.nan)
    out = np.full(p.shape, 255, dtype=np.uint8)
    k = ~np.isnan(p)
    out[k] = np.clip(np.round(p[k] * 100), 0, 100).astype(np.uint8)
    return out.tobytes(), p.shape[1], p.shape[0]


def grid_map(grid, transform=None, z: float = Z_SUBMAP, opacity: float = SUBMAP_OPACITY) -> rr.GridMap:
    """The grid as a GridMap; ``transform`` (x, y, θ) moves it from its local frame to the map frame."""
    data, w, h = occupancy_bytes(grid)
    corner = np.array([float(grid.origin[0]), float(grid.origin[1]), z])
    theta = 0.0
    if transform is not None:
        c, s = math.cos(transform[2]), math.sin(transform[2])
        corner = np.array([transform[0] + c * corner[0] - s * corner[1], transform[1] + s * corner[0] + c * corner[1], z])
        theta = float(transform[2])
    return rr.GridMap(data=data, format=rr.components.ImageFormat(width=w, height=h, color_model="L", channel_datatype="U8"),
                      cell_size=grid.resolution, translation=corner.tolist(),
                      quaternion=rr.Quaternion(xyzw=[0.0, 0.0, math.sin(theta / 2), math.cos(theta / 2)]),
                      colormap=rr.components.Colormap.RvizMap, opacity=opacity)


class RerunObserver(Observer):
    wants_graph_error = True  # plotted after every optimization

    def __init__(self, path: str | None = None, spawn: bool = False, flush_every: int = 200,
                 trajectory_every: int = 50, submap_every: int = 20):
        rr.init("slam2d", spawn=spawn, default_blueprint=blueprint())
        if path:
            rr.save(path, default_blueprint=blueprint())
        self.flush_every = flush_every
        self.trajectory_every = trajectory_every
        self.submap_every = submap_every
        self._buf = self._empty()
        self._traj = []
        self._seq = 0
        self._inserted = 0
        self._logged_finished = set()
        self._global = None
        self._submap_logged: dict = {}
        self._timed: set = set()  # timing series whose first call (numba compile or cache load) is logged apart
        rr.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    @staticmethod
    def _empty():
        return {"seq": [], "t": [], "hits": [], "misses": [], "pose": [], "score": [], "timings": {}}

    def _time_kw(self, t):
        return {"timestamp": t} if t > 1e8 else {"duration": t}

    def on_start(self, info: dict) -> None:
        # at scan 0, not static: static data on an entity hides everything logged on it over time
        rr.set_time("scan", sequence=0)
        rr.log("/events", rr.TextLog(f"slam2d run on {info.get('input')} ({info.get('mode')})",
                                     level=rr.TextLogLevel.INFO))

    def on_scan(self, scan, result) -> None:
        # scans, robot and active submap are drawn in the map frame: the local pose moved by the
        # latest optimization's correction (identity before the first one, or without global SLAM)
        pose = np.asarray(result.local_pose, dtype=float)
        if self._global is not None:
            pose = compose(self._global.correction, pose)
        rd = result.range_data
        b = self._buf
        b["seq"].append(self._seq)
        b["t"].append(scan.timestamp)
        b["hits"].append(transform_points(pose, rd.hits).astype(np.float32))
        b["misses"].append(transform_points(pose, rd.misses).astype(np.float32))
        b["pose"].append(pose)
        b["score"].append(np.nan if result.score is None else float(result.score))
        for k, v in result.timings.items():
            if k not in self._timed:  # the first call compiles (or loads) numba kernels: its own series
                self._timed.add(k)
                k = f"first_call/{k}"
            b["timings"].setdefault(k, {})[self._seq] = v
        self._traj.append(pose[:2].copy())
        self._seq += 1
        if result.inserted:
            self._inserted += 1
            sub = getattr(result, "active_submap", None)
            if sub is not None and self._inserted % self.submap_every == 0:
                rr.set_time("scan", sequence=self._seq - 1)
                rr.set_time("time", **self._time_kw(scan.timestamp))
                rr.log("/world/submaps/active", grid_map(sub.grid, None if self._global is None else self._global.correction))
        for sub in getattr(result, "finished_submaps", ()) or ():
            self.on_submap_finished(sub)
        if self._seq % self.trajectory_every == 0:
            rr.set_time("scan", sequence=self._seq - 1)
            rr.set_time("time", **self._time_kw(scan.timestamp))
            rr.log("/world/trajectory", rr.LineStrips3D([xyz(self._traj, Z_GRAPH)], colors=[TRAJ], radii=[0.02]))
        if len(b["seq"]) >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        b = self._buf
        if not b["seq"]:
            return
        seq = np.asarray(b["seq"])
        t = np.asarray(b["t"])
        idx = [rr.TimeColumn("scan", sequence=seq),
               rr.TimeColumn("time", **({"timestamp": t} if t.min() > 1e8 else {"duration": t}))]
        for name, key, color in (("hits", "hits", HIT), ("no_return", "misses", NO_RETURN)):
            arrays = b[key]
            lengths = [len(a) for a in arrays]
            pos = np.concatenate(arrays) if sum(lengths) else np.zeros((0, 2), np.float32)
            cols = rr.Points3D.columns(positions=xyz(pos, Z_SCAN), colors=np.tile(np.array(color, np.uint8), (len(pos), 1)),
                                       radii=np.full(len(pos), 0.03, np.float32)).partition(lengths)
            rr.send_columns(f"/world/scan/{name}", indexes=idx, columns=cols)
        poses = np.asarray(b["pose"])
        vec = 0.4 * np.column_stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])])
        rr.send_columns("/world/robot", indexes=idx,
                        columns=rr.Arrows3D.columns(origins=xyz(poses[:, :2], Z_SCAN), vectors=xyz(vec)))
        sc = np.asarray(b["score"])
        ok = ~np.isnan(sc)
        if ok.any():
            rr.send_columns("/metrics/score/local_match", indexes=[rr.TimeColumn("scan", sequence=seq[ok])],
                            columns=rr.Scalars.columns(scalars=sc[ok]))
        for k, d in b["timings"].items():
            s = np.fromiter(d.keys(), dtype=np.int64)
            v = np.fromiter(d.values(), dtype=np.float64)
            path = f"/metrics/{k}" if k.startswith("first_call/") else f"/metrics/timing/{k}"
            rr.send_columns(path, indexes=[rr.TimeColumn("scan", sequence=s)],
                            columns=rr.Scalars.columns(scalars=v))
        self._buf = self._empty()

    def on_submap_finished(self, submap) -> None:
        if submap.index in self._logged_finished:
            return
        self._logged_finished.add(submap.index)
        rr.set_time("scan", sequence=self._seq - 1 if self._seq else 0)
        rr.log(f"/world/submaps/{submap.index}", grid_map(submap.grid))
        rr.log("/events", rr.TextLog(f"submap {submap.index} finished ({submap.num_range_data} scans)",
                                     level=rr.TextLogLevel.INFO))

    def on_loop_candidate(self, record: dict) -> None:
        rr.set_time("scan", sequence=self._seq - 1 if self._seq else 0)
        path = "/metrics/timing/loop_search" if "loop_search" in self._timed else "/metrics/first_call/loop_search"
        self._timed.add("loop_search")
        rr.log(path, rr.Scalars(record["search_ms"]))
        if record["score"] is not None:
            rr.log("/metrics/score/loop", rr.Scalars(record["score"]))
        level = rr.TextLogLevel.INFO if record["accepted"] else rr.TextLogLevel.DEBUG
        what = f"accepted, score {record['score']:.3f}" if record["accepted"] else record["reason"]
        how = f" [{record['search']}]" if record.get("search") else ""  # the wide or the final search
        rr.log("/events", rr.TextLog(f"loop candidate scan {record['to_scan']} vs submap {record['submap']}{how}: {what}",
                                     level=level))

    def on_optimized(self, global_slam) -> None:
        """Move finished submaps and the pose graph to the optimized poses."""
        self._global = global_slam
        seq = self._seq - 1 if self._seq else 0
        rr.set_time("scan", sequence=seq)
        # an optimization takes far longer than a scan: its own plot, so the per-scan timings keep their scale
        rr.log("/metrics/optimization/time_ms", rr.Scalars(1e3 * getattr(global_slam, "last_optimize_seconds", 0.0)))
        before, after = global_slam.graph.last_error
        rr.log("/metrics/optimization/error", rr.Scalars(after))
        for k, T in global_slam.submap_transforms().items():
            last = self._submap_logged.get(k)
            # a submap is re-sent only when the optimization moved it visibly (throttles the recording)
            grid = global_slam.matchers[k].submap.grid
            if 0 in grid.shape:  # released for the final solve: the final map replaces the submaps
                continue
            if last is None or np.hypot(*(T[:2] - last[:2])) > 0.02 or abs(T[2] - last[2]) > 0.0035:
                rr.log(f"/world/submaps/{k}", grid_map(grid, T))
                self._submap_logged[k] = T
        # the whole pose graph is re-sent after every optimization, from one bulk read of the node poses
        ids, poses = global_slam.graph.all_node_poses()
        xy = poses[:, :2].astype(np.float32)

        def at(scan_ids):
            return xy[np.searchsorted(ids, np.asarray(scan_ids, dtype=np.int64))]

        recs = [r for r in global_slam.records if r["relative_pose"] is not None]
        final = np.array([bool(r.get("in_final_graph")) for r in recs], dtype=bool)
        if recs:
            segs = np.stack([at([r["from_scan"] for r in recs]), at([r["to_scan"] for r in recs])], axis=1)
        else:
            segs = np.zeros((0, 2, 2), np.float32)
        a_list, n_list = [], []
        for k, m in global_slam.matchers.items():
            js = [j for j in m.submap.node_indices if j in global_slam.nodes]
            a_list.extend([global_slam.submap_anchor[k]] * len(js))
            n_list.extend(js)
        intra = np.stack([at(a_list), at(n_list)], axis=1) if n_list else np.zeros((0, 2, 2), np.float32)
        self.on_constraints(seq, xy, intra, segs[final], segs[~final])
        err = f"error {after:.1f}" if math.isnan(before) else f"error {before:.1f} -> {after:.1f}"
        rr.log("/events", rr.TextLog(f"pose graph optimized: {len(global_slam.graph.loops)} loop constraints, {err}",
                                     level=rr.TextLogLevel.INFO))

    def on_constraints(self, seq, nodes, node_in_submap, loops=(), rejected=()) -> None:
        """Pose graph: node positions (N, 2) and constraints as (M, 2, 2) segment arrays."""
        rr.set_time("scan", sequence=seq)
        rr.log("/world/graph/nodes", rr.Points3D(xyz(nodes, Z_GRAPH), radii=0.04, colors=[(250, 200, 0, 255)]))
        for name, segs, color in (("node_in_submap", node_in_submap, INTRA), ("loops", loops, LOOP),
                                  ("rejected", rejected, REJECTED)):
            if len(segs):
                strips = [xyz(seg, Z_GRAPH) for seg in np.asarray(segs, np.float32)]
                rr.log(f"/world/graph/{name}", rr.LineStrips3D(strips, colors=[color], radii=[0.01]))

    def on_finish(self, result) -> None:
        """The final map, trajectory and pose graph at the last scan."""
        self.flush()
        g = result.graph
        self.log_final(len(result.stamps) - 1, result.map, result.poses, g["nodes"], g["node_in_submap"], g["loops"],
                       g["rejected"], {"scans": len(result.stamps), "nodes": len(result.nodes)})

    def log_final(self, seq, grid, poses, nodes, node_in_submap, loops, rejected, stats: dict) -> None:
        rr.set_time("scan", sequence=seq)
        # the final map replaces the submaps (which were last drawn before the final solve)
        rr.log("/world/submaps", rr.Clear(recursive=True))
        rr.log("/world/map", grid_map(grid, z=Z_MAP, opacity=1.0))
        rr.log("/world/trajectory", rr.LineStrips3D([xyz(poses[:, :2], Z_GRAPH)], colors=[TRAJ], radii=[0.02]))
        self.on_constraints(seq, nodes, node_in_submap, loops, rejected)
        rr.log("/events", rr.TextLog("run finished: " + ", ".join(f"{k} {v}" for k, v in stats.items()),
                                     level=rr.TextLogLevel.INFO))
        # the camera above the whole map, looking down (the blueprint of the start knew no map yet)
        b = grid.known_bounds()
        if b is not None:
            r0, r1, c0, c1 = b
            lo = grid.origin + np.array([c0, r0]) * grid.resolution
            hi = grid.origin + np.array([c1, r1]) * grid.resolution
            rr.send_blueprint(blueprint(0.5 * (lo + hi), float(np.hypot(*(hi - lo)))), make_active=True)

    def close(self) -> None:
        """Flush everything and close the recording (the .rrd is complete after this)."""
        self.flush()
        rr.disconnect()


def view(path: str) -> int:
    """Open a recording in the Rerun viewer (the ``rerun`` binary the wheel ships)."""
    import shutil
    import subprocess
    import sys

    exe = shutil.which("rerun") or os.path.join(os.path.dirname(sys.executable), "rerun")
    return subprocess.call([exe, path])


__all__ = ["RerunObserver", "view"]
