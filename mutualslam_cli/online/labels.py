"""What Algorithm 1 reads at a time t (DESIGN §5): a keyframe's labels from the map as it stands
(:class:`MapLabels`), and the network's depth of a keyframe as adapted up to t (:func:`depth_predictor`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.adapt.depthnet import predict_depth
from mutualslam_cli.adapt.inputs import scale_pixels
from mutualslam_cli.device import module_device
from mutualslam_cli.map.state import MapState

DepthOf = Callable[[int], np.ndarray]
"""``depth_of(kf_id)``: ``(h, w)`` depth of the current network at network resolution, map units."""


def depth_predictor(net: torch.nn.Module, load: Callable[[int], torch.Tensor], fast: bool,
                    buffer: KeyframeBuffer | None = None) -> DepthOf:
    """:data:`DepthOf` of ``net`` (on its device) for keyframe images from ``buffer`` when stored, else
    ``load(kf_id)``; the depth comes back to the CPU (culling, bridges)."""
    device = module_device(net)

    def depth_of(kf_id: int) -> np.ndarray:
        img = buffer.get(kf_id, device).image if buffer is not None and kf_id in buffer else load(kf_id)
        return predict_depth(net, img[None], fast)[0]

    return depth_of


class MapLabels:
    """A keyframe's labels read from the map when they are used (DESIGN §5): pose ``T_wc`` and the sparse
    depths of the points it observes, at network resolution ``width × height``."""

    def __init__(self, state: MapState, width: int, height: int) -> None:
        self.state, self.width, self.height = state, width, height

    def pose(self, kf_id: int) -> np.ndarray:
        return self.state.pose(kf_id)

    def sparse(self, kf_id: int) -> tuple[torch.Tensor, torch.Tensor]:
        uv, d = self.state.sparse_depth(kf_id)
        uv = scale_pixels(uv, self.state.intr, self.width, self.height)
        return torch.from_numpy(uv).float(), torch.from_numpy(d).float()
