"""Records that flow through the pipeline."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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
