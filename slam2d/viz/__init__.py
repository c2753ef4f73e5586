"""Visualization: the only place that imports rerun (through the observer interface)."""
