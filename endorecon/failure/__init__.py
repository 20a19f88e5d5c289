"""Failure detection: per-frame checks of depth and pose against simulated depth and SfM tracks."""

from endorecon.failure.detect import METRICS, FailureReport, check_low_thresholds, detect_failures, run

__all__ = ["METRICS", "FailureReport", "check_low_thresholds", "detect_failures", "run"]
