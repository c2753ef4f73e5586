"""Correlative scan matching: real-time (Olson 2009) and branch-and-bound (Hess et al. 2016), and refinement."""
