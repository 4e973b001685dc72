"""Monodepth2's pose network (Godard et al., ICCV 2019, §3 and ``networks/pose_*.py``), written without torchvision.

Two RGB frames stacked along channels (6 channels) → a ResNet-18 whose first convolution takes
6 channels → :class:`PoseDecoder` → axis-angle + translation. Module names reproduce the released
files key for key:

- ``pose_encoder.pth``: the ResNet under ``encoder.`` (``encoder.conv1.weight`` is ``(64, 6, 7, 7)``,
  ``encoder.layer1.0.bn1.running_mean`` …, ``encoder.fc.weight`` ``(1000, 512)``); no
  ``height``/``width`` keys (Monodepth2 writes those into ``encoder.pth`` only).
- ``pose.pth``: Monodepth2 keeps its convolutions in an ``OrderedDict`` and registers them as
  ``self.net = nn.ModuleList(...)``, so the keys are ``net.0.*`` (``squeeze``, 1×1, 512→256),
  ``net.1.*`` (``("pose", 0)``, 3×3, 256→256), ``net.2.*`` (``("pose", 1)``, 3×3, 256→256) and
  ``net.3.*`` (``("pose", 2)``, 1×1, 256→6·F). The released models have F = 2
  (``num_frames_to_predict_for=2``); Monodepth2's trainer uses only the first prediction.
"""

from __future__ import annotations

import torch
from torch import nn

from mutualslam_cli.adapt.networks.resnet_encoder import ResnetEncoder
from mutualslam_cli.errors import ShapeError

#: Monodepth2 scales the decoder's output by this before reading it as axis-angle + translation.
POSE_SCALE = 0.01


class PoseEncoder(ResnetEncoder):
    """ResNet encoder taking ``num_input_images`` stacked RGB frames (Monodepth2 ``ResNetMultiImageInput``).

    Input ``(B, 3·n, H, W)`` in [0, 1], normalised inside as ``(x − 0.45) / 0.225``; output the
    five feature maps of :class:`ResnetEncoder` (only the last is used by the pose decoder).
    """

    def __init__(self, num_layers: int = 18, num_input_images: int = 2):
        super().__init__(num_layers)
        self.num_input_images = int(num_input_images)
        self.encoder.conv1 = nn.Conv2d(3 * self.num_input_images, 64, kernel_size=7, stride=2, padding=3, bias=False)
        nn.init.kaiming_normal_(self.encoder.conv1.weight, mode="fan_out", nonlinearity="relu")

    @torch.no_grad()
    def init_from_single_image(self, single: ResnetEncoder) -> None:
        """Copy a 3-channel encoder's weights; ``conv1`` repeated over the n frames and divided by n (Monodepth2)."""
        sd = {k: v.clone() for k, v in single.state_dict().items()}
        w = sd["encoder.conv1.weight"]
        sd["encoder.conv1.weight"] = torch.cat([w] * self.num_input_images, 1) / self.num_input_images
        self.load_state_dict(sd)


class PoseDecoder(nn.Module):
    """Monodepth2's ``PoseDecoder`` (one input feature map, ``num_frames_to_predict_for`` outputs).

    Output per frame: ``0.01 · mean_{u,v}(conv(…))`` split into axis-angle ``(B, F, 1, 3)``
    (radians) and translation ``(B, F, 1, 3)`` (units of the depth it is trained with).
    """

    def __init__(self, num_ch_enc: int = 512, num_frames_to_predict_for: int = 2):
        super().__init__()
        self.num_frames_to_predict_for = int(num_frames_to_predict_for)
        self.net = nn.ModuleList([
            nn.Conv2d(num_ch_enc, 256, 1),                                # convs["squeeze"]
            nn.Conv2d(256, 256, 3, 1, 1),                                 # convs[("pose", 0)]
            nn.Conv2d(256, 256, 3, 1, 1),                                 # convs[("pose", 1)]
            nn.Conv2d(256, 6 * self.num_frames_to_predict_for, 1),        # convs[("pose", 2)]
        ])
        self.relu = nn.ReLU()

    def forward(self, last_feature: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.relu(self.net[0](last_feature))
        for i in (1, 2, 3):
            out = self.net[i](out)
            if i != 3:
                out = self.relu(out)
        out = POSE_SCALE * out.mean(3).mean(2).view(-1, self.num_frames_to_predict_for, 1, 6)
        return out[..., :3], out[..., 3:]


def rot_from_axisangle(vec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula ``R = I + sin θ [k]× + (1 − cos θ) [k]×²``, ``θ = ‖vec‖``, ``k = vec/θ``.

    Args:
        vec: ``(B, 3)`` axis-angle, radians.

    Returns:
        ``(B, 3, 3)`` rotation matrices (differentiable; ``vec = 0`` gives I).
    """
    theta = vec.norm(dim=1, keepdim=True)
    k = vec / (theta + 1e-7)
    kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
    zero = torch.zeros_like(kx)
    Kx = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], 1).view(-1, 3, 3)
    s, c = torch.sin(theta)[..., None], torch.cos(theta)[..., None]
    eye = torch.eye(3, dtype=vec.dtype, device=vec.device).expand_as(Kx)
    return eye + s * Kx + (1 - c) * (Kx @ Kx)


def pose_matrix(axisangle: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """``[R(axisangle) | t]`` as ``(B, 4, 4)`` from ``(B, 3)`` axis-angle and ``(B, 3)`` translation."""
    b = axisangle.shape[0]
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=axisangle.dtype, device=axisangle.device).expand(b, 1, 4)
    top = torch.cat([rot_from_axisangle(axisangle), translation.reshape(b, 3, 1)], 2)
    return torch.cat([top, bottom], 1)


class PoseNet(nn.Module):
    """Encoder + decoder: two frames in temporal order → relative camera motion.

    ``forward(first, second)`` returns ``T_{first→second}`` ``(B, 4, 4)``, mapping points of the first
    camera to the second (``inv(T_wc_second) @ T_wc_first``): Monodepth2 feeds ``[I_0, I_+1]``
    for a later source and ``[I_−1, I_0]`` (then inverts) for an earlier one, so the network always sees
    frames in temporal order and its (non-inverted) output is this transform.
    """

    def __init__(self, num_layers: int = 18, num_frames_to_predict_for: int = 2):
        super().__init__()
        with torch.device("cpu"):  # built on the CPU (where weights are loaded), then moved to the run's device
            self.encoder = PoseEncoder(num_layers, num_input_images=2)
            self.decoder = PoseDecoder(self.encoder.num_ch_enc[-1], num_frames_to_predict_for)

    def forward(self, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        """``first``, ``second``: ``(B, 3, H, W)`` in [0, 1] → ``(B, 4, 4)`` float32 ``T_{first→second}``."""
        if first.shape != second.shape or first.dim() != 4 or first.shape[1] != 3:
            raise ShapeError(f"PoseNet: expected two (B, 3, H, W) images, got {tuple(first.shape)}, "
                             f"{tuple(second.shape)}")
        feats = self.encoder(torch.cat([first, second], 1))
        axisangle, translation = self.decoder(feats[-1])
        return pose_matrix(axisangle[:, 0, 0].float(), translation[:, 0, 0].float())
