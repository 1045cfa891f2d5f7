"""Evaluation: error statistics against truth (:mod:`.metrics`), CRLB and DOP, RSSI statistics."""

from robustloc.eval.metrics import STAT_COLUMNS, epoch_errors, error_stats, error_table, match_truth

__all__ = ["STAT_COLUMNS", "epoch_errors", "error_stats", "error_table", "match_truth"]
