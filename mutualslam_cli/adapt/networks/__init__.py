"""adapt/networks: Monodepth2's ResNet encoder and depth decoder (released key names)."""

from mutualslam_cli.adapt.networks.depth_decoder import DepthDecoder
from mutualslam_cli.adapt.networks.resnet_encoder import ResnetEncoder

__all__ = ["DepthDecoder", "ResnetEncoder"]
