"""Load and save depth networks in the released Monodepth2 file format.

A model folder holds ``encoder.pth`` (the encoder's ``state_dict`` plus the extra keys
``height``, ``width``, ``use_stereo``) and ``depth.pth`` (the decoder's ``state_dict``),
exactly as Monodepth2 ships ``mono+stereo_640x192`` etc. Loading is strict: apart from the
three extra keys, every key must be present with the right shape, and no unknown key is
accepted. Two documented tolerances: ``*.num_batches_tracked`` buffers may be absent (files
from PyTorch < 0.4.1 lack them; they do not affect the output), and ``encoder.fc.*`` may be
absent *together* (the ImageNet classifier head is never used for depth; mslam's shipped
default model may drop it to save 1 MB).

Tensors may be stored as fp16 (``save_monodepth2(..., half=True)``); loading converts
them back to fp32.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias, TypedDict

import torch

from mutualslam_cli.adapt.depthnet import DepthNet
from mutualslam_cli.adapt.networks.pose import PoseNet
from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.errors import ConfigError

if TYPE_CHECKING:
    from typing_extensions import Unpack

log = logging.getLogger(__name__)

ENCODER_FILE = "encoder.pth"
DECODER_FILE = "depth.pth"
EXTRA_KEYS = ("height", "width", "use_stereo")
FC_KEYS = ("encoder.fc.weight", "encoder.fc.bias")

StateFile: TypeAlias = dict[str, torch.Tensor | int | bool]
"""A Monodepth2 ``.pth`` file: tensors by parameter name, and in an encoder file :data:`EXTRA_KEYS` (``height``,
``width``: ints, ``use_stereo``: a bool)."""


class DepthNetSettings(TypedDict, total=False):
    """Keyword arguments of :class:`~mutualslam_cli.adapt.depthnet.DepthNet` a loader passes on."""

    min_depth: float
    max_depth: float
    scales: Iterable[int]
    num_layers: int


def default_weights_dir() -> Path:
    """``$MSLAM_WEIGHTS`` if set, else the package's ``mutualslam_cli/weights/default``."""
    env = os.environ.get("MSLAM_WEIGHTS")
    if env:
        return Path(env).expanduser()
    return Path(__file__).resolve().parents[1] / "weights" / "default"


def _read(path: Path) -> StateFile:
    if not path.is_file():
        raise ConfigError(f"{path}: file not found (expected a Monodepth2 {path.name})")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ConfigError(f"{path}: cannot read as a PyTorch state dict ({exc})") from exc
    if not isinstance(obj, dict):
        raise ConfigError(f"{path}: expected a dict of tensors (Monodepth2 format), got {type(obj).__name__}")
    return obj


def _fmt(keys: list[str], limit: int = 8) -> str:
    keys = sorted(keys)
    more = f" … (+{len(keys) - limit} more)" if len(keys) > limit else ""
    return ", ".join(keys[:limit]) + more


def _check_and_load(module: torch.nn.Module, loaded: dict[str, Any], path: Path) -> None:
    """Strictly load ``loaded`` into ``module``; any mismatch → one ConfigError naming the file and keys."""
    own = module.state_dict()
    missing = [k for k in own if k not in loaded]
    unexpected = [k for k in loaded if k not in own]
    tolerated = [k for k in missing if k.endswith("num_batches_tracked")]
    if all(k in missing for k in FC_KEYS):
        tolerated += list(FC_KEYS)
    missing = [k for k in missing if k not in tolerated]
    bad_shape = [f"{k} {tuple(loaded[k].shape)} != {tuple(own[k].shape)}" for k in own
                 if k in loaded and (not isinstance(loaded[k], torch.Tensor) or loaded[k].shape != own[k].shape)]
    problems = []
    if missing:
        problems.append(f"missing keys: {_fmt(missing)}")
    if unexpected:
        problems.append(f"unexpected keys: {_fmt(unexpected)}")
    if bad_shape:
        problems.append(f"shape mismatch (file != model): {_fmt(bad_shape, 4)}")
    if problems:
        raise ConfigError(f"{path}: not a Monodepth2 ResNet-18 file for this model; " + "; ".join(problems))
    if tolerated:
        log.info("%s: keys absent and left at their initial values: %s", path, _fmt(tolerated))
    with torch.no_grad():
        for k, v in loaded.items():
            own[k].copy_(v.to(own[k].dtype))


def has_depth_files(folder: Path) -> bool:
    """Whether ``folder`` holds both ``encoder.pth`` and ``depth.pth`` (what :func:`load_monodepth2` reads)."""
    return (Path(folder) / ENCODER_FILE).is_file() and (Path(folder) / DECODER_FILE).is_file()


def load_monodepth2(folder: Path, **net_kwargs: Unpack[DepthNetSettings]) -> DepthNet:
    """Build a :class:`DepthNet` from ``folder/encoder.pth`` and ``folder/depth.pth``.

    Args:
        folder: model folder (e.g. Monodepth2's ``mono+stereo_640x192`` or ``mslam pretrain`` output).
        **net_kwargs: passed to :class:`DepthNet` (``min_depth``, ``max_depth``, ``scales``).

    Returns:
        The network in eval mode, fp32, with attributes ``feed_height``/``feed_width`` from the file.

    Raises:
        ConfigError: a file is missing/unreadable, or a key is missing, unexpected or of the
            wrong shape (the message names the file and the keys).
    """
    folder = Path(folder)
    net = DepthNet(**net_kwargs)
    enc = _read(folder / ENCODER_FILE)
    extras = {k: enc.pop(k) for k in EXTRA_KEYS if k in enc}
    _check_and_load(net.encoder, enc, folder / ENCODER_FILE)
    _check_and_load(net.decoder, _read(folder / DECODER_FILE), folder / DECODER_FILE)
    net.feed_height = int(extras["height"]) if "height" in extras else None
    net.feed_width = int(extras["width"]) if "width" in extras else None
    return net.eval()


