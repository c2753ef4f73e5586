"""Motion filter (Cartographer's ``MotionFilter``): pass a pose when the robot moved, turned or waited enough."""
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

    def is_similar(self, time: float, pose) -> bool:
        """True when the pose is too close to the last passed one (and then it is dropped)."""
        if self.last_pose is not None:
            d = between(self.last_pose, pose)
            if (abs(time - self.last_time) <= self.cfg.max_time and math.hypot(d[0], d[1]) <= self.cfg.max_distance
                    and abs(d[2]) <= math.radians(self.cfg.max_angle_deg)):
                return True
        self.last_time, self.last_pose = time, np.asarray(pose, dtype=float).copy()
        return False
