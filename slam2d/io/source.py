"""``open_source(path)``: the right reader for a log, chosen by its name.

CARMEN logs (``.clf``/``.log``/``.carmen``, plain or ``.gz``/``.bz2``) → `slam2d.io.carmen`;
``.mcap`` (a plain MCAP or the storage file of a ROS 2 bag) → `slam2d.io.mcap`; a ROS 1
``.bag``, a ROS 2 bag folder (with ``metadata.yaml``) or its ``.db3`` → `slam2d.io.rosbag`.
"""
from __future__ import annotations

from pathlib import Path

from slam2d.errors import InputError

CARMEN_SUFFIXES = (".clf", ".log", ".carmen")
COMPRESSION = (".gz", ".bz2")
KNOWN = ("expected a CARMEN log (.clf, .log, optionally .gz/.bz2), an MCAP file (.mcap), a ROS 1 bag (.bag) "
         "or a ROS 2 bag (its folder with metadata.yaml, or its .db3/.mcap file)")


#: what a file's first bytes say it is, whatever its name
MAGIC = {b"\x89MCAP0\r\n": ("an MCAP file", ".mcap"), b"#ROSBAG V2.0": ("a ROS 1 bag", ".bag"),
         b"SQLite format 3": ("an SQLite file (a ROS 2 bag's .db3)", ".db3")}


def _content_kind(path: Path) -> tuple[str, str] | None:
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError:
        return None
    return next((v for magic, v in MAGIC.items() if head.startswith(magic)), None)


def source_kind(path: str | Path) -> str:
    """``carmen``, ``mcap`` or ``rosbag``; a file whose first bytes say it is another kind than its name
    says is an error that names both."""
    kind = _kind_by_name(path)
    p = Path(path)
    if p.is_file():
        content = _content_kind(p)
        named = p.name.lower()
        if content is not None and not named.endswith(content[1]):
            raise InputError(path, f"this file is {content[0]} (its first bytes say so), not what its name says: "
                             f"name it *{content[1]}")
    return kind


def _kind_by_name(path: str | Path) -> str:
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").exists():
            return "rosbag"
        raise InputError(path, f"a folder without metadata.yaml is not a ROS 2 bag; {KNOWN}")
    name = p.name.lower()
    for c in COMPRESSION:
        if name.endswith(c):
            name = name[: -len(c)]
            break
    if name.endswith((".mcap", ".bag", ".db3")) and name != p.name.lower():
        raise InputError(path, "compressed bags are not supported (bags compress their own chunks); decompress it first")
    if name.endswith(".mcap"):
        return "mcap"
    if name.endswith(".bag"):
        return "rosbag"
    if name.endswith(".db3"):
        if not (p.parent / "metadata.yaml").exists():
            raise InputError(path, "a .db3 file is read with its bag's metadata.yaml, which is not beside it")
        return "rosbag"
    if name.endswith(CARMEN_SUFFIXES):
        return "carmen"
    raise InputError(path, f"unknown file type: {KNOWN}")


def open_source(path: str | Path, scan_topic: str | None = None, odom_topic: str | None = None,
                scan_period: float | None = None):
    """An iterable of `Scan` for a log (lazy; errors name the file and line or record). ``scan_period``:
    a CARMEN log's scans stamped that many seconds apart in file order, its own timestamps ignored."""
    if not Path(path).exists():
        raise InputError(path, "no such file")
    kind = source_kind(path)
    if scan_period is not None and kind != "carmen":
        raise InputError(path, "--scan-period applies to CARMEN logs only (ROS input matches odometry and TF to "
                         "scans by their stamps)")
    if kind == "mcap":
        from slam2d.io.mcap import McapLog

        return McapLog(path, scan_topic=scan_topic, odom_topic=odom_topic)
    if kind == "rosbag":
        from slam2d.io.rosbag import RosbagLog

        return RosbagLog(path, scan_topic=scan_topic, odom_topic=odom_topic)
    if scan_topic or odom_topic:
        raise InputError(path, "--scan-topic/--odom-topic apply to ROS input (MCAP, bags) only")
    from slam2d.io.carmen import CarmenLog

    return CarmenLog(path, scan_period=scan_period)
