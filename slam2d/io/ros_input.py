"""What the ROS readers (MCAP in `slam2d.io.mcap`, rosbags in `slam2d.io.rosbag`) share: topics
chosen by message type, stamped pose tracks interpolated to scan times, and decoded
``sensor_msgs/LaserScan`` messages turned into `Scan` records (REP 117 semantics, via
`Scan.from_ranges`) with the checks that name the file and record of a bad message.
"""
from __future__ import annotations

import bisect
import functools
import logging
import math

import numpy as np

from slam2d.errors import InputError, UsageError
from slam2d.geometry import interpolate_pose, quaternion_to_yaw
from slam2d.io.ros2_msgs import stamp_text
from slam2d.io.tf_tree import LaserMount, TfTree, frame_name, laser_mount
from slam2d.types import MAX_TIME_REVERSAL, Scan

SCAN_TYPES = ("sensor_msgs/msg/LaserScan", "sensor_msgs/LaserScan")
ODOM_TYPES = ("nav_msgs/msg/Odometry", "nav_msgs/Odometry")
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/PoseStamped")
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf2_msgs/TFMessage", "tf/msg/tfMessage", "tf/tfMessage")
GROUND_TRUTH_TOPIC = "/ground_truth"
log = logging.getLogger("slam2d.io")


def stamp(header) -> tuple[float, str]:
    """(seconds, exact decimal text) of a header stamp; the float is the text's correctly rounded
    value, as a CARMEN log's stamp is, so a converted log gives bit-identical times."""
    text = stamp_text(int(header.stamp.sec), int(header.stamp.nanosec))
    return float(text), text


def yaw_of(q) -> float:
    """Yaw of a quaternion. A rotation about z alone (x = y = 0) is 2·atan2(z, w), the exact inverse
    of the half-angle encoding `slam2d.io.mcap.yaw_quaternion` writes (bit-identical round trip)."""
    if q.x == 0 and q.y == 0:
        yaw = 2.0 * math.atan2(q.z, q.w)
        return yaw - 2 * math.pi if yaw > math.pi else yaw + 2 * math.pi if yaw <= -math.pi else yaw
    return float(quaternion_to_yaw(q.x, q.y, q.z, q.w))


def pose2d(pose) -> np.ndarray:
    """(x, y, yaw) of a ``geometry_msgs/Pose``."""
    return np.array([pose.position.x, pose.position.y, yaw_of(pose.orientation)])


@functools.lru_cache(maxsize=1024)
def laser_angle(value: float, beams: int) -> float:
    """The float64 angle a LaserScan's float32 ``angle_min`` / ``angle_increment`` was rounded from.

    Drivers and logs state scan angles as a fraction of π (−π/2, π/180, π/720) or as a short
    decimal (−1.570796, 0.017453): the first π·p/q with q ≤ 2·beams + 2 that rounds to the same
    float32, else the shortest decimal that does. A scan written from float64 angles of either
    kind so reads back bit-identical (a CARMEN log and its bag give the same trajectory); any
    other value moves by less than half a float32 step."""
    f = np.float32(value)
    x = float(f)
    if x == 0.0 or not math.isfinite(x):
        return x
    for q in range(1, 2 * beams + 3):
        p = round(x / math.pi * q)
        if p != 0:
            v = math.pi * p / q
            if np.float32(v) == f:
                return v
    return float(np.format_float_positional(f, unique=True))


def choose_topics(path, topics: dict[str, str], scan_topic: str | None, odom_topic: str | None):
    """(scan topic, odometry topic or None, ground-truth topic or None) from ``{topic: type}``:
    the given ones after checking their type, else the only topic of each type."""
    listing = ", ".join(f"{t} [{n}]" for t, n in sorted(topics.items())) or "none"

    def pick(given, types, what, required):
        if given is not None:
            if given not in topics:
                raise InputError(path, f"no topic {given!r} (topics: {listing})")
            if topics[given] not in types:
                raise InputError(path, f"topic {given!r} is {topics[given]}, not {types[0]}")
            return given
        found = sorted(t for t, n in topics.items() if n in types)
        if not found:
            if required:
                raise InputError(path, f"no {types[0]} topic (topics: {listing})")
            return None
        if len(found) > 1:
            raise InputError(path, f"several {types[0]} topics ({', '.join(found)}); choose one with --{what}-topic")
        return found[0]

    gt = GROUND_TRUTH_TOPIC if topics.get(GROUND_TRUTH_TOPIC) in POSE_TYPES else None
    return pick(scan_topic, SCAN_TYPES, "scan", True), pick(odom_topic, ODOM_TYPES, "odom", False), gt


