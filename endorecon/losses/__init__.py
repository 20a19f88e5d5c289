"""Gaussian NLL losses of the depth network (sparse depth, depth consistency, sparse flow, dense simulation)."""

from endorecon.losses.nll import (
    carried_std,
    consistency_inputs,
    dense_simulation_loss,
    depth_consistency_loss,
    flow_depth_derivative,
    gaussian_nll,
    propagated_flow_std,
    sparse_depth_loss,
    sparse_flow_loss,
    sparse_flow_loss_points,
)

__all__ = [
    "carried_std",
    "consistency_inputs",
    "dense_simulation_loss",
    "depth_consistency_loss",
    "flow_depth_derivative",
    "gaussian_nll",
    "propagated_flow_std",
    "sparse_depth_loss",
    "sparse_flow_loss",
    "sparse_flow_loss_points",
]
