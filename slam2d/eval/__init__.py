"""Evaluation: Kümmerle et al. 2009 relations metric, ATE/RPE, loop-closure precision/recall."""
