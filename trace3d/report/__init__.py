"""Aggregation of per-scene results into the pipeline's tables and plots."""
