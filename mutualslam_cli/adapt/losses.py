"""Training losses of the online adaptation (paper §III-B, Eq. 3–8).

Everything here runs in fp32 even inside a bf16 autocast region: inputs in half
precision are promoted to float32 (float64 inputs stay float64, for gradcheck) and
autocast is disabled inside each function.

Averaging convention for batches (Eq. 8 averages L_train over the recent and the replayed
keyframe): every term is a mean per image, then the mean over the images of the batch
(images without any valid pixel / sparse point are left out of that term's mean).

>>> import torch
>>> d = torch.full((1, 1, 8, 8), 2.0, requires_grad=True)
>>> float(sparse_depth_loss(d, torch.tensor([[[3.0, 4.0]]]), torch.tensor([[4.0]]), torch.tensor([[True]])))
0.25
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import torch
import torch.nn.functional as F

from mutualslam_cli.adapt.warp import warp
from mutualslam_cli.errors import ShapeError
from mutualslam_cli.types import check_shape

P = ParamSpec("P")
R = TypeVar("R")

_C1, _C2 = 0.01 ** 2, 0.03 ** 2  # SSIM constants for images in [0, 1] (Wang et al. 2004)


def _fp32(fn: Callable[P, R]) -> Callable[P, R]:
    """Run ``fn`` with autocast off on the CPU and, where it is on, on CUDA (the fast path keeps losses in
    full precision on every device)."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with contextlib.ExitStack() as stack:
            stack.enter_context(torch.autocast("cpu", enabled=False))
            if torch.is_autocast_enabled("cuda"):
                stack.enter_context(torch.autocast("cuda", enabled=False))
            return fn(*args, **kwargs)

    return wrapper


def _f(x: torch.Tensor) -> torch.Tensor:
    """Promote half/bfloat16 (and integer) tensors to float32; keep float32/float64."""
    return x if x.dtype in (torch.float32, torch.float64) else x.float()


