"""What the depth network is given: images at network resolution, sparse pixels, the model itself.

One place turns sensor frames into network input, for training keyframes and for evaluation
alike, so both see the same geometry (pinhole, :class:`~mutualslam_cli.vo.camera.Undistorter`)
and the same resampling (area).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch

from mutualslam_cli.adapt import weights
from mutualslam_cli.adapt.depthnet import DepthNet, fast_path_supported, predict_depth, prepare
from mutualslam_cli.adapt.inference import openvino_predictor, resolve_runtime
from mutualslam_cli.config import NetConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.device import amp_supported, module_device
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo.camera import Undistorter


def resample(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(H, W, 3)`` uint8 → ``(height, width, 3)`` uint8 (area resampling, as :func:`to_net_image`)."""
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def to_net_image(rgb: np.ndarray, width: int, height: int) -> torch.Tensor:
    """``(H, W, 3)`` uint8 → ``(3, height, width)`` float32 in [0, 1] on the CPU (area resampling)."""
    return torch.from_numpy(resample(rgb, width, height)).permute(2, 0, 1).float().div_(255.0)


def scale_pixels(uv: np.ndarray, src: Intrinsics, width: int, height: int) -> np.ndarray:
    """Pixels ``(N, 2)`` at ``src`` resolution → pixels at ``width × height`` (pixel-centre convention)."""
    s = np.array([width / src.width, height / src.height])
    return (uv + 0.5) * s - 0.5


def frame_lookup(keyframes: VOResult | Callable[[int], int]) -> Callable[[int], int]:
    """``kf_id → frame index``: of a map's keyframes, or the given function (a map that grows)."""
    if isinstance(keyframes, VOResult):
        return lambda kf_id: keyframes.keyframes[kf_id].frame_index
    return keyframes


def keyframe_images(seq: Sequence, keyframes: VOResult | Callable[[int], int], width: int,
                    height: int) -> Callable[[int], torch.Tensor]:
    """A loader ``kf_id → (3, height, width)`` of keyframe images, undistorted to the pinhole camera.

    ``keyframes``: the map whose keyframes are read, or ``kf_id → frame index``. The same
    :class:`~mutualslam_cli.vo.camera.Undistorter` geometry as the evaluation's
    (:func:`mutualslam_cli.stages.evaluation.evaluate_depth`).
    """
    und = Undistorter(seq.intrinsics)
    frame_of = frame_lookup(keyframes)

    def load(kf_id: int) -> torch.Tensor:
        return to_net_image(und.image(seq.load_rgb(frame_of(kf_id))), width, height)

    return load


def make_predictor(net: torch.nn.Module, settings: NetConfig, fast: bool,
                   calibration: list[np.ndarray] | None = None) -> Callable[[list[np.ndarray]], np.ndarray]:
    """Batched predictor for evaluation: ``B`` frames ``(H, W, 3)`` uint8 (pinhole geometry) → ``(B, h, w)``
    float32 depth at network resolution (map units), in the runtime ``settings.runtime`` (the run's ``net``
    section) resolves to for the network's device (:func:`~mutualslam_cli.adapt.inference.resolve_runtime`;
    OpenVINO copies the weights now; the torch path runs on the network's device, resampled frames sent there as uint8).
    ``calibration``: frames of the same kind for the int8 runtime's activation ranges (required there)."""
    runtime = resolve_runtime(settings.runtime, settings.fast, module_device(net))
    if runtime == "openvino-int8" and not calibration:
        raise ConfigError("net.runtime=openvino-int8 needs calibration frames")
    if runtime.startswith("openvino"):
        calib = (torch.stack([to_net_image(rgb, settings.width, settings.height) for rgb in calibration])
                 if runtime == "openvino-int8" and calibration else None)  # int8: calibration checked above
        run = openvino_predictor(net, settings.width, settings.height, calibration=calib)

        def predict(frames: list[np.ndarray]) -> np.ndarray:
            return run(torch.stack([to_net_image(rgb, settings.width, settings.height) for rgb in frames]))
    else:
        def predict(frames: list[np.ndarray]) -> np.ndarray:
            small = np.stack([resample(rgb, settings.width, settings.height) for rgb in frames])  # (B, h, w, 3) uint8
            return predict_depth(net, small, fast=fast)

    return predict


def load_network(settings: NetConfig, fast: bool = False, device: torch.device | str = "cpu") -> DepthNet:
    """The pre-trained model of the run's ``net`` section (``settings``): ``weights`` (Monodepth2 files) or the
    ``mslam pretrain`` default, on ``device``, in the memory layout of the chosen path
    (:func:`~mutualslam_cli.adapt.depthnet.prepare`: channels-last with ``fast``, as the adapted model is; an
    unprepared model under bf16 autocast was 1.27× slower)."""
    kw: weights.DepthNetSettings = {"min_depth": settings.min_depth, "max_depth": settings.max_depth}
    net = weights.load_monodepth2(Path(settings.weights), **kw) if settings.weights else weights.load_default(**kw)
    return prepare(net, fast, device=device)


def load_saved_network(folder: Path, settings: NetConfig, fast: bool = False,
                       device: torch.device | str = "cpu") -> DepthNet:
    """A model saved in ``folder`` (Monodepth2 files, e.g. a run's adapted ``weights/``), prepared as
    :func:`load_network` prepares the pre-trained one."""
    net = weights.load_monodepth2(folder, min_depth=settings.min_depth, max_depth=settings.max_depth)
    return prepare(net, fast, device=device)


def use_fast_path(settings: NetConfig, device: torch.device | str = "cpu") -> bool:
    """Resolve the ``net`` section's ``fast`` (``settings``): ``auto`` → bf16 where the CPU supports it; on a CUDA
    device mixed precision (bf16 or fp16) where the GPU has tensor cores
    (:func:`~mutualslam_cli.device.amp_supported`)."""
    device = torch.device(device)
    if device.type == "cuda":
        return settings.fast == "on" or (settings.fast == "auto" and amp_supported(device))
    return settings.fast == "on" or (settings.fast == "auto" and fast_path_supported())
