"""Submaps (Hess et al. 2016, Sec. III-B/IV): two active, overlapping log-odds grids.

A new submap starts every ``num_range_data`` insertions; each scan goes into both active
submaps; the older one is finished (frozen) after ``2 × num_range_data`` insertions, as in
Cartographer's ``ActiveSubmaps2D``. Local matching uses the older active submap, which
always holds more data. A submap's grid is axis-aligned in the local frame; its
``local_pose`` is the tracking pose of the scan that started it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slam2d.grid.probability_grid import ProbabilityGrid, insert_scan
from slam2d.matching.search import MatchGrid


@dataclass
class Submap:
    index: int
    local_pose: np.ndarray
    grid: ProbabilityGrid
    num_range_data: int = 0
    finished: bool = False
    node_indices: list = field(default_factory=list)

    def match_grid(self) -> MatchGrid:
        """The grid scans are scored against: the likelihood field when the submap keeps one, else probabilities."""
        g = self.grid
        if g.field_sigma:
            return MatchGrid(g.field, g.origin, g.resolution, 0.0)
        return self.probability_grid()

    def probability_grid(self) -> MatchGrid:
        """Hit probabilities (unknown cells at the minimum probability), for sub-cell refinement."""
        g = self.grid
        return MatchGrid(g.prob, g.origin, g.resolution, g.unknown_probability)

    def finish(self):
        """Freeze: crop to the observed cells and drop the insertion buffers."""
        self.finished = True
        g = self.grid
        b = g.known_bounds()
        if b is not None:
            g.freeze(*b)


class ActiveSubmaps:
    def __init__(self, grid_cfg, num_range_data: int, field_sigma: float | None = None):
        self.grid_cfg = grid_cfg
        self.field_sigma = field_sigma
        self.num_range_data = num_range_data
        self.submaps: list[Submap] = []  # active ones, oldest first
        self.count = 0

    def insert(self, local_pose, origin, hits, misses, node_index: int) -> list[Submap]:
        """Insert range data (local frame) into the active submaps; returns submaps finished by it."""
        if not self.submaps or self.submaps[-1].num_range_data == self.num_range_data:
            self._add(local_pose)
        finished = []
        self.last_inserted_into = [(s.index, s.local_pose) for s in self.submaps]
        insert_scan([s.grid for s in self.submaps], origin, hits, misses)
        for s in self.submaps:
            s.num_range_data += 1
            s.node_indices.append(node_index)
        if self.submaps[0].num_range_data == 2 * self.num_range_data:
            old = self.submaps.pop(0)
            old.finish()
            finished.append(old)
        return finished

    def _add(self, local_pose):
        grid = ProbabilityGrid.from_config(self.grid_cfg, field_sigma=self.field_sigma)
        self.submaps.append(Submap(self.count, np.asarray(local_pose, dtype=float).copy(), grid))
        self.count += 1

    @property
    def matching_submap(self) -> Submap | None:
        return self.submaps[0] if self.submaps else None
