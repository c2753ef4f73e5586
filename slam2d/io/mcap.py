"""MCAP (ROS 2 profile) reading and writing: ``sensor_msgs/msg/LaserScan`` in,
``nav_msgs/msg/Odometry`` for wheel odometry, ``geometry_msgs/msg/PoseStamped`` for ground
truth, ``tf2_msgs/msg/TFMessage`` on ``/tf_static`` for the laser mount. CDR encoding via
``mcap_ros2``; Foxglove and ROS 2 tools open what this writes.
"""
from __future__ import annotations

import bisect
import math
from pathlib import Path

import numpy as np

from slam2d.errors import InputError
from slam2d.geometry import interpolate_pose, quaternion_to_yaw
from slam2d.io.ros2_msgs import msgdef, stamp_from_text, stamp_text
from slam2d.types import Scan

SCAN_TYPES = ("sensor_msgs/msg/LaserScan", "sensor_msgs/LaserScan")
ODOM_TYPES = ("nav_msgs/msg/Odometry", "nav_msgs/Odometry")
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/PoseStamped")
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf2_msgs/TFMessage")
GROUND_TRUTH_TOPIC = "/ground_truth"


def _mcap_errors():
    from mcap.exceptions import McapError

    return (McapError, ValueError, KeyError, EOFError, OSError, IndexError, AssertionError)


def _yaw(q) -> float:
    return float(quaternion_to_yaw(q.x, q.y, q.z, q.w))


def _stamp(header) -> tuple[float, str]:
    s, ns = int(header.stamp.sec), int(header.stamp.nanosec)
    return s + ns * 1e-9, stamp_text(s, ns)


class _Track:
    """Stamped poses, interpolated at query times."""

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

    def at(self, t) -> np.ndarray:
        i = bisect.bisect_left(self.t, t)
        if i <= 0:
            return self.p[0].copy()
        if i >= len(self.t):
            return self.p[-1].copy()
        return interpolate_pose(t, self.t[i - 1], self.p[i - 1], self.t[i], self.p[i])


class McapLog:
    """Lazy iterator over the LaserScans of an MCAP file (odometry and ground truth interpolated to scan stamps)."""

    def __init__(self, path, scan_topic: str | None = None, odom_topic: str | None = None):
        self.path = Path(path)
        if not self.path.exists():
            raise InputError(self.path, "no such file")
        self.scan_topic, self.odom_topic, self.gt_topic, self.topics = self._detect(scan_topic, odom_topic)

    def _reader(self, f):
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        return make_reader(f, decoder_factories=[DecoderFactory()])

    def _detect(self, scan_topic, odom_topic):
        try:
            with open(self.path, "rb") as f:
                summary = self._reader(f).get_summary()
        except _mcap_errors() as e:
            raise InputError(self.path, f"not a readable MCAP file ({type(e).__name__}: {e})") from None
        if summary is None:
            raise InputError(self.path, "MCAP file has no summary section (unindexed or truncated); re-save it with `mcap recover`")
        topics = {}
        for ch in summary.channels.values():
            sch = summary.schemas.get(ch.schema_id)
            topics[ch.topic] = sch.name if sch else ""
        listing = ", ".join(f"{t} [{n}]" for t, n in sorted(topics.items())) or "none"

        def pick(given, types, what, required):
            if given is not None:
                if given not in topics:
                    raise InputError(self.path, f"no topic {given!r} (topics: {listing})")
                if topics[given] not in types:
                    raise InputError(self.path, f"topic {given!r} is {topics[given]}, not {types[0]}")
                return given
            found = sorted(t for t, n in topics.items() if n in types)
            if what == "pose":
                return GROUND_TRUTH_TOPIC if GROUND_TRUTH_TOPIC in found else None
            if not found:
                if required:
                    raise InputError(self.path, f"no {types[0]} topic (topics: {listing})")
                return None
            if len(found) > 1:
                raise InputError(self.path, f"several {types[0]} topics ({', '.join(found)}); choose one with --{what}-topic")
            return found[0]

        return (pick(scan_topic, SCAN_TYPES, "scan", True), pick(odom_topic, ODOM_TYPES, "odom", False),
                pick(None, POSE_TYPES, "pose", False), topics)

    def num_scans(self) -> int | None:
        with open(self.path, "rb") as f:
            summary = self._reader(f).get_summary()
        if summary is None or summary.statistics is None:
            return None
        ids = [cid for cid, ch in summary.channels.items() if ch.topic == self.scan_topic]
        return sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)

    def _tracks(self):
        odom, gt, mount = _Track(), _Track(), None
        wanted = [t for t in (self.odom_topic, self.gt_topic) if t]
        tf_topics = [t for t, n in self.topics.items() if n in TF_TYPES and t == "/tf_static"]
        if not wanted and not tf_topics:
            return odom, gt, mount
        with open(self.path, "rb") as f:
            for k, (_sch, ch, _msg, m) in enumerate(self._reader(f).iter_decoded_messages(topics=wanted + tf_topics)):
                if ch.topic in tf_topics:
                    for tr in m.transforms:
                        if tr.child_frame_id.lstrip("/") in ("laser", "base_scan", "laser_frame"):
                            mount = np.array([tr.transform.translation.x, tr.transform.translation.y, _yaw(tr.transform.rotation)])
                    continue
                t, _ = _stamp(m.header)
                pose = m.pose.pose if ch.topic == self.odom_topic else m.pose
                p = np.array([pose.position.x, pose.position.y, _yaw(pose.orientation)])
                if not np.all(np.isfinite(p)):
                    raise InputError(self.path, f"non-finite pose on {ch.topic}", record=k)
                (odom if ch.topic == self.odom_topic else gt).add(t, p)
        return odom, gt, mount

    def __iter__(self):
        try:
            yield from self._iter()
        except InputError:
            raise
        except _mcap_errors() as e:
            raise InputError(self.path, f"corrupt MCAP data ({type(e).__name__}: {e})") from None

    def _iter(self):
        odom, gt, mount = self._tracks()
        prev_t = None
        with open(self.path, "rb") as f:
            for k, (_sch, _ch, _msg, m) in enumerate(self._reader(f).iter_decoded_messages(topics=[self.scan_topic])):
                t, text = _stamp(m.header)
                r = np.asarray(m.ranges, dtype=np.float32)
                if r.size == 0:
                    raise InputError(self.path, "LaserScan with no ranges", record=k)
                if not (m.angle_increment != 0 and math.isfinite(m.angle_increment)):
                    raise InputError(self.path, f"LaserScan angle_increment is {m.angle_increment}", record=k)
                if prev_t is not None and t < prev_t - 1.0:
                    raise InputError(self.path, f"scan stamp {text} goes back {prev_t - t:.3f} s", record=k)
                prev_t = t if prev_t is None else max(prev_t, t)
                with np.errstate(invalid="ignore"):
                    if np.any(r < 0):
                        raise InputError(self.path, "negative range reading", record=k)
                inten = np.asarray(m.intensities, dtype=np.float32) if len(m.intensities) == r.size else None
                yield Scan.from_ranges(t, r, m.angle_min, m.angle_increment, m.range_max,
                                       odom_pose=odom.at(t) if odom else None, range_min=m.range_min,
                                       laser_offset=mount, intensities=inten, timestamp_text=text, index=k,
                                       ground_truth=gt.at(t) if gt else None)


