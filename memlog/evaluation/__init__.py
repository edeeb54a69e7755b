"""Localization metrics: PR curve and AUC (the paper's trapezoid rule), Recall@N, coverage, the
map-only and paper protocols, ground truth. Errors are :class:`EvaluationError`."""

from memlog.errors import EvaluationError

__all__ = ["EvaluationError"]
