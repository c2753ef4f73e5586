"""MCAP (ROS 2 profile) reading and writing: ``sensor_msgs/msg/LaserScan`` in,
``nav_msgs/msg/Odometry`` for wheel odometry, ``geometry_msgs/msg/PoseStamped`` for ground
truth, ``tf2_msgs/msg/TFMessage`` on ``/tf_static`` and ``/tf`` for the laser mount (the TF
chain from the odometry's child frame to the scan's ``header.frame_id``, `slam2d.io.tf_tree`).
CDR encoding via ``mcap_ros2``; Foxglove and ROS 2 tools open what this writes. A file without a
summary section (a recorder that never closed it, or was cut off) is read in file order, up to
its first broken record.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from slam2d.errors import InputError
from slam2d.io.ros2_msgs import msgdef, stamp_from_text
from slam2d.io.ros_input import (GROUND_TRUTH_TOPIC, TF_TYPES, PoseTrack, ScanConverter, TopicCounter, add_pose,
                                 choose_topics, robot_tracks)
from slam2d.io.tf_tree import LaserMount, TfTree
from slam2d.types import Scan

log = logging.getLogger("slam2d.io")


def _mcap_errors():
    import struct

    from mcap.exceptions import McapError

    # struct.error: a file shorter than a record header (a few bytes of junk, or cut right after the magic)
    return (McapError, ValueError, KeyError, EOFError, OSError, IndexError, AssertionError, struct.error)


class McapLog:
    """Lazy iterator over the LaserScans of an MCAP file (odometry and ground truth interpolated to scan stamps)."""

    def __init__(self, path, scan_topic: str | None = None, odom_topic: str | None = None):
        self.path = Path(path)
        if not self.path.exists():
            raise InputError(self.path, "no such file")
        self._summary_cache = None
        self._indexed = True  # False: no usable summary section; read in file order (``_read_summary``)
        self._broken_after: int | None = None  # messages before the broken record that ends a cut-off file
        self.topics = self._topics()
        self.scan_topic, self.odom_topic, self.gt_topic = choose_topics(self.path, self.topics, scan_topic, odom_topic)
        self._check_encodings()
        self._tracks_cache = None  # read once: a second pass (results.mcap) warns about the mount only once
        self.odometry_from: str | None = None  # known once a pass over the scans read the log (``robot_tracks``)

    @property
    def laser_mount(self) -> LaserMount | None:
        """The laser's mount from the log's TF tree (``tf_tree.laser_mount``) once a pass over the scans read it."""
        return None if self._tracks_cache is None else self._tracks_cache[2]

    def _reader(self, f):
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        return make_reader(f, decoder_factories=[DecoderFactory()])

    def _check_encodings(self) -> None:
        """The topics read must be CDR (ROS 2) encoded: what the decoder reads. A ROS 1 bag re-saved as MCAP
        keeps its messages in the ROS 1 encoding."""
        read = {t for t in (self.scan_topic, self.odom_topic, self.gt_topic) if t} | {
            t for t, n in self.topics.items() if n in TF_TYPES}
        for ch in self._summary().channels.values():
            if ch.topic in read and ch.message_encoding != "cdr":
                hint = " (a ROS 1 bag saved as MCAP: give slam2d the .bag itself)" if ch.message_encoding == "ros1" else ""
                raise InputError(self.path, f"{ch.topic} is {ch.message_encoding!r}-encoded; slam2d reads the ROS 2 "
                                 f"(CDR) encoding of MCAP{hint}")

    def _summary(self):
        if self._summary_cache is None:
            self._summary_cache = self._read_summary()
        return self._summary_cache

    def _read_summary(self):
        """The summary section; a file without one (written live and never closed, or cut off when
        the recorder stopped) is read record by record instead, up to the first broken record, with a
        warning saying how far it got."""
        try:
            with open(self.path, "rb") as f:
                summary = self._reader(f).get_summary()
        except _mcap_errors():
            summary = None
        if summary is not None:
            return summary
        from types import SimpleNamespace

        from mcap.reader import NonSeekingReader

        self._indexed = False
        channels, schemas, n = {}, {}, 0
        with open(self.path, "rb") as f:
            try:
                for sch, ch, _msg in NonSeekingReader(f).iter_messages(log_time_order=False):
                    channels[ch.id] = ch
                    if sch is not None:
                        schemas[sch.id] = sch
                    n += 1
            except _mcap_errors() as e:
                if n == 0:
                    raise InputError(self.path, f"not a readable MCAP file, truncated or corrupt ({type(e).__name__}: "
                                     f"{e})") from None
                self._broken_after = n
                log.warning("%s: no summary section, and a broken record after %d messages (a recording cut off?): "
                            "reading the messages before it", self.path, n)
        if self._broken_after is None:
            log.info("%s: no summary section (written live?): read in file order", self.path)
        return SimpleNamespace(channels=channels, schemas=schemas, statistics=None)

    def _messages(self, topics: list[str]):
        """(channel, decoded message) of ``topics``: in log-time order by the index, or in file order
        (up to the broken record of a cut-off file) without one."""
        with open(self.path, "rb") as f:
            if self._indexed:
                for _sch, ch, _msg, m in self._reader(f).iter_decoded_messages(topics=topics):
                    yield ch, m
                return
            from mcap.reader import NonSeekingReader
            from mcap_ros2.decoder import DecoderFactory

            it = NonSeekingReader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=topics, log_time_order=False)
            while True:
                try:
                    _sch, ch, _msg, m = next(it)
                except StopIteration:
                    return
                except _mcap_errors():
                    if self._broken_after is None:
                        raise
                    return  # the broken tail ``_read_summary`` warned about
                yield ch, m

    def _topics(self) -> dict[str, str]:
        summary = self._summary()
        topics = {}
        for ch in summary.channels.values():
            sch = summary.schemas.get(ch.schema_id)
            topics[ch.topic] = sch.name if sch else ""
        return topics

    def num_scans(self) -> int | None:
        summary = self._summary()
        if summary.statistics is None:
            return None
        ids = [cid for cid, ch in summary.channels.items() if ch.topic == self.scan_topic]
        return sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)

    def _tracks(self):
        """Odometry and ground-truth tracks, the TF tree, the odometry's child frame, the scan frame."""
        odom, gt, tree = PoseTrack(), PoseTrack(), TfTree()
        base = scan_frame = None
        wanted = [t for t in (self.odom_topic, self.gt_topic) if t]
        tf_topics = [t for t, n in self.topics.items() if n in TF_TYPES]
        for _ch, m in self._messages([self.scan_topic]):
            scan_frame = m.header.frame_id or None
            break
        else:
            raise InputError(self.path, f"no messages on {self.scan_topic}")
        position = TopicCounter()
        for ch, m in (self._messages(wanted + tf_topics) if wanted + tf_topics else ()):
            k = position(ch.topic)
            if ch.topic in tf_topics:
                try:
                    tree.add_message(m, static=ch.topic.lstrip("/") == "tf_static")
                except ValueError as e:
                    raise InputError(self.path, f"bad transform on {ch.topic}: {e}", record=k) from None
            elif ch.topic == self.odom_topic:
                base = base or m.child_frame_id or None
                add_pose(odom, self.path, k, ch.topic, m.header, m.pose.pose)
            else:
                add_pose(gt, self.path, k, ch.topic, m.header, m.pose)
        odom, mount, self.odometry_from = robot_tracks(self.path, tree, odom, self.odom_topic, scan_frame, base)
        return odom, gt, mount

    def __iter__(self):
        try:
            yield from self._iter()
        except InputError:
            raise
        except _mcap_errors() as e:
            raise InputError(self.path, f"corrupt MCAP data ({type(e).__name__}: {e})") from None

    def _iter(self):
        if self._tracks_cache is None:
            self._tracks_cache = self._tracks()
        odom, gt, mount = self._tracks_cache
        convert = ScanConverter(self.path, mount, odom, gt)
        for k, (_ch, m) in enumerate(self._messages([self.scan_topic])):
            yield convert(k, m)


