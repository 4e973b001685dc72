"""Where scheme ``comoda``'s pose network comes from (:func:`make_pose_net`): the pose files named by
``adapt.comoda_pose_weights``, else those beside the depth weights (``net.weights``), else the default weights
folder's, else an encoder copied from the depth encoder with a random decoder. ``summary.json`` names the
choice (``adaptation.pose_network``); the adapter that trains it is :mod:`~mutualslam_cli.adapt.comoda`."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import cast

from torch import nn

from mutualslam_cli.adapt.networks import ResnetEncoder
from mutualslam_cli.adapt.networks.pose import PoseNet
from mutualslam_cli.adapt.weights import default_weights_dir, has_pose_files, load_pose
from mutualslam_cli.config import AdaptConfig

log = logging.getLogger("mutualslam_cli.adapt.comoda")  # the scheme's messages, under one name

#: ``adaptation.pose_network`` when no pose files were found (:func:`make_pose_net`).
RANDOM_POSE = "random (encoder from the depth encoder, decoder random)"


def _pose_folder(cfg: AdaptConfig, weights_dir: str | Path | None,
                default_dir: str | Path | None) -> tuple[Path | None, str]:
    """``(folder, origin)`` of the pose files :func:`make_pose_net` loads, ``(None, "")`` when none."""
    if cfg.comoda_pose_weights:
        return Path(cfg.comoda_pose_weights).expanduser(), "adapt.comoda_pose_weights"
    if weights_dir and has_pose_files(Path(weights_dir).expanduser()):
        return Path(weights_dir).expanduser(), "net.weights"
    folder = Path(default_dir if default_dir is not None else default_weights_dir()).expanduser()
    if has_pose_files(folder):
        if weights_dir:
            log.warning("comoda: net.weights %s has no pose_encoder.pth/pose.pth; using the default weights "
                        "folder's pose network %s, trained beside another depth network", weights_dir, folder)
        return folder, "the default weights folder"
    return None, ""


def make_pose_net(depth_net: nn.Module, cfg: AdaptConfig, default_dir: str | Path | None = None,
                  weights_dir: str | Path | None = None) -> tuple[PoseNet, str]:
    """The pose network of scheme ``comoda`` and where it came from.

    Order of preference: ``cfg.comoda_pose_weights`` if set (must hold the files); else
    ``weights_dir`` (the run's ``net.weights``, the depth network's folder) when it holds
    ``pose_encoder.pth`` + ``pose.pth``; else ``default_dir``'s (default: :func:`default_weights_dir`)
    pose files; else the pose encoder initialised from ``depth_net.encoder`` (``conv1`` repeated over
    the two frames and halved, as Monodepth2 does from ImageNet) and a random decoder (its 0.01 output
    scale starts it near the identity), with a warning.

    Returns:
        ``(net, source)``: the network in eval mode; ``source`` is the resolved path of the pose
        files' folder, or :data:`RANDOM_POSE` (the ``adaptation.pose_network`` of ``summary.json``).

    Raises:
        ConfigError: ``comoda_pose_weights`` names a folder without valid pose files, or a folder's
            pose files are not Monodepth2's.
    """
    folder, origin = _pose_folder(cfg, weights_dir, default_dir)
    if folder is not None:
        net = load_pose(folder)
        source = str(folder.resolve())
        log.info("comoda: pose network from %s (%s)", source, origin)
        return net, source
    where = ", ".join(str(f) for f in (weights_dir, default_dir or default_weights_dir()) if f)
    log.warning("comoda: no pose_encoder.pth/pose.pth in %s; pose encoder initialised from the depth "
                "encoder, decoder random (set adapt.comoda_pose_weights to load Monodepth2's)", where)
    net = PoseNet()
    net.encoder.init_from_single_image(cast(ResnetEncoder, depth_net.encoder))  # a DepthNet's encoder
    return net.eval(), RANDOM_POSE
