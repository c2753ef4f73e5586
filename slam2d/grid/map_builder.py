"""The map of a run: every node's range data inserted at its final pose (Hess et al. 2016, Sec. IV,
the same probability-grid insertion as submaps, at ``map.resolution``). Built once, by ``Slam.finish``."""
from __future__ import annotations

import numpy as np

from slam2d.config import SlamConfig
from slam2d.grid.probability_grid import ProbabilityGrid
from slam2d.types import Node


def build_map(cfg: SlamConfig, nodes: list[Node], poses: dict[int, np.ndarray] | None = None) -> ProbabilityGrid:
    """Insert every node's range data at its pose (``poses`` by scan index overrides the node's own).

    The map is finished as it is built (``ProbabilityGrid.build_finished``): it keeps each cell's
    probability and whether it was observed, and never holds the log-odds of the whole area at once.
    """
    grid = ProbabilityGrid.from_config(cfg.grid, resolution=cfg.map.resolution)
    if not nodes:
        return grid
    pose = np.array([poses[n.scan_index] if poses is not None else n.local_pose for n in nodes], dtype=np.float64)
    cos, sin = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    scans = []
    for n, (x, y, _), c, s in zip(nodes, pose, cos, sin):  # node by node: no copy of every point at once
        pts = np.concatenate([n.origin[None, :], n.hits, n.misses]).astype(np.float64)
        world = np.empty_like(pts)
        world[:, 0] = x + c * pts[:, 0] - s * pts[:, 1]
        world[:, 1] = y + s * pts[:, 0] + c * pts[:, 1]
        h = len(n.hits)
        scans.append((world[0], world[1:1 + h], world[1 + h:]))
    grid.build_finished(scans)  # in order, rows split among threads: equal to inserting one at a time
    return grid


__all__ = ["build_map"]
