"""Depth networks: FC-DenseNet with mean-depth and std heads, the Depth Scaling Layer, flip averaging."""

from endorecon.networks.fcdensenet import FCDenseNet, count_parameters
from endorecon.networks.flip import combine_predictions, predict_flip_averaged
from endorecon.networks.scaling import (DepthScalingLayer, depth_scale, local_log_scale, scale_depth,
                                       scale_depth_locally)

__all__ = ["DepthScalingLayer", "FCDenseNet", "combine_predictions", "count_parameters", "depth_scale", "local_log_scale",
           "predict_flip_averaged", "scale_depth", "scale_depth_locally"]
