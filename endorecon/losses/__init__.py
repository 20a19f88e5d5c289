"""Gaussian NLL losses of the depth network (sparse depth, depth consistency, sparse flow, dense simulation)."""

from endorecon.losses.nll import (
    dense_simulation_loss,
    depth_consistency_loss,
    flow_depth_derivative,
    gaussian_nll,
    sparse_depth_loss,
    sparse_flow_loss,
)

__all__ = [
    "dense_simulation_loss",
    "depth_consistency_loss",
    "flow_depth_derivative",
    "gaussian_nll",
    "sparse_depth_loss",
    "sparse_flow_loss",
]
