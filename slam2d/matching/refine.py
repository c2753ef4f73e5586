"""Continuous refinement below cell size: Cartographer's Ceres scan matcher cost (Hess et al. 2016, Sec. IV, eq. CS),
solved by Levenberg-Marquardt in a numba kernel on a Catmull-Rom bicubic interpolation of the probability grid.

The cost pulls every point toward high probability and the pose toward the correlative
result (translation and rotation weights), which keeps the solution inside the basin the
correlative search found. It runs on the probability grid, not on the likelihood field:
the field is flat across a wall's width (every cell of a thick wall is "occupied"), which
leaves no gradient below cell size (tests/test_matchers.py shows the refinement halving the
error on the probability grid). Its cost per scan is the ``refine`` timing in summary.json and BENCHMARKS.md.
"""
from __future__ import annotations

import numpy as np

from slam2d.matching import _kernels
from slam2d.matching.search import MatchGrid


def refine(grid: MatchGrid, initial, points: np.ndarray, occupied_weight=1.0, translation_weight=10.0,
           rotation_weight=40.0, max_iterations=20) -> tuple[np.ndarray, float]:
    """(refined pose, final cost)."""
    x, y, t, cost, _ = _kernels.refine_pose(grid.values, float(grid.origin[0]), float(grid.origin[1]),
                                            float(grid.resolution), float(grid.unknown),
                                            np.ascontiguousarray(points, dtype=np.float64),
                                            float(initial[0]), float(initial[1]), float(initial[2]),
                                            float(occupied_weight), float(translation_weight),
                                            float(rotation_weight), int(max_iterations), float(grid.scale),
                                            _kernels.ALL_KNOWN if grid.known is None else grid.known)
    return np.array([x, y, t]), float(cost)
