"""The compact U-Net of Neural Shadow Mapping (Datta et al., SIGGRAPH 2022) in PyTorch, and its ONNX export.

2x2 space-to-depth at the input, 5 levels (3x3 + 1x1 convolutions with ReLU per block, 2x2 average
pooling down, bilinear upsampling up), additive skips at levels 1..4 and none at level 0, a 1x1 head
whose 4 channels go back to full resolution by depth-to-space, and a sigmoid: visibility in [0, 1].
Space-to-depth and depth-to-space are fixed one-hot (transposed) convolutions, numerically the same
permutation, because every OpenCV 4.x dnn build runs Conv/ConvTranspose (not all run SpaceToDepth).
"""
from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

IN_CHANNELS = 7          # photoreg.render.shadow_buffers.CHANNELS
WIDTHS = (16, 24, 32, 48, 64)
OUT_BIAS = 2.0          # initial output logit: v = 0.88 ('lit', the common answer) off the sigmoid's flat tail
MULTIPLE = 32            # input sides must be multiples of 2 (space-to-depth) * 2^4 (pooling)


def _one_hot_s2d(channels: int) -> torch.Tensor:
    """(4C, C, 2, 2) weights mapping each 2x2 block of channel c to channels 4c + 2dy + dx."""
    w = torch.zeros(4 * channels, channels, 2, 2)
    for c in range(channels):
        for dy in range(2):
            for dx in range(2):
                w[4 * c + 2 * dy + dx, c, dy, dx] = 1.0
    return w


class Block(nn.Sequential):
    """3x3 conv + ReLU, 1x1 conv + ReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 1), nn.ReLU(inplace=True))


class ShadowUNet(nn.Module):
    def __init__(self, in_channels: int = IN_CHANNELS, widths: tuple[int, ...] = WIDTHS):
        super().__init__()
        self.register_buffer("s2d", _one_hot_s2d(in_channels))
        self.register_buffer("d2s", _one_hot_s2d(1))
        self.enc = nn.ModuleList([Block(4 * in_channels if i == 0 else widths[i - 1], w)
                                  for i, w in enumerate(widths)])
        # decoder block at level i takes level i's width and gives level i-1's (the next skip's) width
        self.dec = nn.ModuleList([Block(widths[i], widths[i - 1]) for i in range(len(widths) - 1, 0, -1)])
        self.head0 = Block(widths[0], widths[0])
        self.out = nn.Conv2d(widths[0], 4, 1)
        nn.init.constant_(self.out.bias, OUT_BIAS)
        self.pool = nn.AvgPool2d(2)
        self.up = nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (N, C, H, W), H and W multiples of MULTIPLE -> visibility (N, 1, H, W) in [0, 1]."""
        h = nn.functional.conv2d(x, self.s2d, stride=2)
        skips = []
        for i, block in enumerate(self.enc):
            if i > 0:
                h = self.pool(h)
            h = block(h)
            skips.append(h)
        for k, block in enumerate(self.dec):
            level = len(self.enc) - 2 - k              # the level this block's output goes up to
            h = self.up(block(h))
            if level > 0:                              # no skip at the first level
                h = h + skips[level]
        h = self.out(self.head0(h))
        return torch.sigmoid(nn.functional.conv_transpose2d(h, self.d2s, stride=2))


def parameter_count(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters() if p.requires_grad)


def export_onnx(net: ShadowUNet, path: str | Path, height: int = 96, width: int = 128) -> None:
    """ONNX graph (opset 13), written atomically. Exported at a fixed size: OpenCV's importer re-infers the
    shapes from each input it is given, and with dynamic axes it fails to match the skip additions."""
    from photoreg.io.atomic import atomic_path

    net = net.eval()
    x = torch.zeros(1, net.enc[0][0].in_channels // 4, height, width)
    with atomic_path(path) as tmp, torch.no_grad():
        torch.onnx.export(net, x, str(tmp), input_names=["buffers"], output_names=["visibility"], opset_version=13,
                          dynamo=False)
