"""From a `Scan` to range data in the tracking (robot) frame: hits and free-space ray ends.

Cartographer's ``RangeData`` (origin, returns, misses) after its range filter: hits
farther than ``max_range`` become misses cut at ``max_range``; no-return beams become
misses of length ``missing_data_ray_length``; NaN/invalid readings are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam2d.config import RangeFilterConfig
from slam2d.geometry import transform_points
from slam2d.types import Scan


@dataclass
class RangeData:
    origin: np.ndarray  # (2,) laser position in the tracking frame
    hits: np.ndarray    # (N, 2) tracking frame
    misses: np.ndarray  # (M, 2) tracking frame, ends of free-space rays

    def transformed(self, pose) -> "RangeData":
        o = transform_points(pose, self.origin[None, :])[0]
        return RangeData(o, transform_points(pose, self.hits), transform_points(pose, self.misses))


def range_data(scan: Scan, cfg: RangeFilterConfig) -> RangeData:
    r = scan.ranges.astype(np.float64)
    a = scan.angles
    min_r = max(cfg.min_range, scan.range_min)
    valid = scan.valid & (r >= min_r)
    hit = valid & (r <= cfg.max_range)
    far = valid & (r > cfg.max_range)
    no_ret = scan.no_return if scan.no_return is not None else np.zeros_like(valid)
    c, s = np.cos(a), np.sin(a)
    hits = np.stack([r[hit] * c[hit], r[hit] * s[hit]], axis=1)
    parts = [np.stack([cfg.max_range * c[far], cfg.max_range * s[far]], axis=1)]
    if cfg.missing_data_ray_length > 0:
        L = min(cfg.missing_data_ray_length, cfg.max_range)
        parts.append(np.stack([L * c[no_ret], L * s[no_ret]], axis=1))
    misses = np.vstack(parts)
    off = scan.laser_offset
    return RangeData(np.array(off[:2], dtype=float), transform_points(off, hits), transform_points(off, misses))


def voxel_filter(points: np.ndarray, size: float) -> np.ndarray:
    """One point per square cell of ``size`` (the first in input order), like Cartographer's voxel filter."""
    if size <= 0 or len(points) == 0:
        return points
    k = np.floor(points / size).astype(np.int64)
    keys = (k[:, 0] << 32) ^ (k[:, 1] & 0xFFFFFFFF)
    _, idx = np.unique(keys, return_index=True)
    return points[np.sort(idx)]
