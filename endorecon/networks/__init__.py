"""Depth networks: FC-DenseNet with mean-depth and std heads, and the Depth Scaling Layer."""

from endorecon.networks.fcdensenet import FCDenseNet, count_parameters
from endorecon.networks.scaling import DepthScalingLayer, depth_scale, scale_depth

__all__ = ["DepthScalingLayer", "FCDenseNet", "count_parameters", "depth_scale", "scale_depth"]
