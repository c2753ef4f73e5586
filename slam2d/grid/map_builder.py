"""The map of a run: every node's range data inserted at its final pose (Hess et al. 2016, Sec. IV,
the same probability-grid insertion as submaps, at ``map.resolution``). Built once, by ``Slam.finish``."""
from __future__ import annotations

import numpy as np

from slam2d.config import SlamConfig
from slam2d.grid.probability_grid import ProbabilityGrid
from slam2d.types import Node


def build_map(cfg: SlamConfig, nodes: list[Node], poses: dict[int, np.ndarray] | None = None) -> ProbabilityGrid:
    """Insert every node's range data at its pose (``poses`` by scan index overrides the node's own)."""
    grid = ProbabilityGrid.from_config(cfg.grid, resolution=cfg.map.resolution)
    if not nodes:
        return grid
    # every node's origin, hits and misses moved to its pose in one vectorized transform
    parts = [np.concatenate([n.origin[None, :], n.hits, n.misses]) for n in nodes]
    sizes = np.array([len(p) for p in parts])
    pts = np.concatenate(parts).astype(np.float64)
    pose = np.array([poses[n.scan_index] if poses is not None else n.local_pose for n in nodes], dtype=np.float64)
    per_point = np.repeat(pose, sizes, axis=0)
    c, s = np.cos(per_point[:, 2]), np.sin(per_point[:, 2])
    world = np.empty_like(pts)
    world[:, 0] = per_point[:, 0] + c * pts[:, 0] - s * pts[:, 1]
    world[:, 1] = per_point[:, 1] + s * pts[:, 0] + c * pts[:, 1]
    scans, at = [], 0
    for n, size in zip(nodes, sizes):
        h = len(n.hits)
        scans.append((world[at], world[at + 1:at + 1 + h], world[at + 1 + h:at + size]))
        at += size
    grid.insert_scans(scans)  # in order, rows split among threads: equal to inserting one at a time
    return grid


__all__ = ["build_map"]
