"""Depth decoder of Monodepth2 (Godard et al., ICCV 2019) with its released parameter names.

Module order (and therefore ``state_dict`` keys ``decoder.<n>.…``) follows Monodepth2:
for i = 4 … 0: ``upconv(i, 0)``, ``upconv(i, 1)`` (ConvBlock = reflection-padded 3×3 conv +
ELU, keys ``decoder.<n>.conv.conv.{weight,bias}``), then ``dispconv(s)`` for s in ``scales``
(plain padded 3×3 conv, keys ``decoder.<n>.conv.{weight,bias}``). With the default
``scales=range(4)`` that is ``decoder.0`` … ``decoder.13``, 28 keys.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
import torch.nn.functional as F
from torch import nn

NUM_CH_DEC = (16, 32, 64, 128, 256)


class Conv3x3(nn.Module):
    """Reflection pad by 1, then a 3×3 convolution (attributes ``pad``, ``conv``)."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.pad = nn.ReflectionPad2d(1)
        self.conv = nn.Conv2d(int(in_channels), int(out_channels), 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(self.pad(x))


class ConvBlock(nn.Module):
    """:class:`Conv3x3` followed by ELU (attributes ``conv``, ``nonlin``).

    The ELU is *not* in place (Monodepth2's is): an in-place ELU's backward is computed from its output,
    ``g·(y + 1)`` for ``y = eˣ − 1 ≤ 0``, and under bf16 autocast ``y`` rounds to −1 once ``eˣ < 2⁻⁹``
    (x < −6.2; fp32: x < −16.6), so the gradient of every unit below −6.2 is exactly 0. Measured on real
    ICL-NUIM batches (AMX, ``tests/adapt/test_fast_path.py``): 22 % of ``decoder.1``'s weights got no gradient
    at all in bf16 where fp32 gave them one, and the bf16 step's Adam-preconditioned direction was 0.98
    cosine-similar to fp32's; out of place (backward from the input, ``g·eˣ``) 0.998, for ~1 % of a step.
    """

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = Conv3x3(in_channels, out_channels)
        self.nonlin = nn.ELU(inplace=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.nonlin(self.conv(x))


class DepthDecoder(nn.Module):
    """U-Net style decoder with skip connections, sigmoid disparity outputs.

    Args:
        num_ch_enc: channels of the five encoder features, e.g. ``[64, 64, 128, 256, 512]``.
        scales: scales that own a ``dispconv`` (keep ``range(4)`` to load released files).
    """

    def __init__(self, num_ch_enc: Sequence[int], scales: Iterable[int] = range(4)):
        super().__init__()
        self.num_ch_enc = [int(c) for c in num_ch_enc]
        self.scales = tuple(scales)
        self._index: dict[tuple[str | int, ...], int] = {}
        mods: list[nn.Module] = []
        for i in range(4, -1, -1):
            c_in = self.num_ch_enc[-1] if i == 4 else NUM_CH_DEC[i + 1]
            self._index[("upconv", i, 0)] = len(mods)
            mods.append(ConvBlock(c_in, NUM_CH_DEC[i]))
            c_in = NUM_CH_DEC[i] + (self.num_ch_enc[i - 1] if i > 0 else 0)
            self._index[("upconv", i, 1)] = len(mods)
            mods.append(ConvBlock(c_in, NUM_CH_DEC[i]))
        for s in self.scales:
            self._index[("dispconv", s)] = len(mods)
            mods.append(Conv3x3(NUM_CH_DEC[s], 1))
        self.decoder = nn.ModuleList(mods)

    def _m(self, *key: str | int) -> nn.Module:
        return self.decoder[self._index[key]]

    def forward(self, features: Sequence[torch.Tensor], scales: Iterable[int] | None = None) -> dict[int, torch.Tensor]:
        """Decode encoder features.

        Args:
            features: the five encoder maps, finest first.
            scales: which disparities to compute (default: all of ``self.scales``); the
                others are skipped, which saves time when only scale 0 is needed.

        Returns:
            ``{s: disp_s}``, ``disp_s`` of shape ``(B, 1, H / 2**s, W / 2**s)`` in (0, 1).
        """
        wanted = self.scales if scales is None else tuple(scales)
        out: dict[int, torch.Tensor] = {}
        x = features[-1]
        for i in range(4, -1, -1):
            x = self._m("upconv", i, 0)(x)
            x = F.interpolate(x, scale_factor=2, mode="nearest")
            if i > 0:
                x = torch.cat([x, features[i - 1]], 1)
            x = self._m("upconv", i, 1)(x)
            if i in wanted:
                out[i] = torch.sigmoid(self._m("dispconv", i)(x))
        return out
