"""slam2d: 2D LiDAR SLAM (local SLAM on log-odds submaps, loop closure in a GTSAM pose graph).

    import slam2d
    slam = slam2d.Slam()                            # or Slam(config), Slam.from_yaml(path)
    for scan in slam2d.open_source("log.clf.bz2"):  # CARMEN, MCAP; or slam2d.Scan.from_ranges(...)
        est = slam.add_scan(scan)                   # est.local_pose, est.global_pose: (x, y, θ) now
    result = slam.finish()                          # result.poses (N, 3), result.map, result.summary
    result.save("runs/x")                           # the files ``slam2d run`` writes
"""
from __future__ import annotations

import importlib
import os

# numba's OpenMP threads would otherwise spin for milliseconds after every parallel kernel, on the
# core global SLAM's worker needs (the user's own setting wins; without effect where the process
# already loaded an OpenMP runtime)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# names resolve on first use, so ``slam2d --help`` does not pay for numba and gtsam
_EXPORTS = {"Slam": "slam2d.slam", "SlamResult": "slam2d.slam", "Estimate": "slam2d.types", "Scan": "slam2d.types",
            "SlamConfig": "slam2d.config", "load_config": "slam2d.config", "open_source": "slam2d.io.source",
            "Slam2dError": "slam2d.errors"}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'slam2d' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
