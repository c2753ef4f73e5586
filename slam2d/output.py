"""The output folder of a run, written so that a failed run never leaves files that look whole.

Every file is first written under a ``.partial`` name and renamed only when all of them are
complete: ``trajectory.txt`` (TUM, every input scan, stamps ascending: `slam2d.io.trajectory`), ``map.pgm`` +
``map.yaml`` (ROS map_server) + ``map.png``, ``config.yaml``, ``summary.json``.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from slam2d.config import SlamConfig, dump_config
from slam2d.errors import UsageError
from slam2d.grid.map_export import write_map
from slam2d.io.trajectory import write_tum

PARTIAL = ".partial"
#: every file a run may write into its folder (``SlamResult.save``)
OUTPUT_FILES = ("trajectory.txt", "map.pgm", "map.yaml", "map.png", "config.yaml", "constraints.jsonl",
                "results.mcap", "summary.json")


class OutputDir:
    def __init__(self, path):
        self.path = Path(path)
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UsageError(f"{self.path}: cannot create output folder ({e.strerror})") from None
        if not os.access(self.path, os.W_OK):
            raise UsageError(f"{self.path}: output folder is not writable")
        self.pending: list[Path] = []

    def staged(self, name: str) -> Path:
        """Path to write ``name`` under its partial name; committed by `commit`."""
        final = self.path / name
        self.pending.append(final)
        return Path(f"{final}{PARTIAL}")

    def write_text(self, name, text):
        self.staged(name).write_text(text)

    def write_json(self, name, obj):
        self.staged(name).write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")

    def write_map(self, grid, cfg: SlamConfig, stem="map"):
        paths = write_map(self.path, grid, cfg.map.occupied_thresh, cfg.map.free_thresh, stem=stem, suffix=PARTIAL,
                          cells=cfg.map.cell_thresholds(cfg.grid))
        self.pending.extend(paths)

    def write_trajectory(self, name, stamps, poses):
        write_tum(self.staged(name), stamps, poses)

    def commit(self):
        """Rename every file into place, after checking that none of the names is taken by a folder, and
        remove the outputs of an earlier run into this folder that this one does not write (a local run
        saved over a global one left the global run's constraints.jsonl beside its own summary)."""
        taken = [p for p in self.pending if p.is_dir()]
        if taken:
            raise UsageError(f"{taken[0]}: is a folder; the run's output file of that name cannot be written")
        for p in self.pending:
            os.replace(f"{p}{PARTIAL}", p)
        for name in OUTPUT_FILES:
            stale = self.path / name
            if stale not in self.pending and stale.is_file():
                stale.unlink()
        self.pending = []

    def abort(self):
        for p in self.pending:
            try:
                os.unlink(f"{p}{PARTIAL}")
            except FileNotFoundError:
                pass
        self.pending = []


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o))


def config_text(cfg: SlamConfig) -> str:
    return dump_config(cfg)
