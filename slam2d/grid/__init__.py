"""Occupancy grids: log-odds probability grid, range insertion, submaps, map export."""
