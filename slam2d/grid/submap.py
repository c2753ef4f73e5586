"""Submaps (Hess et al. 2016, Sec. III-B/IV): two active, overlapping log-odds grids.

A new submap starts every ``num_range_data`` insertions; each scan goes into both active
submaps; the older one is finished (frozen) after ``2 × num_range_data`` insertions, as in
Cartographer's ``ActiveSubmaps2D``. A count alone ties a submap's extent to the scan rate:
a sparse log (scans a metre apart) would grow submaps five times the size of a dense one,
with five times the drift inside and the memory. So a submap is also full once the robot
travelled ``max_travel`` metres since it started (path length of the inserted poses). Local matching uses the older active submap, which
always holds more data; the newer one takes its scans in one batch when it becomes the older
(``ActiveSubmaps``), since nothing reads it before. A submap's grid is axis-aligned in the local frame; its
``local_pose`` is the tracking pose of the scan that started it. Where local SLAM lost track
(a scan forced in from the edge of every window), the active submaps are finished and the scan
starts a new one (``ActiveSubmaps.insert``'s ``restart``), as Cartographer starts a new
trajectory: the old submaps keep what was mapped before, consistent, and the pose graph can
turn the new ones against them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam2d.grid.probability_grid import ProbabilityGrid, dequantize, insert_scan
from slam2d.matching.search import MatchGrid


@dataclass
class Submap:
    index: int
    local_pose: np.ndarray
    grid: ProbabilityGrid
    num_range_data: int = 0
    travel: float = 0.0  # path length of the poses inserted since it started [m]
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
        values = dequantize(g.prob) if g.prob.dtype == np.uint8 else g.prob  # a finished submap keeps uint8
        return MatchGrid(values, g.origin, g.resolution, g.unknown_probability)

    def refinement_grid(self, unobserved: str = "min_probability") -> MatchGrid:
        """What local SLAM's refinement below cell size climbs: the hit probabilities, a cell no scan
        has observed at the grid's lowest probability (``"min_probability"``, Cartographer's way);
        with ``"mirrored"``, such a cell lying just behind a surface reads as that surface's observed
        free side instead (``matching/_kernels.py`` ``_unobserved``).

        Why the option: a wall seen from one side has free cells before it and never-observed cells
        behind it. Read at the lowest probability, the interpolated profile across the wall drops
        steeper behind it than before it, so its peak lies toward the side the wall was seen from
        and a scan's points on it are pulled that way: the robot seems to have advanced less than it
        did toward what it saw from behind. Where cells were seen by many scans the free side sits
        near the lowest probability too; where each was seen by a few (scans a metre apart) it reads
        just under 0.5 and the pull shrinks whole maps (``tests/test_grid_kernels.py`` shows it; the
        README has what mirroring did on the benchmark logs, and why it is not the default)."""
        g = self.grid
        if unobserved != "mirrored" or self.finished or g.stamp.shape != g.prob.shape:
            return self.probability_grid()
        return MatchGrid(g.prob, g.origin, g.resolution, g.unknown_probability, known=g.stamp)

    def finish(self):
        """Freeze: crop to the observed cells and drop the insertion buffers."""
        self.finished = True
        g = self.grid
        b = g.known_bounds()
        if b is not None:
            g.freeze(*b)


class ActiveSubmaps:
    """The two active submaps: every scan goes into both, the older one is matched against, and it
    is finished once the newer one holds ``num_range_data`` scans.

    The newer submap is not read until it becomes the older one (nor by anything else: observers
    see the matched submap, global SLAM only finished ones), so its scans are kept and inserted in
    one batch then (``ProbabilityGrid.insert_scans``: the same cells as one scan at a time, the
    likelihood field computed afresh). Its grid is then allocated once for the extent of all of
    them, instead of growing, and copying itself, scan after scan."""

    def __init__(self, grid_cfg, num_range_data: int, field_sigma: float | None = None, max_travel: float = math.inf):
        self.grid_cfg = grid_cfg
        self.field_sigma = field_sigma
        self.num_range_data = num_range_data
        self.max_travel = max_travel
        self.submaps: list[Submap] = []  # active ones, oldest first
        self.count = 0
        self._last_pose = None
        self._pending: list[tuple] = []  # (origin, hits, misses) of the scans the newer submap has yet to take

    def _full(self, s: Submap) -> bool:
        return s.num_range_data >= self.num_range_data or s.travel >= self.max_travel

    def insert(self, local_pose, origin, hits, misses, node_index: int, restart: bool = False) -> list[Submap]:
        """Insert range data (local frame) into the active submaps; returns submaps finished by it.

        ``restart``: local SLAM lost track before this scan (its pose is a guess). The active
        submaps are finished first, so what was mapped before is not overlaid by what is mapped
        from the guess on, and the scan starts a new submap; the pose graph can then turn the new
        submaps against the old ones where loops show how."""
        finished = []
        if restart:
            self._flush()
            while self.submaps:
                old = self.submaps.pop(0)
                old.finish()
                finished.append(old)
            self._last_pose = None
        if not self.submaps or self._full(self.submaps[-1]):
            self._add(local_pose)
        step = 0.0 if self._last_pose is None else math.hypot(local_pose[0] - self._last_pose[0],
                                                               local_pose[1] - self._last_pose[1])
        self._last_pose = (float(local_pose[0]), float(local_pose[1]))
        self.last_inserted_into = [(s.index, s.local_pose) for s in self.submaps]
        insert_scan([self.submaps[0].grid], origin, hits, misses)
        if len(self.submaps) == 2:
            self._pending.append((np.asarray(origin, dtype=float), hits, misses))
        for s in self.submaps:
            if s.num_range_data:
                s.travel += step
            s.num_range_data += 1
            s.node_indices.append(node_index)
        # the older submap is finished when the newer one is full (with counts alone: after 2 × N)
        if len(self.submaps) == 2 and self._full(self.submaps[1]):
            old = self.submaps.pop(0)
            old.finish()
            finished.append(old)
            self._flush()  # the newer submap is matched against from the next scan on
        return finished

    def _flush(self):
        """Insert the kept scans into the newest active submap."""
        if self._pending:
            self.submaps[-1].grid.insert_scans(self._pending)
            self._pending = []

    def _add(self, local_pose):
        grid = ProbabilityGrid.from_config(self.grid_cfg, field_sigma=self.field_sigma)
        self.submaps.append(Submap(self.count, np.asarray(local_pose, dtype=float).copy(), grid))
        self.count += 1

    @property
    def matching_submap(self) -> Submap | None:
        return self.submaps[0] if self.submaps else None
