"""Records that flow through the pipeline."""
from __future__ import annotations

from dataclasses import dataclass, field

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from slam2d.range_data import RangeData


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
        r = np.asarray(ranges, dtype=np.float32).reshape(-1)
        with np.errstate(invalid="ignore"):
            no_return = np.isposinf(r) | (r > range_max)
            valid = np.isfinite(r) & (r >= range_min) & (r <= range_max) & (r > 0)
        return cls(timestamp=float(time), ranges=r, angle_min=float(angle_min), angle_increment=float(angle_increment),
                   range_min=float(range_min), range_max=float(range_max), valid=valid, no_return=no_return,
                   intensities=None if intensities is None else np.asarray(intensities, dtype=np.float32),
                   odom_pose=None if odom_pose is None else np.asarray(odom_pose, dtype=float).reshape(3),
                   laser_offset=np.zeros(3) if laser_offset is None else np.asarray(laser_offset, dtype=float).reshape(3),
                   **fields)


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

