"""``slam2d info`` and the run's ``summary.json``."""
from __future__ import annotations

import math
import platform
from pathlib import Path

import numpy as np

from slam2d.allocator import peak_rss_mb as _peak_rss_mb
from slam2d.errors import InputError


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("slam2d")
    except PackageNotFoundError:
        return "unknown"


def describe(source, usable_range: float | None = None) -> dict:
    """One streaming pass over the scans. ``usable_range``: ``range_filter.max_range`` (default:
    the default config's); returns beyond it are inserted as free space, not as hits."""
    if usable_range is None:
        from slam2d.config import RangeFilterConfig

        usable_range = RangeFilterConfig().max_range
    usable = float(usable_range)
    beyond = 0
    n = 0
    t_min, t_max = math.inf, -math.inf
    beams = set()
    a_min, a_max = math.inf, -math.inf
    r_min, r_max = math.inf, -math.inf
    hit_max = 0.0
    invalid = no_ret = nan = readings = reversals = with_odom = with_gt = 0
    odom_pairs = odom_changes = 0  # consecutive scans with odometry, and those whose readings differ
    last = last_odom = None
    offset = None
    for s in source:
        n += 1
        t_min, t_max = min(t_min, s.timestamp), max(t_max, s.timestamp)
        if last is not None and s.timestamp < last:
            reversals += 1
        last = s.timestamp
        beams.add(s.num_beams)
        a_min = min(a_min, s.angle_min)
        a_max = max(a_max, s.angle_min + (s.num_beams - 1) * s.angle_increment)
        r_min, r_max = min(r_min, s.range_min), max(r_max, s.range_max)
        readings += s.num_beams
        invalid += int(s.num_beams - np.count_nonzero(s.valid))
        nan += int(np.count_nonzero(np.isnan(s.ranges)))
        if s.valid.any():
            hit_max = max(hit_max, float(s.ranges[s.valid].max()))
            beyond += int(np.count_nonzero(s.ranges[s.valid] > usable))
        if s.no_return is not None:
            no_ret += int(np.count_nonzero(s.no_return))
        with_odom += s.odom_pose is not None
        if s.odom_pose is not None:
            if last_odom is not None:
                odom_pairs += 1
                odom_changes += not np.array_equal(s.odom_pose, last_odom)
            last_odom = s.odom_pose
        with_gt += s.ground_truth is not None
        offset = s.laser_offset
    if n == 0:
        raise InputError(getattr(source, "path", "input"), "no scans")
    return {
        "scans": n,
        "duration_s": round(t_max - t_min, 6),
        "first_timestamp": t_min,
        "last_timestamp": t_max,
        "beams": sorted(beams)[0] if len(beams) == 1 else sorted(beams),
        "angle_min_deg": round(math.degrees(a_min), 4),
        "angle_max_deg": round(math.degrees(a_max), 4),
        "range_min_m": r_min,
        "range_max_m": r_max,
        "max_hit_range_m": round(hit_max, 4),
        "usable_range_m": usable,
        "returns_beyond_usable_range": beyond,
        "readings": readings,
        "invalid_readings": invalid,
        "no_return_readings": no_ret,
        "nan_readings": nan,
        "has_odometry": with_odom == n,
        # the share of consecutive scans whose odometry readings differ: 0 is an odometry that carries
        # no motion (local SLAM sets a stalled stream aside, ``LocalSlam._odometry_reading``)
        "odometry_changes_between_scans": round(odom_changes / odom_pairs, 4) if odom_pairs else None,
        "has_ground_truth": with_gt == n,
        "laser_offset": [round(float(v), 6) for v in offset] if offset is not None else None,
        "timestamp_reversals": reversals,
    }


def peak_rss_mb() -> float:
    """The process's own peak resident memory [MB] (``allocator.peak_rss_mb``), to 0.1 MB."""
    return round(_peak_rss_mb(), 1)


def run_summary(input_path, mode, times: np.ndarray, counts: dict, timings: dict, map_s: float, tracker) -> dict:
    """The head of ``summary.json``; ``Slam.finish`` adds wall time, global SLAM and health."""
    duration = float(times.max() - times.min()) if len(times) > 1 else 0.0
    s = {
        "slam2d_version": _version(),
        "python": platform.python_version(),
        "input": str(input_path),
        # the same, absolute: what `slam2d eval` reads the run's scans from, whatever folder it runs in
        "input_absolute": str(Path(input_path).resolve()) if Path(str(input_path)).exists() else None,
        "mode": mode,
        "scans": int(len(times)),
        "duration_s": round(duration, 6),
        "wall_time_s": None,
        "real_time_factor": None,
        "peak_rss_mb": peak_rss_mb(),
        "counts": counts,
        "timings": {**timings, "map_build_s": round(map_s, 3)},
    }
    extra = getattr(tracker, "summary", None)
    if callable(extra):
        s.update(extra())
    return s
