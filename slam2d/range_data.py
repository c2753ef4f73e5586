"""From a `Scan` to range data in the tracking (robot) frame: hits and free-space ray ends.

Cartographer's ``RangeData`` (origin, returns, misses) after its range filter: hits
farther than ``max_range`` become misses cut at ``max_range``; no-return beams become
misses of length ``missing_data_ray_length``, never longer than the sensor's own range (a
no-return says nothing lies within it; beyond, the space is unknown); NaN/invalid readings are
dropped.

Unlike Cartographer, a no-return beam between two returns from one surface (their end points
at most ``SAME_SURFACE_GAP`` apart) is cut at the nearer of them: a laser gets no echo from
dark, glossy or transparent patches of a wall as well as from open space, and a free ray
through such a patch marks what lies behind the wall free: the next room, whose walls are then
weak in the submap when the robot gets there (``_kernels.scan_to_range_data``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam2d import _kernels
from slam2d.config import RangeFilterConfig
from slam2d.geometry import transform_points
from slam2d.types import Scan

#: two returns whose end points lie at most this far apart [m] are taken to lie on one surface
SAME_SURFACE_GAP = 1.0


@dataclass
class RangeData:
    origin: np.ndarray  # (2,) laser position in the tracking frame
    hits: np.ndarray    # (N, 2) tracking frame
    misses: np.ndarray  # (M, 2) tracking frame, ends of free-space rays
    far: int = 0        # the first ``far`` misses are returns beyond max_range (cut there), the rest no-returns

    def transformed(self, pose) -> "RangeData":
        n = len(self.hits)
        pts = transform_points(pose, np.concatenate([self.origin[None, :], self.hits, self.misses]))
        return RangeData(pts[0], pts[1:n + 1], pts[n + 1:], self.far)


def range_data(scan: Scan, cfg: RangeFilterConfig) -> RangeData:
    n = scan.num_beams
    hits = np.empty((n, 2))
    misses = np.empty((n, 2))
    no_ret = scan.no_return if scan.no_return is not None else np.zeros(n, dtype=np.bool_)
    off = scan.laser_offset
    # a no-return says nothing lies within the sensor's range: beyond it the space is unknown
    sensor = scan.range_max if scan.range_max > 0 else math.inf
    miss_len = min(cfg.missing_data_ray_length, cfg.max_range, sensor) if cfg.missing_data_ray_length > 0 else 0.0
    min_range = float(max(cfg.min_range, scan.range_min))
    nh, nm, far = _kernels.scan_to_range_data(scan.ranges, scan.valid, no_ret, float(scan.angle_min),
                                              float(scan.angle_increment), min_range, float(cfg.max_range),
                                              float(miss_len), float(off[0]), float(off[1]), float(off[2]),
                                              hits, misses, SAME_SURFACE_GAP)
    return RangeData(np.array([float(off[0]), float(off[1])]), hits[:nh], misses[:nm], int(far))


def voxel_filter(points: np.ndarray, size: float) -> np.ndarray:
    """One point per square cell of ``size`` (the first in input order), like Cartographer's voxel filter."""
    return points[voxel_filter_index(points, size)]


def voxel_filter_index(points: np.ndarray, size: float) -> np.ndarray:
    """The indices (increasing) of the points ``voxel_filter`` keeps."""
    if size <= 0 or len(points) == 0:
        return np.arange(len(points))
    return _kernels.voxel_filter_indices(points, float(size))


def adaptive_voxel_filter(points: np.ndarray, min_points: int, max_length: float) -> np.ndarray:
    """Cartographer's adaptive voxel filter: the coarsest voxel filter, up to ``max_length``, that still
    keeps ``min_points`` points (bisection on the cell size, in ``_kernels.adaptive_voxel_indices``); a
    cloud of at most ``min_points`` points is returned as it is (so is every cloud when ``min_points``
    is 0). Matching costs time in proportion to the points."""
    if min_points <= 0 or len(points) <= min_points:
        return points
    return points[_kernels.adaptive_voxel_indices(points, int(min_points), float(max_length))]
