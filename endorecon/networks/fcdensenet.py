"""FC-DenseNet ("Tiramisu") encoder-decoder with a mean-depth head and a std head.

The family of the paper's network (FC-DenseNet-57: 48 first-conv channels,
growth 12, five dense blocks of 4 layers down and up, a 4-layer bottleneck;
about 1.4 M parameters).  Every size is a constructor argument so that
``conf/model/`` can trade width and depth for CPU speed while keeping the
architecture: dense blocks (BN-ReLU-conv3x3 layers whose inputs are the
concatenation of all earlier outputs), transition-down (BN-ReLU-1x1 conv,
max-pool), transition-up (3x3 transposed conv, concatenation with the skip).

Output: ``depth = softplus(a) + min_depth`` and ``std = softplus(b) + std_floor``,
both (B,1,H,W) and strictly positive.  Depth is up to scale; the Depth
Scaling Layer (:mod:`endorecon.networks.scaling`) fixes it per frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

from endorecon.geometry._checks import check_shape


class _DenseLayer(nn.Sequential):
    def __init__(self, in_ch: int, growth: int, dropout: float):
        super().__init__(
            nn.BatchNorm2d(in_ch),
            nn.ReLU(inplace=True),
            nn.Conv2d(in_ch, growth, 3, padding=1, bias=False),
        )
        if dropout > 0:
            self.append(nn.Dropout2d(dropout))


class _DenseBlock(nn.Module):
    """``n_layers`` dense layers; returns input ⊕ new features, or only the new ones (``new_only``)."""

    def __init__(self, in_ch: int, growth: int, n_layers: int, dropout: float, new_only: bool):
        super().__init__()
        self.layers = nn.ModuleList(_DenseLayer(in_ch + i * growth, growth, dropout) for i in range(n_layers))
        self.new_only = new_only
        self.out_channels = n_layers * growth if new_only else in_ch + n_layers * growth

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        feats = [x]
        for layer in self.layers:
            feats.append(layer(torch.cat(feats, 1) if len(feats) > 1 else x))
        return torch.cat(feats[1:] if self.new_only else feats, 1)


class _TransitionDown(nn.Sequential):
    def __init__(self, ch: int, dropout: float):
        super().__init__(nn.BatchNorm2d(ch), nn.ReLU(inplace=True), nn.Conv2d(ch, ch, 1, bias=False))
        if dropout > 0:
            self.append(nn.Dropout2d(dropout))
        self.append(nn.MaxPool2d(2))


class FCDenseNet(nn.Module):
    """FC-DenseNet with two positive heads (mean depth, std).

    Args:
        in_channels: image channels (3).
        first_conv_channels: channels of the first 3x3 conv (paper: 48).
        growth_rate: channels each dense layer adds (paper: 12).
        down_layers: layers per dense block on the way down; its length is the
            number of levels L, input sides must be divisible by 2**L (paper: (4,)*5).
        up_layers: layers per block on the way up (default: ``down_layers`` reversed).
        bottleneck_layers: layers of the bottleneck block (paper: 4).
        dropout: Dropout2d after each conv (paper: 0.2).
        std_floor: added to the std head so that std > 0 always (NLL stability).
        min_depth: added to the depth head so that depth > 0 always.
        image_mean, image_std: per-channel normalisation of the [0,1] input (after ``input_transform``).
        input_transform: ``"linear"`` (the image as it is) or ``"log"``: log(max(image, 1/255)).  With a
            light at the camera and a gamma-encoded sensor, log intensity is about linear in log depth (inverse-
            square fall-off), and the frame's exposure an additive offset.  ``"log_centered"``: the log image less
            its per-channel mean over the mask (the whole frame without one): blind to a frame's exposure and
            white balance (set image_mean to 0 for it).
        depth_activation: ``"softplus"`` or ``"exp"`` (the head predicts log depth) for the depth head.
        channels_last: keep the conv weights and feature maps in channels-last memory layout.  The same
            maths in another layout: on CPU, oneDNN runs this network's small-channel convolutions, batch
            norms and concatenations about twice as fast that way (benchmarks/train_throughput.py).  The
            outputs are (B,1,H,W), for which both layouts are the same.
    """

    def __init__(
        self,
        in_channels: int = 3,
        first_conv_channels: int = 48,
        growth_rate: int = 12,
        down_layers: Sequence[int] = (4, 4, 4, 4, 4),
        up_layers: Sequence[int] | None = None,
        bottleneck_layers: int = 4,
        dropout: float = 0.2,
        std_floor: float = 1e-3,
        min_depth: float = 1e-3,
        image_mean: Sequence[float] = (0.5, 0.5, 0.5),
        image_std: Sequence[float] = (0.25, 0.25, 0.25),
        input_transform: str = "linear",
        depth_activation: str = "softplus",
        channels_last: bool = True,
    ):
        super().__init__()
        if input_transform not in ("linear", "log", "log_centered"):
            raise ValueError(f"input_transform must be 'linear', 'log' or 'log_centered', got {input_transform!r}")
        if depth_activation not in ("softplus", "exp"):
            raise ValueError(f"depth_activation must be 'softplus' or 'exp', got {depth_activation!r}")
        self.input_transform, self.depth_activation = input_transform, depth_activation
        down_layers = [int(n) for n in down_layers]
        up_layers = [int(n) for n in (up_layers if up_layers is not None else down_layers[::-1])]
        if len(up_layers) != len(down_layers) or not down_layers:
            raise ValueError(f"down_layers and up_layers need the same non-zero length, got {down_layers}, {up_layers}")
        if std_floor <= 0 or min_depth <= 0:
            raise ValueError(f"std_floor and min_depth must be > 0, got {std_floor}, {min_depth}")
        self.levels = len(down_layers)
        self.std_floor = float(std_floor)
        self.min_depth = float(min_depth)
        self.register_buffer("image_mean", torch.tensor(image_mean, dtype=torch.float32).view(1, -1, 1, 1))
        self.register_buffer("image_std", torch.tensor(image_std, dtype=torch.float32).view(1, -1, 1, 1))

        self.first_conv = nn.Conv2d(in_channels, first_conv_channels, 3, padding=1, bias=True)
        ch = first_conv_channels
        self.down_blocks, self.trans_down, skip_ch = nn.ModuleList(), nn.ModuleList(), []
        for n in down_layers:
            block = _DenseBlock(ch, growth_rate, n, dropout, new_only=False)
            self.down_blocks.append(block)
            ch = block.out_channels
            skip_ch.append(ch)
            self.trans_down.append(_TransitionDown(ch, dropout))
        self.bottleneck = _DenseBlock(ch, growth_rate, bottleneck_layers, dropout, new_only=True)
        prev = self.bottleneck.out_channels
        self.trans_up, self.up_blocks = nn.ModuleList(), nn.ModuleList()
        for k, n in enumerate(up_layers):
            self.trans_up.append(nn.ConvTranspose2d(prev, prev, 3, stride=2, padding=1, output_padding=1, bias=True))
            last = k == len(up_layers) - 1
            # Upper blocks pass only their new features up (keeps the decoder narrow, as the Tiramisu).
            block = _DenseBlock(prev + skip_ch[-1 - k], growth_rate, n, dropout, new_only=not last)
            self.up_blocks.append(block)
            prev = block.out_channels
        self.depth_head = nn.Conv2d(prev, 1, 1)
        self.std_head = nn.Conv2d(prev, 1, 1)
        self._init_weights()
        self.channels_last = bool(channels_last)
        if self.channels_last:
            self.to(memory_format=torch.channels_last)  # 4-D weights; state dicts load into either layout

    def _init_weights(self):
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.kaiming_uniform_(m.weight, nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        # Small heads: a random init starts near depth ≈ 1, std ≈ 0.3 everywhere (finite NLL).
        depth_bias = 0.55 if self.depth_activation == "softplus" else 0.0
        for head, bias in ((self.depth_head, depth_bias), (self.std_head, -1.0)):
            nn.init.normal_(head.weight, std=1e-3)
            nn.init.constant_(head.bias, bias)

    def normalise(self, image: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        if self.input_transform != "linear":
            image = torch.log(image.clamp(min=1.0 / 255))
        if self.input_transform == "log_centered":
            w = torch.ones_like(image[:, :1]) if mask is None else mask.to(image.dtype)
            image = image - (image * w).sum((2, 3), keepdim=True) / w.sum((2, 3), keepdim=True).clamp(min=1.0)
        x = (image - self.image_mean) / self.image_std
        return x if mask is None else x * mask.to(x.dtype)

    def forward(self, image: torch.Tensor, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Predict depth and std.

        Args:
            image: (B, C, H, W) in [0, 1]; H and W divisible by 2**levels.
            mask: optional (B, 1, H, W) bool; the input is zeroed outside it (after normalisation).
        Returns:
            depth: (B, 1, H, W) > 0 (up to scale), float32 also under autocast.
            std: (B, 1, H, W) >= std_floor, float32 also under autocast.
        """
        B, C, H, W = check_shape(image, "image", (None, self.image_mean.shape[1], None, None))
        if mask is not None:
            check_shape(mask, "mask", (B, 1, H, W))
        m = 2**self.levels
        if H % m or W % m:
            raise ValueError(
                f"image size {H}x{W} must be divisible by 2**levels = {m} (levels = len(down_layers) = {self.levels}); "
                f"resize/crop the frames or use fewer levels"
            )
        x = self.normalise(image, mask)
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        x = self.first_conv(x)
        skips = []
        for block, down in zip(self.down_blocks, self.trans_down):
            x = block(x)
            skips.append(x)
            x = down(x)
        x = self.bottleneck(x)
        for up, block in zip(self.trans_up, self.up_blocks):
            x = block(torch.cat([up(x), skips.pop()], 1))
        # Heads' outputs in float32: under mixed precision (trainer=gpu) the NLL losses' eps 1e-8 and
        # squared residuals in mm would underflow / lose digits in float16.
        a = self.depth_head(x).float()
        # exp: clamped so that a diverging step gives a large finite depth, not inf
        depth = (F.softplus(a) if self.depth_activation == "softplus" else torch.exp(a.clamp(max=20.0))) + self.min_depth
        std = F.softplus(self.std_head(x).float()) + self.std_floor
        return depth, std


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