class PoseTrack:
    """Stamped poses (any arrival order), interpolated at query times."""

    def __init__(self):
        self.t: list[float] = []
        self.p: list[np.ndarray] = []

    def add(self, t, pose):
        if self.t and t < self.t[-1]:
            i = bisect.bisect(self.t, t)
            self.t.insert(i, t)
            self.p.insert(i, pose)
        else:
            self.t.append(t)
            self.p.append(pose)

    def __bool__(self):
        return bool(self.t)

    def at(self, t, occurrence: int = 0) -> np.ndarray:
        """The pose at ``t``: a pose stamped exactly ``t`` (the ``occurrence``-th of several, in
        arrival order, the last when there are fewer), else interpolated, else the nearest end."""
        i = bisect.bisect_left(self.t, t)
        if i < len(self.t) and self.t[i] == t:
            last = bisect.bisect_right(self.t, t) - 1
            return self.p[min(i + occurrence, last)].copy()
        if i <= 0:
            return self.p[0].copy()
        if i >= len(self.t):
            return self.p[-1].copy()
        return interpolate_pose(t, self.t[i - 1], self.p[i - 1], self.t[i], self.p[i])


def robot_tracks(path, tree: TfTree, odom: PoseTrack, odom_topic: str | None, scan_frame: str | None,
                 base: str | None) -> tuple[PoseTrack, LaserMount, str]:
    """(odometry, laser mount, where the odometry came from) once a log's messages are read.

    The odometry is that of the ``nav_msgs/Odometry`` topic; a log without one may still carry the
    wheel odometry as the moving TF edge into the robot frame (``odom`` → ``base_footprint`` on
    ``/tf``, the only odometry slam_toolbox reads), and then that edge is it. The robot frame is
    the Odometry's child frame, else the root of the fixed TF chain the laser hangs from."""
    if odom_topic is not None:
        return odom, laser_mount(tree, scan_frame, base, path), f"nav_msgs/Odometry on {odom_topic}"
    robot = (tree.root_of(scan_frame) or frame_name(scan_frame)) if scan_frame else None
    edge = tree.moving_edge(robot) if robot is not None else None
    if edge is None:
        return odom, laser_mount(tree, scan_frame, None, path), "none"
    parent, rows = edge
    for t, x, y, yaw in rows:
        odom.add(float(t), np.array([x, y, yaw]))
    log.info("%s: no nav_msgs/Odometry topic; the odometry is the TF edge %r -> %r (%d transforms on /tf)",
             path, parent, robot, len(rows))
    return odom, laser_mount(tree, scan_frame, robot, path), f"TF {parent} -> {robot} ({len(rows)} transforms on /tf)"


def add_pose(track: PoseTrack, path, record: int, topic: str, header, pose) -> None:
    """A decoded pose message's (x, y, yaw) into ``track``; a non-finite pose, or an orientation
    quaternion that is no rotation (all zero), is an error naming the message: ``record``, its
    position among ``topic``'s messages, and its stamp."""
    t, text = stamp(header)
    q = pose.orientation
    if not all(math.isfinite(v) for v in (q.x, q.y, q.z, q.w)) or q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w < 1e-18:
        raise InputError(path, f"orientation quaternion ({q.x}, {q.y}, {q.z}, {q.w}) on {topic} (stamp {text}) "
                         "has no rotation", record=record)
    p = pose2d(pose)
    if not np.all(np.isfinite(p)):
        raise InputError(path, f"non-finite pose {tuple(float(v) for v in p)} on {topic} (stamp {text})", record=record)
    track.add(t, p)


class TopicCounter:
    """Each message's position among its own topic's messages: what an error's ``record`` names."""

    def __init__(self):
        self._n: dict[str, int] = {}

    def __call__(self, topic: str) -> int:
        k = self._n.get(topic, 0)
        self._n[topic] = k + 1
        return k


