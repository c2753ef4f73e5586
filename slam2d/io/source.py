"""``open_source(path)``: the right reader for a file, chosen by its name."""
from __future__ import annotations

from pathlib import Path

from slam2d.errors import InputError

CARMEN_SUFFIXES = (".clf", ".log", ".carmen")
COMPRESSION = (".gz", ".bz2")


def source_kind(path: str | Path) -> str:
    name = Path(path).name.lower()
    for c in COMPRESSION:
        if name.endswith(c):
            name = name[: -len(c)]
            break
    if name.endswith(".mcap"):
        if name != Path(path).name.lower():
            raise InputError(path, "compressed MCAP is not supported (MCAP compresses its own chunks); decompress it first")
        return "mcap"
    if name.endswith(CARMEN_SUFFIXES):
        return "carmen"
    raise InputError(path, "unknown file type: expected a CARMEN log (.clf, .log, optionally .gz/.bz2) or an MCAP file (.mcap)")


def open_source(path: str | Path, scan_topic: str | None = None, odom_topic: str | None = None):
    """An iterable of `Scan` for a log file (lazy; errors name the file and line or record)."""
    kind = source_kind(path)
    if not Path(path).exists():
        raise InputError(path, "no such file")
    if kind == "mcap":
        from slam2d.io.mcap import McapLog

        return McapLog(path, scan_topic=scan_topic, odom_topic=odom_topic)
    if scan_topic or odom_topic:
        raise InputError(path, "--scan-topic/--odom-topic apply to MCAP input only")
    from slam2d.io.carmen import CarmenLog

    return CarmenLog(path)
