"""adapt/networks: Monodepth2's ResNet encoder, depth decoder and pose network (released key names)."""

from mutualslam_cli.adapt.networks.depth_decoder import DepthDecoder
from mutualslam_cli.adapt.networks.pose import PoseDecoder, PoseEncoder, PoseNet
from mutualslam_cli.adapt.networks.resnet_encoder import ResnetEncoder

__all__ = ["DepthDecoder", "PoseDecoder", "PoseEncoder", "PoseNet", "ResnetEncoder"]
