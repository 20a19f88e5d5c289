"""Depth networks: FC-DenseNet with mean-depth and std heads, and the Depth Scaling Layer."""

from endorecon.networks.fcdensenet import FCDenseNet, count_parameters
from endorecon.networks.scaling import (DepthScalingLayer, depth_scale, local_log_scale, scale_depth,
                                       scale_depth_locally)

__all__ = ["DepthScalingLayer", "FCDenseNet", "count_parameters", "depth_scale", "local_log_scale", "scale_depth",
           "scale_depth_locally"]
