"""Motion filter (Cartographer's ``MotionFilter``): pass a pose when the robot moved, turned or waited enough.

One addition to Cartographer's rule: with wheel odometry, the odometry's own travel since the
last passed scan counts as well, so a scan passes when either its matched pose or the
odometry says the robot moved. Judged on the matched pose alone, the filter can be trapped:
a match that slides back onto the mapped part of the submap while the robot drives into
unmapped ground (a short-range scanner in a corridor, where the points ahead fall on cells
not yet observed and score nothing) stays within ``max_distance`` of the last passed pose,
so nothing is inserted, the map never reaches the new ground, and the slide goes on. With the
odometry's travel counted, the scan is inserted after ``max_distance`` of driving and the
following scans match against the new ground. The odometry's rotation is not counted: the
scan constrains heading well, and heading is where wheel odometry is weakest.
"""
from __future__ import annotations

import math

import numpy as np

from slam2d.config import MotionFilterConfig
from slam2d.geometry import between


class MotionFilter:
    def __init__(self, cfg: MotionFilterConfig):
        self.cfg = cfg
        self.last_time: float | None = None
        self.last_pose: np.ndarray | None = None
        self.last_odom: np.ndarray | None = None

    def is_similar(self, time: float, pose, odom=None) -> bool:
        """True when the pose is too close to the last passed one (and then it is dropped).
        ``odom``: the scan's wheel odometry pose, if any; the odometry's travel since the last
        passed scan's must be within ``max_distance`` too."""
        if self.last_pose is not None:
            d = between(self.last_pose, pose)
            if (abs(time - self.last_time) <= self.cfg.max_time and math.hypot(d[0], d[1]) <= self.cfg.max_distance
                    and abs(d[2]) <= math.radians(self.cfg.max_angle_deg)
                    and (odom is None or self.last_odom is None or self._odometry_travel(odom) <= self.cfg.max_distance)):
                return True
        self.last_time, self.last_pose = time, np.asarray(pose, dtype=float).copy()
        self.last_odom = None if odom is None else np.asarray(odom, dtype=float).copy()
        return False

    def _odometry_travel(self, odom) -> float:
        """How far the wheel odometry moved since the last passed scan [m]."""
        return math.hypot(odom[0] - self.last_odom[0], odom[1] - self.last_odom[1])