# ------------------------------------------------------------------ writing
def _header(sec, nsec, frame):
    return {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": frame}


def _neighbours(x: float, k: int) -> list[float]:
    """x and the k floats on either side of it, nearest first."""
    out, up, down = [x], x, x
    for _ in range(k):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, -math.inf)
        out += [up, down]
    return out


def yaw_quaternion(theta: float) -> tuple[float, float]:
    """(z, w) of a rotation by ``theta`` about z: sin/cos of θ/2, moved by at most a few ulps so
    that 2·atan2(z, w) gives ``theta`` back exactly (`slam2d.io.ros_input.yaw_of`)."""
    z, w = math.sin(theta / 2), math.cos(theta / 2)
    for zz in _neighbours(z, 4):
        for ww in _neighbours(w, 4):
            if 2.0 * math.atan2(zz, ww) == theta:
                return zz, ww
    return z, w


def _pose_dict(p):
    z, w = yaw_quaternion(float(p[2]))
    return {"position": {"x": float(p[0]), "y": float(p[1]), "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": z, "w": w}}


#: seconds a ``builtin_interfaces/Time`` (ROS 2, int32) and a ROS 1 ``time`` (uint32) can hold
ROS2_SECONDS = (-2**31, 2**31 - 1)
ROS1_SECONDS = (0, 2**32 - 1)


