"""Evaluation against ground truth: metrics and reports of what the pipeline found."""
