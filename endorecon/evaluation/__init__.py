"""Evaluation: registration of a reconstruction to the reference ("CT") surface, residuals in mm,
residual pictures, and depth metrics against ground-truth depth."""

from endorecon.evaluation.depth_metrics import depth_error_by_range, depth_metrics, format_depth_ranges, std_error_spearman
from endorecon.evaluation.evaluate import evaluate_mesh, residual_stats
from endorecon.evaluation.meshes import ReferenceSurface, load_mesh, sample_points
from endorecon.evaluation.registration import (
    RegistrationResult,
    Sim3,
    global_registration,
    icp_sim3,
    init_from_trajectory,
    register,
    trajectory_candidates,
)

__all__ = [
    "depth_metrics",
    "depth_error_by_range",
    "format_depth_ranges",
    "std_error_spearman",
    "evaluate_mesh",
    "residual_stats",
    "ReferenceSurface",
    "load_mesh",
    "sample_points",
    "RegistrationResult",
    "Sim3",
    "global_registration",
    "icp_sim3",
    "init_from_trajectory",
    "register",
    "trajectory_candidates",
]
