"""Evaluation: the paper's test protocol, its metrics, and the report."""
