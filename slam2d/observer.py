"""Observer interface: how the pipeline reports what it does without knowing who listens.

Visualization (Rerun), progress bars and recorders implement the methods they need; the
core never imports any of them.
"""
from __future__ import annotations


class Observer:
    """Every method is optional; the default does nothing."""

    #: whether ``on_optimized`` reads the pose graph's error (``graph.last_error``); computing it
    #: is a pass over every factor, so global SLAM skips it for observers that do not
    wants_graph_error = False

    def on_start(self, info: dict) -> None: ...

    def on_scan(self, scan, result) -> None: ...

    def on_submap_finished(self, submap) -> None: ...

    def on_loop_candidate(self, record: dict) -> None: ...

    def on_optimized(self, global_slam) -> None: ...

    def on_finish(self, result) -> None:
        """The run is finished: ``result`` is the ``slam.SlamResult`` (final poses, map, graph, summary)."""