# ------------------------------------------------------------------ writing
def _header(sec, nsec, frame):
    return {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": frame}


def _pose_dict(p):
    return {"position": {"x": float(p[0]), "y": float(p[1]), "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(p[2] / 2), "w": math.cos(p[2] / 2)}}


def _stamp_of(scan: Scan) -> tuple[int, int]:
    if scan.timestamp_text is not None:
        return stamp_from_text(scan.timestamp_text)
    ns = round(scan.timestamp * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000


class McapWriter:
    """Writes scans (+ odometry, ground truth, laser mount) in the ROS 2 profile."""

    def __init__(self, f, scan_topic="/scan", odom_topic="/odom"):
        from mcap_ros2.writer import Writer

        self._w = Writer(f)
        self.scan_topic, self.odom_topic = scan_topic, odom_topic
        self._schemas = {}
        self._seq = 0
        self._log_time = -1
        self._mount_written = False

    def schema(self, name):
        if name not in self._schemas:
            self._schemas[name] = self._w.register_msgdef(*msgdef(name))
        return self._schemas[name]

    def write(self, topic, type_name, msg, sec, nsec):
        ns = sec * 1_000_000_000 + nsec
        # log time never goes back, so readers that sort by it keep the source's order even
        # where the source's own stamps go back (the Intel log does); header stamps stay exact
        self._log_time = max(ns, self._log_time + 1)
        self._w.write_message(topic, self.schema(type_name), msg, log_time=self._log_time, publish_time=ns,
                              sequence=self._seq)
        self._seq += 1

    def write_scan(self, scan: Scan):
        sec, nsec = _stamp_of(scan)
        if not self._mount_written:
            self._mount_written = True
            off = scan.laser_offset
            self.write("/tf_static", "tf2_msgs/TFMessage", {"transforms": [{
                "header": _header(sec, nsec, "base_link"), "child_frame_id": "laser",
                "transform": {"translation": {"x": float(off[0]), "y": float(off[1]), "z": 0.0},
                              "rotation": _pose_dict(off)["orientation"]}}]}, sec, nsec)
        n = scan.num_beams
        # readings the source marks as no-return lie above range_max, as ROS expects
        rmax = float(scan.range_max)
        if scan.no_return is not None:
            finite_no_return = scan.ranges[scan.no_return & np.isfinite(scan.ranges)]
            if finite_no_return.size:
                rmax = min(rmax, float(np.nextafter(np.float32(finite_no_return.min()), np.float32(0))))
        self.write(self.scan_topic, "sensor_msgs/LaserScan", {
            "header": _header(sec, nsec, "laser"),
            "angle_min": scan.angle_min, "angle_max": scan.angle_min + (n - 1) * scan.angle_increment,
            "angle_increment": scan.angle_increment, "time_increment": 0.0, "scan_time": 0.0,
            "range_min": scan.range_min, "range_max": rmax,
            "ranges": scan.ranges.astype(np.float32).tolist(),
            "intensities": [] if scan.intensities is None else scan.intensities.astype(np.float32).tolist(),
        }, sec, nsec)
        if scan.odom_pose is not None:
            self.write(self.odom_topic, "nav_msgs/Odometry", {
                "header": _header(sec, nsec, "odom"), "child_frame_id": "base_link",
                "pose": {"pose": _pose_dict(scan.odom_pose), "covariance": [0.0] * 36},
                "twist": {"twist": {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
                          "covariance": [0.0] * 36}}, sec, nsec)
        if scan.ground_truth is not None:
            self.write_pose(GROUND_TRUTH_TOPIC, scan.ground_truth, sec, nsec, "map")

    def write_pose(self, topic, pose, sec, nsec, frame="map"):
        self.write(topic, "geometry_msgs/PoseStamped", {"header": _header(sec, nsec, frame), "pose": _pose_dict(pose)}, sec, nsec)

    def finish(self):
        self._w.finish()
