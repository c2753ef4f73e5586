"""Records that flow through the pipeline."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from slam2d.range_data import RangeData


#: a scan stamped earlier than the latest one before it by up to this much [s] is tolerated (the Intel
#: log has such reorderings, up to 0.9 s); by more, it is an error (every reader, and ``Slam.add_scan``)
MAX_TIME_REVERSAL = 1.0
#: a scan stamped this much [s] after the latest one is warned about, once: a broken stamp, or two logs in one
MAX_TIME_GAP = 3600.0


def _bad(where: str, message: str):
    from slam2d.errors import UsageError

    raise UsageError(f"{where}: {message}")


@dataclass
class Scan:
    """One 2D laser scan as the source gave it.

    ``timestamp`` is the source's own clock (CARMEN ``ipc_ts``, ROS header stamp).
    ``valid`` is False for readings that are not hits: no-returns (at or beyond the
    sensor's maximum / no-return value), NaN, below ``range_min``.
    ``odom_pose`` is the robot's odometry pose at the scan time, when the source has one;
    ``laser_offset`` is the pose of the laser in the robot (tracking) frame.
    """

    timestamp: float
    ranges: np.ndarray  # float32 (N,)
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    valid: np.ndarray  # bool (N,)
    index: int = 0
    intensities: np.ndarray | None = None
    odom_pose: np.ndarray | None = None
    laser_offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ground_truth: np.ndarray | None = None
    timestamp_text: str | None = None  # the timestamp exactly as the source wrote it
    no_return: np.ndarray | None = None  # bool (N,): beams that saw nothing (max range / inf)

    @property
    def num_beams(self) -> int:
        return int(self.ranges.shape[0])

    @property
    def stamp_text(self) -> str:
        """The timestamp as the source wrote it, else the shortest decimal that reads back as it
        (1700000000.2, not 1700000000.200000048)."""
        return self.timestamp_text or np.format_float_positional(self.timestamp, unique=True, trim="0")

    def check(self, where: str = "scan") -> None:
        """Raise a UsageError naming the field when the scan cannot be mapped: a stamp, angle or pose that
        is not a finite number, ranges that are not one non-empty row of floats, arrays of another
        length than ``ranges``, a zero angle step, beams spanning more than a full turn, a range_max
        that is not positive or not above range_min. (``Slam.add_scan`` checks every scan, so a call
        that fails changes nothing; plain-float checks: it runs on every scan.)"""
        r = self.ranges
        if not (isinstance(r, np.ndarray) and r.ndim == 1 and r.size and r.dtype.kind == "f"):
            _bad(where, "ranges must be a non-empty 1-D array of floats, not " + (
                f"an array of shape {r.shape} and dtype {r.dtype}" if isinstance(r, np.ndarray) else type(r).__name__))
        for name in ("timestamp", "angle_min", "angle_increment", "range_min"):
            v = getattr(self, name)
            try:
                ok = math.isfinite(v)
            except TypeError:
                ok = False
            if not ok:
                _bad(where, f"{name} must be a finite number, not {v!r}")
        if self.angle_increment == 0:
            _bad(where, "angle_increment must not be 0")
        if abs(self.angle_increment) * (r.size - 1) > 2 * math.pi * 1.001:  # slack: printed resolutions (carmen.py)
            _bad(where, f"{r.size} beams {self.angle_increment:g} rad apart span "
                 f"{math.degrees(abs(self.angle_increment) * (r.size - 1)):.0f}°, more than a full turn "
                 "(angle_increment in degrees?)")
        if not self.range_max > 0:
            _bad(where, f"range_max must be positive, not {self.range_max!r}")
        if not self.range_min < self.range_max:
            _bad(where, f"range_min {self.range_min!r} must be below range_max {self.range_max!r}")
        for name in ("valid", "no_return", "intensities"):
            a = getattr(self, name)
            if a is not None and (a.shape if isinstance(a, np.ndarray) else np.shape(a)) != r.shape:
                _bad(where, f"{name} has shape {np.shape(a)}, ranges {r.shape}")
        for name in ("odom_pose", "laser_offset", "ground_truth"):
            v = getattr(self, name)
            if v is None and name != "laser_offset":
                continue
            try:
                ok = len(v) == 3 and all(math.isfinite(c) and abs(c) <= 1e9 for c in v)
            except TypeError:
                ok = False
            if not ok:
                _bad(where, f"{name} must be (x, y, θ), three finite numbers, not {v!r}")

    @property
    def angles(self) -> np.ndarray:
        return self.angle_min + self.angle_increment * np.arange(self.num_beams)

    def points(self, max_range: float | None = None) -> np.ndarray:
        """Valid hits as (M, 2) points in the laser frame."""
        mask = self.valid
        if max_range is not None:
            mask = mask & (self.ranges <= max_range)
        r = self.ranges[mask].astype(float)
        a = self.angles[mask]
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)

    @classmethod
    def from_ranges(cls, time: float, ranges, angle_min: float, angle_increment: float, range_max: float,
                    odom_pose=None, range_min: float = 0.0, laser_offset=None, intensities=None, **fields) -> "Scan":
        """A scan from a range array as ``sensor_msgs/LaserScan`` carries it (REP 117): a reading is a
        hit when it is finite, positive and within [range_min, range_max]; +inf or above range_max is a
        no-return (free space up to ``range_filter.missing_data_ray_length``, never a hit); NaN and
        readings below range_min are neither. ``odom_pose``: the robot's odometry (x, y, θ) at
        ``time``, if any; ``laser_offset``: the laser's pose in the robot frame; ``fields``: any
        other ``Scan`` field (``index``, ``timestamp_text``, ``ground_truth``)."""
        from slam2d.errors import UsageError

        try:
            r = np.asarray(ranges, dtype=np.float32)
        except (TypeError, ValueError):
            raise UsageError(f"Scan.from_ranges: ranges must be numbers, not {type(ranges).__name__}") from None
        if r.ndim != 1:
            raise UsageError(f"Scan.from_ranges: ranges must be one row of readings, not an array of shape {r.shape}")
        if intensities is not None and np.shape(intensities) != r.shape:
            raise UsageError(f"Scan.from_ranges: intensities has shape {np.shape(intensities)}, ranges {r.shape}")

        def pose(v, name):
            if v is None:
                return None
            try:
                return np.asarray(v, dtype=float).reshape(3)
            except (TypeError, ValueError):
                raise UsageError(f"Scan.from_ranges: {name} must be (x, y, θ), not {v!r}") from None

        def number(v, name):
            if isinstance(v, (bool, str, bytes)) or v is None:
                raise UsageError(f"Scan.from_ranges: {name} must be a number, not {v!r}")
            try:
                return float(v)
            except (TypeError, ValueError):
                raise UsageError(f"Scan.from_ranges: {name} must be a number, not {v!r}") from None

        time, angle_min, angle_increment, range_max, range_min = (
            number(time, "time"), number(angle_min, "angle_min"), number(angle_increment, "angle_increment"),
            number(range_max, "range_max"), number(range_min, "range_min"))
        with np.errstate(invalid="ignore"):
            negative = np.flatnonzero(np.isfinite(r) & (r < 0))  # -inf is REP 117's "too close"
        if negative.size:
            raise UsageError(f"Scan.from_ranges: negative range reading {float(r[negative[0]]):g} at beam {negative[0]}")
        with np.errstate(invalid="ignore"):
            no_return = np.isposinf(r) | (r > range_max)
            valid = np.isfinite(r) & (r >= range_min) & (r <= range_max) & (r > 0)
        scan = cls(timestamp=time, ranges=r, angle_min=angle_min, angle_increment=angle_increment, range_min=range_min,
                   range_max=range_max, valid=valid, no_return=no_return,
                   intensities=None if intensities is None else np.asarray(intensities, dtype=np.float32),
                   odom_pose=pose(odom_pose, "odom_pose"),
                   laser_offset=np.zeros(3) if laser_offset is None else pose(laser_offset, "laser_offset"), **fields)
        scan.check("Scan.from_ranges")
        return scan


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
    point_index: np.ndarray | None = None  # points == range_data.hits[point_index], when known
    quality: str = "unmatched"            # trusted | weak | forced | untrusted | unmatched
    #: how far (m, rad) the pose may be off beyond the drift model, from the steps since the last
    #: inserted scan that local SLAM could not vouch for (``LocalSlam._step_doubt``; sizes global SLAM's windows)
    doubt: tuple = (0.0, 0.0)
    #: the pose a recovered match replaced (the real-time window's match, or the prediction), else None
    replaced: np.ndarray | None = None
    #: local SLAM lost track before this scan and started new submaps with it (``ActiveSubmaps.insert``)
    fresh_start: bool = False

    @property
    def covariance(self) -> np.ndarray | None:
        """Covariance of the local match (Olson 2009, Sec. IV), computed on demand: only global SLAM uses it."""
        return None if self.match is None else self.match.covariance


@dataclass
class Node:
    """A scan kept by the motion filter: its local pose and range data (tracking frame, float32)."""

    scan_index: int
    time: float
    local_pose: np.ndarray
    hits: np.ndarray
    misses: np.ndarray
    origin: np.ndarray
    far_misses: int = 0  # the first ``far_misses`` misses are returns beyond max_range, the rest no-returns

    @classmethod
    def of(cls, scan_index: int, time: float, pose, rd) -> "Node":
        """The node of a scan at ``pose`` with its ``range_data.RangeData`` ``rd`` (kept as float32)."""
        return cls(scan_index, time, np.array(pose, dtype=float), rd.hits.astype(np.float32),
                   rd.misses.astype(np.float32), rd.origin.astype(np.float32), rd.far)


@dataclass
class Estimate:
    """What ``Slam.add_scan`` knows about a scan the moment it returns.

    ``local_pose``: local SLAM's pose (the odometry's with ``mode="odometry"``), continuous but
    drifting; ``global_pose``: the best estimate in the map frame now, i.e. the local pose moved by
    the pose graph's latest correction (equal to the local pose without global SLAM). Later loop
    closures move it; ``Slam.finish`` gives every scan's final pose. Poses are (x, y, θ), θ in (−π, π].
    """

    index: int
    time: float
    local_pose: np.ndarray
    global_pose: np.ndarray
    inserted: bool
    quality: str


@dataclass
class LoopFactor:
    """A loop-closure constraint in the pose graph: node ``node`` seen from submap node ``anchor``."""

    index: int          # its id in the graph that holds it
    anchor: int         # the submap node it is tied to
    node: int
    relative: np.ndarray
    record: dict        # the constraints.jsonl record, updated with the outcome
    base: object = None  # its Gaussian noise model before the robust wrapper (in-process graphs only)
    heading_only: bool = False  # a heading constraint: its translation carries no information