class ScanConverter:
    """Decoded LaserScan messages, in log order, to `Scan` records (index = message number)."""

    def __init__(self, path, mount: LaserMount, odom: PoseTrack, ground_truth: PoseTrack | None = None):
        self.path, self.mount, self.odom, self.gt = path, mount, odom, ground_truth
        self.latest: float | None = None
        self.seen: dict[float, int] = {}  # scans per stamp so far: several scans stamped alike pair
        # with the poses stamped alike in order (a log whose stamps repeat, converted to a bag)
        self.length_warned = False
        self.clock_warned = False

    def __call__(self, k: int, m) -> Scan:
        t, text = stamp(m.header)
        r = np.asarray(m.ranges, dtype=np.float32)
        if r.size == 0:
            raise InputError(self.path, "LaserScan with no ranges", record=k)
        if not (m.angle_increment != 0 and math.isfinite(m.angle_increment)):
            raise InputError(self.path, f"LaserScan angle_increment is {m.angle_increment}", record=k)
        if not (math.isfinite(m.angle_min) and math.isfinite(m.range_max) and m.range_max > 0):
            raise InputError(self.path, f"LaserScan angle_min {m.angle_min} / range_max {m.range_max} unusable",
                             record=k)
        if not (math.isfinite(m.range_min) and 0 <= m.range_min < m.range_max):
            raise InputError(self.path, f"LaserScan range_min {m.range_min} unusable with range_max {m.range_max} "
                             "(it needs 0 <= range_min < range_max)", record=k)
        if self.latest is not None and t < self.latest - MAX_TIME_REVERSAL:
            raise InputError(self.path, f"scan stamp {text} goes back {self.latest - t:.3f} s", record=k)
        self.latest = t if self.latest is None else max(self.latest, t)
        with np.errstate(invalid="ignore"):
            negative = np.flatnonzero((r < 0) & np.isfinite(r))  # -inf is REP 117's "too close": no reading
        if negative.size:
            raise InputError(self.path, f"negative range reading {float(r[negative[0]]):g} at beam {negative[0]} "
                             f"({negative.size} in this scan)", record=k)
        self._check_length(k, m, r.size)
        inten = np.asarray(m.intensities, dtype=np.float32) if len(m.intensities) == r.size else None
        a0, da = laser_angle(float(m.angle_min), r.size), laser_angle(float(m.angle_increment), r.size)
        if self.mount.mirrored:  # upside down: the beam at a lies at -a (``tf_tree``); listed in the same angular order
            a0 = -(a0 + (r.size - 1) * da)
            r = np.ascontiguousarray(r[::-1])
            inten = None if inten is None else np.ascontiguousarray(inten[::-1])
        nth = self.seen.get(t, 0)
        self.seen[t] = nth + 1
        if self.odom and not self.clock_warned and not self.odom.t[0] - 1.0 <= t <= self.odom.t[-1] + 1.0:
            self.clock_warned = True
            log.warning("%s: record %d: the scan stamped %s lies outside the odometry's stamps (%s to %s); such a scan "
                        "takes the odometry's first or last pose (are the scans and the odometry on one clock?)",
                        self.path, k, text, f"{self.odom.t[0]:.3f}", f"{self.odom.t[-1]:.3f}")
        try:
            return Scan.from_ranges(t, r, a0, da, m.range_max,
                                    odom_pose=self.odom.at(t, nth) if self.odom else None, range_min=m.range_min,
                                    laser_offset=self.mount.pose, intensities=inten, timestamp_text=text, index=k,
                                    ground_truth=self.gt.at(t, nth) if self.gt else None)
        except UsageError as e:  # the scan's own fields: named with the file and record
            raise InputError(self.path, str(e).removeprefix("Scan.from_ranges: "), record=k) from None

    def _check_length(self, k: int, m, n: int) -> None:
        """Warn once when a scan's beam count disagrees with its angle_min, angle_max and
        angle_increment by more than one beam (drivers differ on whether angle_max is the last beam's
        angle): the beams are placed at angle_min + i · angle_increment, as Cartographer and
        slam_toolbox place them, and angle_max is not used."""
        if self.length_warned or not math.isfinite(m.angle_max):
            return
        expected = (m.angle_max - m.angle_min) / m.angle_increment + 1
        if abs(expected - n) > 1.5:
            self.length_warned = True
            log.warning("%s: record %d: %d ranges, but angle_min %g to angle_max %g in steps of %g makes %.0f beams; "
                        "the beams are placed from angle_min in steps of angle_increment (angle_max is not used)",
                        self.path, k, n, m.angle_min, m.angle_max, m.angle_increment, expected)
