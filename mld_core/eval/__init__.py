"""Evaluation as in the MLD paper: evaluator networks and metrics."""
