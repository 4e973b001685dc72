"""ResNet encoder of Monodepth2 (Godard et al., ICCV 2019), written without torchvision.

The module tree reproduces torchvision's ``resnet18``/``resnet34`` naming under an
``encoder`` attribute, so ``state_dict()`` keys are exactly those of Monodepth2's released
``encoder.pth`` (``encoder.conv1.weight``, ``encoder.layer1.0.bn1.running_mean``, ...,
``encoder.fc.weight``, ``encoder.fc.bias``). ``fc`` is never used by the depth network but
is kept so that released files load key-for-key.
"""

from __future__ import annotations

import torch
from torch import nn

from mutualslam_cli.errors import ConfigError

#: Channels of the five feature maps returned by :class:`ResnetEncoder` (BasicBlock ResNets).
NUM_CH_ENC = (64, 64, 128, 256, 512)
_BLOCKS = {18: (2, 2, 2, 2), 34: (3, 4, 6, 3)}


class BasicBlock(nn.Module):
    """Two 3×3 convolutions with a residual connection (He et al., CVPR 2016)."""

    expansion = 1

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=1, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample
        self.stride = stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet(nn.Module):
    """ResNet with torchvision's attribute names (``conv1``, ``bn1``, ``layer1..4``, ``fc``)."""

    def __init__(self, layers: tuple[int, int, int, int], num_classes: int = 1000):
        super().__init__()
        self.inplanes = 64
        self.conv1 = nn.Conv2d(3, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(64, layers[0])
        self.layer2 = self._make_layer(128, layers[1], stride=2)
        self.layer3 = self._make_layer(256, layers[2], stride=2)
        self.layer4 = self._make_layer(512, layers[3], stride=2)
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.fc = nn.Linear(512, num_classes)
        for m in self.modules():  # He init as torchvision's ResNet
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def _make_layer(self, planes: int, blocks: int, stride: int = 1) -> nn.Sequential:
        downsample = None
        if stride != 1 or self.inplanes != planes:
            downsample = nn.Sequential(
                nn.Conv2d(self.inplanes, planes, 1, stride=stride, bias=False), nn.BatchNorm2d(planes)
            )
        layers = [BasicBlock(self.inplanes, planes, stride, downsample)]
        self.inplanes = planes
        layers += [BasicBlock(planes, planes) for _ in range(1, blocks)]
        return nn.Sequential(*layers)


class ResnetEncoder(nn.Module):
    """Monodepth2's encoder: a ResNet whose five intermediate feature maps feed the decoder.

    Args:
        num_layers: 18 (default, Monodepth2's released models) or 34.

    Input ``(B, 3, H, W)`` RGB in [0, 1]; normalised inside as ``(x − 0.45) / 0.225``
    (Monodepth2). Output: five maps with :data:`NUM_CH_ENC` channels at strides 2, 4, 8, 16, 32.
    """

    def __init__(self, num_layers: int = 18):
        super().__init__()
        if num_layers not in _BLOCKS:
            raise ConfigError(f"ResnetEncoder: num_layers must be one of {sorted(_BLOCKS)}, got {num_layers}")
        self.num_ch_enc = list(NUM_CH_ENC)
        self.encoder = ResNet(_BLOCKS[num_layers])

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        e = self.encoder
        x = (x - 0.45) / 0.225
        f0 = e.relu(e.bn1(e.conv1(x)))
        f1 = e.layer1(e.maxpool(f0))
        f2 = e.layer2(f1)
        f3 = e.layer3(f2)
        f4 = e.layer4(f3)
        return [f0, f1, f2, f3, f4]
