"""The laser mount from a log's TF tree (``tf2_msgs/TFMessage`` on ``/tf_static`` and ``/tf``).

A ROS log says where the laser sits on the robot as a chain of transforms, e.g.
``base_link → base_laser_mount → laser``. `TfTree` collects every parent→child edge, composes
the chain between two frames in 3D (either direction, any length) and projects the result onto
the plane: the laser's pose (x, y, yaw) in the robot frame, which is `Scan.laser_offset`. A
laser mounted upside down (its z axis pointing down: a roll or pitch of 180°) sweeps the plane
the other way round, so its beam at angle a lies at -a in a frame turned by that yaw
(`LaserMount.mirrored`; the readers mirror its scans, as Cartographer's 3D sensor transform and
slam_toolbox's inverted-laser check do).
Edges from ``/tf_static`` are fixed; an edge from ``/tf`` is used only when it never changed
over the log (old ROS 1 bags publish fixed mounts on ``/tf``); an edge that moves (odom →
base_link) is not a mount. Its stamped values are kept (`TfTree.moving_edge`): where a log has
no ``nav_msgs/Odometry``, the moving edge into the robot frame is the wheel odometry, as
slam_toolbox reads it (``odom_frame`` → ``base_frame`` through TF). Frame names are compared
without a leading ``/`` (ROS 1 style).
"""
from __future__ import annotations

import logging
import math
from array import array
from collections import deque
from typing import NamedTuple

import numpy as np

from slam2d.io.ros2_msgs import stamp_text

log = logging.getLogger("slam2d.io")

#: a /tf edge whose later values differ from its first by more than this (m or rad) is dynamic
CHANGE_TOLERANCE = 1e-6
#: a composed mount whose z axis leans more than this from the robot's (rad) is warned about
TILT_WARNING = math.radians(5.0)


class LaserMount(NamedTuple):
    """Where the laser sits in the robot frame: its planar pose (x, y, yaw) and whether it is
    mounted upside down (``mirrored``: a beam at angle a lies at -a in the frame of that pose)."""

    pose: np.ndarray
    mirrored: bool = False


def frame_name(frame: str) -> str:
    return str(frame).lstrip("/")


def _rotation(qx, qy, qz, qw) -> np.ndarray:
    q = np.array([qw, qx, qy, qz], dtype=float)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"quaternion ({qx}, {qy}, {qz}, {qw}) has no rotation")
    w, x, y, z = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def transform_matrix(translation, quaternion) -> np.ndarray:
    """4×4 homogeneous matrix of a translation (x, y, z) and a quaternion (x, y, z, w)."""
    m = np.eye(4)
    m[:3, :3] = _rotation(*quaternion)
    m[:3, 3] = np.asarray(translation, dtype=float)
    if not np.all(np.isfinite(m[:3, 3])):
        raise ValueError(f"translation ({', '.join(str(v) for v in translation)}) is not finite")
    return m