def _atomic_save(obj: Mapping[str, object], path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def save_monodepth2(net: DepthNet, folder: Path, height: int, width: int, *, half: bool = False,
                    drop_fc: bool = False, use_stereo: bool = False) -> None:
    """Write ``net`` as ``folder/encoder.pth`` + ``folder/depth.pth`` (released Monodepth2 format).

    Args:
        net: the network.
        folder: created if needed; files are written to a temporary name and renamed.
        height, width: the training resolution, stored as ``height``/``width`` (Monodepth2).
        half: store floating tensors as fp16 (half the size; loading converts back to fp32).
        drop_fc: omit ``encoder.fc.*`` (unused by depth; Monodepth2's own loader ignores
            missing keys, :func:`load_monodepth2` tolerates their joint absence).
        use_stereo: value of the ``use_stereo`` key.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)

    def conv(sd: dict[str, torch.Tensor]) -> StateFile:
        return {k: (v.detach().half() if half and v.is_floating_point() else v.detach()).contiguous().clone()
                for k, v in sd.items()}

    enc = conv(net.encoder.state_dict())
    if drop_fc:
        for k in FC_KEYS:
            enc.pop(k)
    enc.update({"height": int(height), "width": int(width), "use_stereo": bool(use_stereo)})
    _atomic_save(enc, folder / ENCODER_FILE)
    _atomic_save(conv(net.decoder.state_dict()), folder / DECODER_FILE)


def load_default(**kw: Unpack[DepthNetSettings]) -> DepthNet:
    """Load the default model from :func:`default_weights_dir`.

    Raises:
        ConfigError: ``no default model at <dir>: run `mslam pretrain``` when absent.
    """
    folder = default_weights_dir()
    if not (folder / ENCODER_FILE).is_file() or not (folder / DECODER_FILE).is_file():
        raise ConfigError(f"no default model at {folder}: run `mslam pretrain` (or pass --weights DIR)")
    return load_monodepth2(folder, **kw)


POSE_ENCODER_FILE = "pose_encoder.pth"
POSE_DECODER_FILE = "pose.pth"


def has_pose_files(folder: Path) -> bool:
    """Whether ``folder`` holds both ``pose_encoder.pth`` and ``pose.pth``."""
    return (Path(folder) / POSE_ENCODER_FILE).is_file() and (Path(folder) / POSE_DECODER_FILE).is_file()


def load_pose(folder: Path) -> PoseNet:
    """Build a :class:`~mutualslam_cli.adapt.networks.pose.PoseNet` from Monodepth2's pose files.

    ``folder/pose_encoder.pth``: the 6-channel ResNet-18 under ``encoder.``; ``folder/pose.pth``:
    the decoder's ``net.0``…``net.3`` (module docstring of ``networks/pose.py``). Same strict rule as
    :func:`load_monodepth2`: extra ``height``/``width``/``use_stereo`` keys are dropped if present,
    every other key must match in name and shape; ``num_batches_tracked`` and ``encoder.fc.*``
    (jointly) may be absent. The number of predicted frames is read from ``net.3.weight``
    (released models: 2).

    Returns:
        The pose network in eval mode, fp32.

    Raises:
        ConfigError: a file missing or unreadable, a key missing/unexpected/of the wrong shape.
    """
    folder = Path(folder)
    enc = _read(folder / POSE_ENCODER_FILE)
    for k in EXTRA_KEYS:
        enc.pop(k, None)
    dec = _read(folder / POSE_DECODER_FILE)
    last = dec.get("net.3.weight")
    if not isinstance(last, torch.Tensor) or last.dim() != 4 or last.shape[0] % 6 or last.shape[0] == 0:
        got = tuple(last.shape) if isinstance(last, torch.Tensor) else "absent"
        raise ConfigError(f"{folder / POSE_DECODER_FILE}: not a Monodepth2 pose decoder; "
                          f"net.3.weight must be (6·F, 256, 1, 1), got {got}")
    net = PoseNet(num_frames_to_predict_for=last.shape[0] // 6)
    _check_and_load(net.encoder, enc, folder / POSE_ENCODER_FILE)
    _check_and_load(net.decoder, dec, folder / POSE_DECODER_FILE)
    return net.eval()


def save_pose(net: PoseNet, folder: Path, *, half: bool = False) -> None:
    """Write ``net`` as ``folder/pose_encoder.pth`` + ``folder/pose.pth`` (released Monodepth2 key names).

    Args:
        net: the pose network.
        folder: created if needed; files are written to a temporary name and renamed.
        half: store floating tensors as fp16 (loading converts back to fp32).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for module, name in ((net.encoder, POSE_ENCODER_FILE), (net.decoder, POSE_DECODER_FILE)):
        sd = {k: (v.detach().half() if half and v.is_floating_point() else v.detach()).contiguous().clone()
              for k, v in module.state_dict().items()}
        _atomic_save(sd, folder / name)