def _stamp_of(scan: Scan, seconds=ROS2_SECONDS, source="input") -> tuple[int, int]:
    if scan.timestamp_text is not None:
        sec, nsec = stamp_from_text(scan.timestamp_text)
    else:
        ns = round(scan.timestamp * 1e9)
        sec, nsec = ns // 1_000_000_000, ns % 1_000_000_000
    if not seconds[0] <= sec <= seconds[1]:
        raise InputError(source, f"scan stamp {scan.timestamp_text or scan.timestamp} is outside the "
                         f"seconds a ROS time holds ({seconds[0]}..{seconds[1]})", record=scan.index)
    return sec, nsec


def scan_messages(scan: Scan, with_mount: bool, scan_topic: str = "/scan", odom_topic: str = "/odom",
                  seconds=ROS2_SECONDS, source="input"):
    """(topic, type, fields, sec, nanosec) of the messages that carry one scan: ``/tf_static``
    base_link → laser (``with_mount``: before the first scan), the LaserScan, its Odometry and
    ground truth when it has them. Every bag and MCAP writer of slam2d writes these. A stamp the
    ROS time type cannot hold (``seconds``) is an error naming ``source`` and the scan."""
    sec, nsec = _stamp_of(scan, seconds, source)
    if with_mount:
        off = scan.laser_offset
        yield "/tf_static", "tf2_msgs/TFMessage", {"transforms": [{
            "header": _header(sec, nsec, "base_link"), "child_frame_id": "laser",
            "transform": {"translation": {"x": float(off[0]), "y": float(off[1]), "z": 0.0},
                          "rotation": _pose_dict(off)["orientation"]}}]}, sec, nsec
    n = scan.num_beams
    # readings the source marks as no-return lie above range_max, as ROS expects
    rmax = float(scan.range_max)
    if scan.no_return is not None:
        finite_no_return = scan.ranges[scan.no_return & np.isfinite(scan.ranges)]
        if finite_no_return.size:
            rmax = min(rmax, float(np.nextafter(np.float32(finite_no_return.min()), np.float32(0))))
    yield scan_topic, "sensor_msgs/LaserScan", {
        "header": _header(sec, nsec, "laser"),
        "angle_min": scan.angle_min, "angle_max": scan.angle_min + (n - 1) * scan.angle_increment,
        "angle_increment": scan.angle_increment, "time_increment": 0.0, "scan_time": 0.0,
        "range_min": scan.range_min, "range_max": rmax,
        "ranges": scan.ranges.astype(np.float32).tolist(),
        "intensities": [] if scan.intensities is None else scan.intensities.astype(np.float32).tolist(),
    }, sec, nsec
    if scan.odom_pose is not None:
        yield odom_topic, "nav_msgs/Odometry", {
            "header": _header(sec, nsec, "odom"), "child_frame_id": "base_link",
            "pose": {"pose": _pose_dict(scan.odom_pose), "covariance": [0.0] * 36},
            "twist": {"twist": {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
                      "covariance": [0.0] * 36}}, sec, nsec
    if scan.ground_truth is not None:
        yield GROUND_TRUTH_TOPIC, "geometry_msgs/PoseStamped", {"header": _header(sec, nsec, "map"),
                                                                "pose": _pose_dict(scan.ground_truth)}, sec, nsec


class McapWriter:
    """Writes scans (+ odometry, ground truth, laser mount) in the ROS 2 profile."""

    def __init__(self, f, scan_topic="/scan", odom_topic="/odom", source="input"):
        from mcap_ros2.writer import Writer

        self.source = source  # the log the scans come from, named in errors
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
        for topic, type_name, msg, sec, nsec in scan_messages(scan, not self._mount_written, self.scan_topic,
                                                              self.odom_topic, source=self.source):
            self.write(topic, type_name, msg, sec, nsec)
        self._mount_written = True

    def write_pose(self, topic, pose, sec, nsec, frame="map"):
        self.write(topic, "geometry_msgs/PoseStamped", {"header": _header(sec, nsec, frame), "pose": _pose_dict(pose)}, sec, nsec)

    def finish(self):
        self._w.finish()