class TfTree:
    """Parent→child transforms of a log; `pose_of` composes the chain between two frames."""

    def __init__(self):
        self._edges: dict[tuple[str, str], np.ndarray] = {}
        self._dynamic: set[tuple[str, str]] = set()
        self._samples: dict[tuple[str, str], array] = {}  # /tf edges: (stamp, x, y, yaw) after one another

    def add(self, parent: str, child: str, translation, quaternion, static: bool, stamp: float | None = None) -> None:
        """One ``TransformStamped``: ``translation`` (x, y, z), ``quaternion`` (x, y, z, w), its
        header's ``stamp`` [s] (kept for an edge that is not static)."""
        key = (frame_name(parent), frame_name(child))
        m = transform_matrix(translation, quaternion)
        if not static and stamp is not None:
            self._samples.setdefault(key, array("d")).extend((stamp, m[0, 3], m[1, 3], math.atan2(m[1, 0], m[0, 0])))
        if static or key not in self._edges:
            self._edges[key] = m
            if static:
                self._dynamic.discard(key)
        elif np.max(np.abs(self._edges[key] - m)) > CHANGE_TOLERANCE:
            self._dynamic.add(key)

    def add_message(self, msg, static: bool) -> None:
        """Every transform of a decoded ``tf2_msgs/TFMessage``."""
        for tr in msg.transforms:
            t, q = tr.transform.translation, tr.transform.rotation
            stamp = float(stamp_text(int(tr.header.stamp.sec), int(tr.header.stamp.nanosec)))
            self.add(tr.header.frame_id, tr.child_frame_id, (t.x, t.y, t.z), (q.x, q.y, q.z, q.w), static, stamp)

    def moving_edge(self, child: str) -> tuple[str, np.ndarray] | None:
        """The one edge into ``child`` that moves over the log: (its parent frame, (N, 4) rows of
        stamp, x, y, yaw in stamp order); None when no edge, or more than one, moves into it."""
        child = frame_name(child)
        keys = [k for k in self._dynamic if k[1] == child and k in self._samples]
        if len(keys) != 1:
            return None
        rows = np.frombuffer(self._samples[keys[0]], dtype=np.float64).reshape(-1, 4)
        return keys[0][0], rows[np.argsort(rows[:, 0], kind="stable")]

    def root_of(self, frame: str) -> str | None:
        """The topmost frame ``frame`` hangs from through fixed edges (None when it has no parent)."""
        parents = {c: p for (p, c) in self._edges if (p, c) not in self._dynamic}
        f, seen = frame_name(frame), set()
        while f in parents and f not in seen:
            seen.add(f)
            f = parents[f]
        return f if seen else None

    def frames(self) -> set[str]:
        return {f for e in self._edges for f in e}

    def _path(self, start: str, goal: str) -> list[tuple[str, str, bool]] | None:
        """Edges (parent, child, forward) from ``start`` to ``goal`` over fixed edges, or None."""
        nbrs: dict[str, list[tuple[str, tuple[str, str, bool]]]] = {}
        for (p, c) in self._edges:
            if (p, c) in self._dynamic:
                continue
            nbrs.setdefault(p, []).append((c, (p, c, True)))
            nbrs.setdefault(c, []).append((p, (p, c, False)))
        prev: dict[str, tuple[str, tuple[str, str, bool]] | None] = {start: None}
        todo = deque([start])
        while todo:
            f = todo.popleft()
            if f == goal:
                path = []
                while prev[f] is not None:
                    f, e = prev[f]
                    path.append(e)
                return path[::-1]
            for g, e in nbrs.get(f, []):
                if g not in prev:
                    prev[g] = (f, e)
                    todo.append(g)
        return None

    def pose_of(self, frame: str, in_frame: str) -> np.ndarray | None:
        """(x, y, yaw) of ``frame`` in ``in_frame`` through fixed edges; None when not connected."""
        mount = self.mount_of(frame, in_frame)
        return None if mount is None else mount.pose

    def mount_of(self, frame: str, in_frame: str) -> LaserMount | None:
        """``frame`` in ``in_frame`` through fixed edges, projected onto the plane (module docstring);
        None when not connected. The yaw is that of ``frame``'s x axis; ``mirrored`` when its z axis
        points down."""
        frame, in_frame = frame_name(frame), frame_name(in_frame)
        if frame == in_frame:
            return LaserMount(np.zeros(3), False)
        path = self._path(in_frame, frame)
        if path is None:
            return None
        m = np.eye(4)
        for p, c, forward in path:
            e = self._edges[(p, c)]
            m = m @ (e if forward else np.linalg.inv(e))
        tilt = math.acos(float(np.clip(m[2, 2], -1.0, 1.0)))
        mirrored = m[2, 2] < 0
        if min(tilt, math.pi - tilt) > TILT_WARNING:
            log.warning("the laser frame %r leans %.1f° from %r's %s; slam2d uses its projection onto the plane",
                        frame, math.degrees(min(tilt, math.pi - tilt)), in_frame,
                        "downward axis (mounted upside down, tilted)" if mirrored else "vertical")
        elif mirrored:
            log.info("the laser frame %r is upside down in %r: its scans are mirrored into the robot's plane",
                     frame, in_frame)
        return LaserMount(np.array([m[0, 3], m[1, 3], math.atan2(m[1, 0], m[0, 0])]), bool(mirrored))


def laser_mount(tree: TfTree, scan_frame: str | None, base_frame: str | None, source) -> LaserMount:
    """The laser's mount in the robot frame, or zero with one warning saying why.

    The robot frame is the odometry's child frame (``base_frame``); a log without odometry has
    none, and then it is the root of the fixed tree the laser hangs from, or, with no TF for the
    laser either, the laser itself (zero, no warning: there is no other frame to be in)."""
    if base_frame is None and scan_frame is not None:
        base_frame = tree.root_of(scan_frame)
        if base_frame is None:
            log.debug("%s: no odometry and no TF for %r: trajectories are the laser's", source, scan_frame)
            return LaserMount(np.zeros(3))
    if scan_frame is not None and base_frame is not None:
        mount = tree.mount_of(scan_frame, base_frame)
        if mount is not None:
            return mount
        why = f"no chain of fixed TF transforms from {frame_name(base_frame)!r} to {frame_name(scan_frame)!r}"
    else:
        why = "the LaserScan has no header.frame_id"
    known = ", ".join(sorted(tree.frames())) or "none"
    log.warning("%s: %s (TF frames: %s); using a zero laser mount (laser at the robot's origin)", source, why, known)
    return LaserMount(np.zeros(3))