def _masked_mean_per_image(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` over ``mask`` per image, then over images with ≥ 1 masked element.

    ``x``, ``mask``: ``(B, ...)``. Returns a 0-d tensor; exactly 0 (connected to the graph
    of ``x``) when ``mask`` is empty everywhere.
    """
    b = x.shape[0]
    m = mask.reshape(b, -1)
    xs = torch.where(m, x.reshape(b, -1), torch.zeros_like(x.reshape(b, -1)))
    cnt = m.sum(1)
    has = cnt > 0
    if not bool(has.any()):
        return x.sum() * 0.0
    per_image = xs.sum(1)[has] / cnt[has].to(x.dtype)
    return per_image.mean()


def _box3(t: torch.Tensor) -> torch.Tensor:
    """3×3 mean of each channel of ``(B, C, H, W)`` on the reflection-padded image (same shape)."""
    c = t.shape[1]
    box = torch.full((c, 1, 3, 3), 1.0 / 9.0, dtype=t.dtype, device=t.device)
    return F.conv2d(F.pad(t, (1, 1, 1, 1), mode="reflect"), box, groups=c)  # depthwise: one pass for all


def _repeat_to(x: torch.Tensor, b: int, what: str) -> tuple[torch.Tensor, int]:
    """``x`` repeated along the batch to ``b`` images (``b`` a multiple of its batch); the factor."""
    if b % x.shape[0]:
        raise ShapeError(f"{what}: batch {b} is not a multiple of the target batch {x.shape[0]}")
    n = b // x.shape[0]
    return (x if n == 1 else x.repeat(n, 1, 1, 1)), n


@_fp32
def ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """SSIM dissimilarity ``(1 − SSIM)/2`` on 3×3 windows, clamped to [0, 1] (Monodepth2 style).

    Local statistics use a 3×3 box filter on reflection-padded images. ``x`` may hold fewer
    images than ``y`` (``y``'s batch a multiple ``n`` of ``x``'s, image k of ``y`` paired with
    image ``k mod B`` of ``x``, as :func:`torch.Tensor.repeat` lays it out): one target against
    each of its warped sources. Then μ_x and σ_x² are computed once per target rather than
    per source, the same numbers with 2/5 less box filtering (16 ms of a 420 ms step).

    Args:
        x: ``(B, C, H, W)`` images in [0, 1]. y: ``(n·B, C, H, W)`` images in [0, 1].

    Returns:
        ``(n·B, C, H, W)`` map in [0, 1] (0 = identical).
    """
    check_shape(x, ["B", "C", "H", "W"], "ssim.x")
    check_shape(y, ["N", x.shape[1], x.shape[2], x.shape[3]], "ssim.y")
    x, y = _f(x), _f(y)
    c = x.shape[1]
    mu_x, e_xx = _box3(torch.cat([x, x * x], 1)).split(c, 1)
    s_x, _ = _repeat_to(e_xx - mu_x ** 2, y.shape[0], "ssim")
    mu_x, _ = _repeat_to(mu_x, y.shape[0], "ssim")
    x, _ = _repeat_to(x, y.shape[0], "ssim")
    mu_y, e_yy, e_xy = _box3(torch.cat([y, y * y, x * y], 1)).split(c, 1)
    s_y = e_yy - mu_y ** 2
    s_xy = e_xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + _C1) * (2 * s_xy + _C2)
    den = (mu_x ** 2 + mu_y ** 2 + _C1) * (s_x + s_y + _C2)
    return torch.clamp((1 - num / den) / 2, 0, 1)


@_fp32
def photometric_error(target: torch.Tensor, warped: torch.Tensor, alpha: float = 0.85) -> torch.Tensor:
    """Per-pixel photometric error ``pe`` (Eq. 4): ``α/2·(1 − SSIM) + (1 − α)·|I_i − I_{s→i}|₁``.

    Channels are averaged (Monodepth2).

    Args:
        target: ``(B, C, H, W)`` images in [0, 1].
        warped: ``(n·B, C, H, W)`` images in [0, 1]; image k is compared with target ``k mod B``
            (n warped sources per target, stacked source by source).
        alpha: SSIM/L1 balance α (paper: 0.85).

    Returns:
        ``(n·B, 1, H, W)``.
    """
    target, warped = _f(target), _f(warped)
    l1 = (_repeat_to(target, warped.shape[0], "photometric_error")[0] - warped).abs().mean(1, keepdim=True)
    return alpha * ssim(target, warped).mean(1, keepdim=True) + (1 - alpha) * l1  # Eq. 4


@_fp32
def photometric_loss(target: torch.Tensor, sources: list[torch.Tensor], depth: torch.Tensor, K: torch.Tensor,
                     T_t2s: list[torch.Tensor], alpha: float = 0.85) -> torch.Tensor:
    """Minimum reprojection loss L_photo (Eq. 3) over the adjacent views.

    Each source is warped once with the target depth (Eq. 5); per pixel, the minimum
    ``pe`` over the sources in which it projects validly is kept, and the loss is the mean
    over pixels valid in at least one source (per image, then over images).

    Args:
        target: ``(B, 3, H, W)`` target keyframe in [0, 1].
        sources: adjacent keyframes, each ``(B, 3, H, W)``.
        depth: ``(B, 1, H, W)`` predicted depth of the target.
        K: ``(B, 3, 3)`` intrinsics at this resolution.
        T_t2s: per source, ``(B, 4, 4)`` target-camera → source-camera transform.
        alpha: α of Eq. 4.

    Returns:
        0-d tensor; 0 (with a graph) when no pixel is valid anywhere.
    """
    if len(sources) == 0 or len(sources) != len(T_t2s):
        raise ShapeError(f"photometric_loss: need ≥ 1 source and one pose per source, "
                         f"got {len(sources)} sources and {len(T_t2s)} poses")
    check_shape(target, ["B", 3, "H", "W"], "photometric_loss.target")
    check_shape(depth, [target.shape[0], 1, target.shape[2], target.shape[3]], "photometric_loss.depth")
    for i, (x, t) in enumerate(zip(sources, T_t2s)):
        check_shape(x, list(target.shape), f"photometric_loss.sources[{i}]")
        check_shape(t, [target.shape[0], 4, 4], f"photometric_loss.T_t2s[{i}]")
    target, depth = _f(target), _f(depth)
    b, n = target.shape[0], len(sources)
    # all sources in one batched warp: each neighbour is warped exactly once (Eq. 5)
    src = torch.cat([_f(x).to(target.dtype) for x in sources], 0)
    T = torch.cat([_f(t) for t in T_t2s], 0)
    warped, valid = warp(src, depth.repeat(n, 1, 1, 1), _f(K).repeat(n, 1, 1), T)
    pe = photometric_error(target, warped, alpha)                              # (S·B, 1, H, W)
    pe = torch.cat(pe.split(b, 0), 1)                                          # (B, S, H, W)
    valid = torch.cat(valid.split(b, 0), 1)
    big = torch.full_like(pe, 1e4)
    pe_min = torch.where(valid, pe, big).min(1, keepdim=True).values  # argmin over s, Eq. 3
    return _masked_mean_per_image(pe_min, valid.any(1, keepdim=True))


@_fp32
def sample_depth(depth: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear depth at subpixel ``uv`` ``(B, M, 2)`` (pixel centres, border clamp) → ``(B, M)``."""
    _b, _, h, w = depth.shape
    grid = torch.stack([2.0 * uv[..., 0] / max(w - 1, 1) - 1.0, 2.0 * uv[..., 1] / max(h - 1, 1) - 1.0], -1)
    out = F.grid_sample(depth, grid.unsqueeze(1).to(depth.dtype), mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out[:, 0, 0, :]


@_fp32
def sparse_depth_loss(depth: torch.Tensor, uv: torch.Tensor, d: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Sparse inverse-depth loss L_sparse (Eq. 6): mean ``|1/D(p) − 1/D_sparse(p)|`` over map points.

    Args:
        depth: ``(B, 1, H, W)`` predicted depth.
        uv: ``(B, M, 2)`` subpixel locations of the projected map points at this resolution.
        d: ``(B, M)`` map-point depths (> 0 where ``mask``).
        mask: ``(B, M)`` bool, valid entries (padding is ``False``).

    Returns:
        0-d tensor. With an empty ``mask`` it is an exact 0 that still ``requires_grad``
        (when ``depth`` does) and back-propagates zero gradients — never NaN.
    """
    check_shape(depth, ["B", 1, "H", "W"], "sparse_depth_loss.depth")
    check_shape(uv, [depth.shape[0], "M", 2], "sparse_depth_loss.uv")
    check_shape(d, [depth.shape[0], uv.shape[1]], "sparse_depth_loss.d")
    check_shape(mask, [depth.shape[0], uv.shape[1]], "sparse_depth_loss.mask")
    depth = _f(depth)
    uv, d = _f(uv).to(depth.dtype), _f(d).to(depth.dtype)
    mask = mask.bool() & (d > 0)
    if uv.shape[1] == 0:
        return depth.sum() * 0.0
    pred = sample_depth(depth, uv)
    d_safe = torch.where(mask, d, torch.ones_like(d))
    err = (1.0 / pred - 1.0 / d_safe).abs()  # Eq. 6
    return _masked_mean_per_image(err, mask)


@_fp32
def label_scale(depth: torch.Tensor, uv: torch.Tensor, d: torch.Tensor, mask: torch.Tensor,
                pooled: bool = False) -> torch.Tensor:
    """Per image (``pooled``: one for the batch, over all its points), the median over its map points of
    ``D_sparse / D``: the map's units per unit of predicted depth.

    ``adapt.scale: align`` / ``align_batch`` multiply the predicted depth by it before L_train and L_val, so the losses
    ask the network for the depth's shape in the map's units without asking it to move its own scale to the map's
    arbitrary one (README "Adapting without picking a rate"). The factor keeps its gradient: ``D·s`` is then
    exactly invariant to the network's global scale, which no loss can push. (Detached, the losses still pull
    on that scale and the alignment undoes every answer: the scale ran away until the sigmoid saturated and
    the gradients vanished, measured on tum_fr1_xyz.)

    Args:
        depth: ``(B, 1, H, W)`` predicted depth. uv, d, mask: the map points, see :func:`sparse_depth_loss`.

    Returns:
        ``(B,)`` float32, differentiable in ``depth``; 1 for an image without a valid map point.
    """
    if uv.shape[1] == 0:
        return torch.ones(depth.shape[0], dtype=torch.float32, device=depth.device)
    pred = sample_depth(_f(depth).float(), _f(uv).float())
    valid = mask.bool() & (d > 0)
    one = torch.ones((), dtype=torch.float32, device=depth.device)
    if pooled and bool(valid.any()):  # one scale for the whole batch: the images' relative scales are learnt
        return (d[valid].float() / pred[valid].clamp_min(1e-6)).median().expand(depth.shape[0])
    return torch.stack([(d[b][valid[b]].float() / pred[b][valid[b]].clamp_min(1e-6)).median()
                        if bool(valid[b].any()) else one for b in range(depth.shape[0])])


@_fp32
def smoothness_loss(depth: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Edge-aware smoothness L_smooth (Eq. 7) on **mean-normalised inverse depth**.

    The paper writes ∂D; like Monodepth2 (which the paper follows for its loss) we apply
    it to ``disp / mean(disp)`` with ``disp = 1/D``: that is invariant to the scale of the
    depth (VO map units are arbitrary) and cannot be lowered by shrinking the depth range,
    whereas raw-depth gradients grow with depth and would penalise far structure most.

    Args:
        depth: ``(B, 1, H, W)`` predicted depth (> 0).
        image: ``(B, 3, H, W)`` the image in [0, 1].

    Returns:
        0-d tensor: ``mean|∂x d̂|·e^{−|∂x I|} + mean|∂y d̂|·e^{−|∂y I|}`` (channel-averaged |∂I|).
    """
    check_shape(depth, ["B", 1, "H", "W"], "smoothness_loss.depth")
    check_shape(image, [depth.shape[0], "C", depth.shape[2], depth.shape[3]], "smoothness_loss.image")
    depth, image = _f(depth), _f(image).to(_f(depth).dtype)
    disp = 1.0 / depth
    disp = disp / (disp.mean((2, 3), keepdim=True) + 1e-7)
    gdx = (disp[..., :, :-1] - disp[..., :, 1:]).abs()
    gdy = (disp[..., :-1, :] - disp[..., 1:, :]).abs()
    gix = (image[..., :, :-1] - image[..., :, 1:]).abs().mean(1, keepdim=True)
    giy = (image[..., :-1, :] - image[..., 1:, :]).abs().mean(1, keepdim=True)
    return (gdx * torch.exp(-gix)).mean() + (gdy * torch.exp(-giy)).mean()  # Eq. 7


@_fp32
def train_loss(depth: torch.Tensor, target: torch.Tensor, sources: list[torch.Tensor], K: torch.Tensor,
               T_t2s: list[torch.Tensor], uv: torch.Tensor, d: torch.Tensor, mask: torch.Tensor,
               lambda_sparse: float = 0.1, lambda_smooth: float = 0.1,
               alpha: float = 0.85) -> tuple[torch.Tensor, dict[str, float]]:
    """L_train = L_photo + λ1·L_sparse + λ2·L_smooth (Eq. 8), averaged over the batch images.

    Args:
        depth: ``(B, 1, H, W)`` predicted depth of the targets (e.g. B = 2: recent + replayed).
        target: ``(B, 3, H, W)`` target keyframes in [0, 1].
        sources: adjacent keyframes (``s ∈ {i−1, i+1}``), each ``(B, 3, H, W)``.
        K: ``(B, 3, 3)`` intrinsics at this resolution.
        T_t2s: per source ``(B, 4, 4)`` target → source camera transforms (VO poses).
        uv, d, mask: sparse map points, see :func:`sparse_depth_loss`.
        lambda_sparse: λ1 (paper 0.1). lambda_smooth: λ2 (paper 0.1). alpha: α of Eq. 4.

    Returns:
        ``(loss, parts)`` with ``parts = {"photo", "sparse", "smooth", "total"}`` as floats.
    """
    l_photo = photometric_loss(target, sources, depth, K, T_t2s, alpha)
    l_sparse = sparse_depth_loss(depth, uv, d, mask)
    l_smooth = smoothness_loss(depth, target)
    total = l_photo + lambda_sparse * l_sparse + lambda_smooth * l_smooth  # Eq. 8
    values = torch.stack([l_photo, l_sparse, l_smooth, total]).detach().tolist()  # one device → host copy
    parts = dict(zip(("photo", "sparse", "smooth", "total"), values))
    return total, parts
