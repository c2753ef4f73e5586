"""``--odometry-only`` / ``Slam(mode="odometry")``: the wheel odometry is the pose, scans only build the map."""
from __future__ import annotations

import numpy as np

from slam2d.config import SlamConfig
from slam2d.errors import InputError
from slam2d.motion_filter import MotionFilter
from slam2d.range_data import range_data
from slam2d.types import MatchingResult


class OdometryTracker:
    """The local pose is the wheel odometry pose; the motion filter picks nodes."""

    name = "odometry"

    def __init__(self, cfg: SlamConfig, source_path="input"):
        self.cfg = cfg
        self.source_path = source_path
        self.filter = MotionFilter(cfg.motion_filter)

    def add_scan(self, scan) -> MatchingResult:
        if scan.odom_pose is None:
            raise InputError(self.source_path, "scan has no odometry; run without --odometry-only", record=scan.index)
        rd = range_data(scan, self.cfg.range_filter)
        pose = np.asarray(scan.odom_pose, dtype=float)
        inserted = not self.filter.is_similar(scan.timestamp, pose)
        return MatchingResult(scan.timestamp, pose, rd, inserted)


__all__ = ["OdometryTracker"]
