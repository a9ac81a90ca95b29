"""Evaluation: metrics (eq. 14), the benchmarks (paper, later generalization and real-vehicle), tables and figures."""
