"""ROS bags through the ``rosbags`` library: ROS 1 ``.bag`` files and ROS 2 bag folders
(``metadata.yaml`` with sqlite3 ``.db3`` or ``.mcap`` storage), read and written.

Reading (`RosbagLog`): ``sensor_msgs/LaserScan`` scans, ``nav_msgs/Odometry`` (and the
simulator's ``/ground_truth`` poses) interpolated to scan stamps, ``tf2_msgs/TFMessage`` on ``/tf_static`` and ``/tf`` for the laser mount (the
TF chain between the odometry's child frame and the scan's ``header.frame_id``,
`slam2d.io.tf_tree`). Messages are decoded with the definitions the bag carries (a ROS 2 bag
without them with the ROS 2 Humble standard types).

Writing (`RosbagWriter`): the same topics as `slam2d.io.mcap.McapWriter` writes (``/scan``,
``/odom``, ``/tf_static`` base_link → laser, ``/ground_truth``) from the same message fields,
ROS 1 (noetic types) or ROS 2 (Humble types, sqlite3 or MCAP storage). A message's bag time
never goes back, so readers that go by it keep the source's order where its stamps go back
(Intel); header stamps stay exact.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from slam2d.errors import InputError, UsageError
from slam2d.io.ros_input import (TF_TYPES, PoseTrack, ScanConverter, TopicCounter, add_pose, choose_topics,
                                 robot_tracks)
from slam2d.io.tf_tree import LaserMount, TfTree
from slam2d.types import Scan


def bag_path(path) -> Path:
    """What `rosbags` opens for a path a user gave: a ``.bag`` file, or a ROS 2 bag's folder
    (given as the folder or as one of its storage files)."""
    p = Path(path)
    if p.is_file() and p.suffix.lower() != ".bag" and (p.parent / "metadata.yaml").exists():
        return p.parent
    return p


def _reader_errors():
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError

    return (AnyReaderError, Reader1Error, Reader2Error, SerdeError, ValueError, KeyError, EOFError, OSError,
            IndexError, AssertionError, AttributeError)


def _why(e: Exception) -> str:
    """An exception as one line (rosbags' YAML errors span several)."""
    return f"{type(e).__name__}: {' '.join(str(e).split())}"


class RosbagLog:
    """Lazy iterator over the LaserScans of a ROS 1 or ROS 2 bag."""

    def __init__(self, path, scan_topic: str | None = None, odom_topic: str | None = None):
        self.path = Path(path)
        if not self.path.exists():
            raise InputError(self.path, "no such file")
        self.bag = bag_path(self.path)
        r = self._open()
        try:
            self.topics = {name: info.msgtype or "" for name, info in r.topics.items()}
            self.counts = {name: info.msgcount for name, info in r.topics.items()}
        finally:
            r.close()
        self.scan_topic, self.odom_topic, self.gt_topic = choose_topics(self.path, self.topics, scan_topic, odom_topic)
        self._tracks_cache = None  # read once: a second pass (results.mcap) warns about the mount only once
        self.odometry_from: str | None = None  # known once a pass over the scans read the log (``robot_tracks``)

    def _open(self):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        try:
            r = AnyReader([self.bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            r.open()
        except _reader_errors() as e:
            raise InputError(self.path, f"not a readable ROS bag ({_why(e)})") from None
        return r

    def num_scans(self) -> int:
        return self.counts[self.scan_topic]

    @property
    def laser_mount(self) -> LaserMount | None:
        """The laser's mount from the log's TF tree (``tf_tree.laser_mount``) once a pass over the scans read it."""
        return None if self._tracks_cache is None else self._tracks_cache[2]

    def _messages(self, reader, topics):
        """(record number, topic, decoded message) of ``topics`` in bag order."""
        conns = [c for c in reader.connections if c.topic in topics]
        if not conns:  # rosbags reads every topic when given none
            return
        for k, (conn, _t, raw) in enumerate(reader.messages(connections=conns)):
            try:
                yield k, conn.topic, reader.deserialize(raw, conn.msgtype)
            except _reader_errors() as e:
                raise InputError(self.path, f"undecodable {conn.msgtype} on {conn.topic} ({_why(e)})", record=k) from None

    def _tracks(self, reader):
        odom, gt, tree = PoseTrack(), PoseTrack(), TfTree()
        base = scan_frame = None
        for _k, _topic, m in self._messages(reader, [self.scan_topic]):
            scan_frame = m.header.frame_id or None
            break
        else:
            raise InputError(self.path, f"no messages on {self.scan_topic}")
        tf_topics = [t for t, n in self.topics.items() if n in TF_TYPES]
        position = TopicCounter()
        for _k, topic, m in self._messages(reader, [t for t in (self.odom_topic, self.gt_topic, *tf_topics) if t]):
            k = position(topic)
            if topic in tf_topics:
                try:
                    tree.add_message(m, static=topic.lstrip("/") == "tf_static")
                except ValueError as e:
                    raise InputError(self.path, f"bad transform on {topic}: {e}", record=k) from None
            elif topic == self.odom_topic:
                base = base or m.child_frame_id or None
                add_pose(odom, self.path, k, topic, m.header, m.pose.pose)
            else:
                add_pose(gt, self.path, k, topic, m.header, m.pose)
        odom, mount, self.odometry_from = robot_tracks(self.path, tree, odom, self.odom_topic, scan_frame, base)
        return odom, gt, mount

    def __iter__(self):
        reader = self._open()
        try:
            if self._tracks_cache is None:
                self._tracks_cache = self._tracks(reader)
            odom, gt, mount = self._tracks_cache
            convert = ScanConverter(self.path, mount, odom, gt)
            for k, _topic, m in self._messages(reader, [self.scan_topic]):
                yield convert(k, m)
        except InputError:
            raise
        except _reader_errors() as e:
            raise InputError(self.path, f"corrupt ROS bag data ({_why(e)})") from None
        finally:
            reader.close()


# ------------------------------------------------------------------ writing
_TF_MSG_ROS1 = "geometry_msgs/TransformStamped[] transforms"


def _build(typestore, msgtype: str, value):
    """A rosbags message object of ``msgtype`` from the nested dict `McapWriter` encodes."""
    from rosbags.interfaces import Nodetype

    cls = typestore.types[msgtype]
    _, fields = typestore.fielddefs[msgtype]
    kw = {}
    for name, (kind, detail) in fields:
        v = value.get(name) if isinstance(value, dict) else None
        if kind == Nodetype.NAME:
            kw[name] = _build(typestore, detail, v or {})
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            (sub_kind, sub_detail), size = detail
            if v is None:  # a fixed-size array left out is zeros
                v = [0] * size if kind == Nodetype.ARRAY else []
            if sub_kind == Nodetype.BASE:
                kw[name] = np.asarray(v, dtype=_DTYPES[sub_detail[0]])
            else:
                kw[name] = [_build(typestore, sub_detail, x) for x in v]
        else:
            base = detail[0]
            kw[name] = ("" if base == "string" else 0) if v is None else (str(v) if base == "string" else v)
    return cls(**kw)


_DTYPES = {"float32": np.float32, "float64": np.float64, "int8": np.int8, "uint8": np.uint8, "int32": np.int32,
           "uint32": np.uint32}

ROS1, ROS2_SQLITE3, ROS2_MCAP = "ros1", "sqlite3", "mcap"


class RosbagWriter:
    """Writes scans (+ odometry, ground truth, laser mount) as a ROS 1 ``.bag`` or a ROS 2 bag folder."""

    def __init__(self, path, kind: str = ROS1, source="input"):
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.path, self.kind, self.source = Path(path), kind, source
        if kind == ROS1:
            from rosbags.rosbag1 import Writer

            self.typestore = get_typestore(Stores.ROS1_NOETIC)
            # noetic's standard store lacks tf2_msgs; its definition (and so its md5) is this one line
            self.typestore.register(get_types_from_msg(_TF_MSG_ROS1, "tf2_msgs/msg/TFMessage"))
            self._w = Writer(self.path)
        elif kind in (ROS2_SQLITE3, ROS2_MCAP):
            from rosbags.rosbag2 import StoragePlugin, Writer

            self.typestore = get_typestore(Stores.ROS2_HUMBLE)
            plugin = StoragePlugin.MCAP if kind == ROS2_MCAP else StoragePlugin.SQLITE3
            self._w = Writer(self.path, version=9, storage_plugin=plugin)
        else:
            raise UsageError(f"unknown bag kind {kind!r} (ros1, sqlite3, mcap)")
        self._w.open()
        self._conns: dict[str, object] = {}
        self._last_ns = -1

    def write(self, topic: str, type_name: str, msg: dict, sec: int, nsec: int) -> None:
        """One message (``type_name`` like ``sensor_msgs/LaserScan``, fields as a nested dict)."""
        pkg, name = type_name.split("/")
        msgtype = f"{pkg}/msg/{name}"
        if topic not in self._conns:
            kw = {"latching": 1} if self.kind == ROS1 and topic == "/tf_static" else {}
            self._conns[topic] = self._w.add_connection(topic, msgtype, typestore=self.typestore, **kw)
        obj = _build(self.typestore, msgtype, msg)
        data = (self.typestore.serialize_ros1(obj, msgtype) if self.kind == ROS1
                else self.typestore.serialize_cdr(obj, msgtype))
        self._last_ns = max(sec * 1_000_000_000 + nsec, self._last_ns + 1)
        self._w.write(self._conns[topic], self._last_ns, data)

    def write_scan(self, scan: Scan) -> None:
        from slam2d.io.mcap import ROS1_SECONDS, ROS2_SECONDS, scan_messages

        seconds = ROS1_SECONDS if self.kind == ROS1 else ROS2_SECONDS
        for topic, type_name, msg, sec, nsec in scan_messages(scan, with_mount=not self._conns, seconds=seconds,
                                                              source=self.source):
            self.write(topic, type_name, msg, sec, nsec)

    def finish(self) -> None:
        self._w.close()
