"""The bf16 fast path trains what fp32 trains (issue 46): no gradient that fp32 has is lost to bf16.

Runs where the CPU has native bf16 (AMX or AVX512-BF16) and says it skipped elsewhere. The network is the
default pre-trained model at the run's 640×192 on a rendered textured plane, the loss the run's L_train
(photometric to a neighbour + sparse depth + smoothness).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from mutualslam_cli.adapt import losses
from mutualslam_cli.adapt.depthnet import fast_context, fast_path_supported, prepare
from mutualslam_cli.adapt.regularizers import trainable
from mutualslam_cli.adapt.weights import load_default

pytestmark = pytest.mark.skipif(not fast_path_supported(), reason="this CPU has no native bf16 (AMX / AVX512-BF16)")

H, W = 192, 640
K = torch.tensor([[[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]]])


def _image(shift: float) -> torch.Tensor:
    """A smooth colour texture on a fronto-parallel plane, seen from ``shift`` (metres along x) at 2 m."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    X, Y = (u - W / 2) / 300.0 * 2.0 + shift, (v - H / 2) / 300.0 * 2.0
    chans = [0.5 + 0.2 * np.sin(a * X + c) * np.cos(b * Y) + 0.15 * np.sin(23 * X + 17 * Y + c)
             for c, (a, b) in enumerate([(7.0, 5.0), (11.0, 3.0), (4.0, 13.0)])]
    return torch.tensor(np.clip(np.stack(chans), 0, 1), dtype=torch.float32)[None]


def _grads(net: nn.Module, fast: bool) -> list[torch.Tensor]:
    target, source = _image(0.0), _image(0.05)
    T = torch.eye(4)[None]
    T[0, 0, 3] = -0.05  # target → source camera
    rng = np.random.default_rng(0)
    uv = torch.tensor(np.stack([rng.integers(0, W, 200), rng.integers(0, H, 200)], 1), dtype=torch.float32)[None]
    with fast_context(fast):
        depth = net.predict(target).float()
    loss, _ = losses.train_loss(depth, target, [source], K, [T], uv, torch.full((1, 200), 2.0),
                                torch.ones(1, 200, dtype=torch.bool), 0.1, 0.1, 0.85)
    params = trainable(net)
    return [torch.zeros_like(p) if g is None else g for p, g in
            zip(params, torch.autograd.grad(loss, params, allow_unused=True))]


def _lost_share(net: nn.Module) -> dict[str, float]:
    """Per parameter tensor: the share of its entries with an fp32 gradient whose bf16 gradient is exactly 0."""
    names = [n for n, p in net.named_parameters() if p.requires_grad]
    g32, g16 = _grads(net, False), _grads(net, True)
    return {n: float(((a != 0) & (b == 0)).sum()) / max(int((a != 0).sum()), 1) for n, a, b in zip(names, g32, g16)}


@pytest.fixture(scope="module")
def net() -> nn.Module:
    torch.manual_seed(0)
    return prepare(load_default().eval(), True)


def test_bf16_loses_no_gradient_fp32_has(net):
    lost = _lost_share(net)
    worst = max(lost, key=lost.get)
    assert lost[worst] < 0.02, f"{worst}: {100 * lost[worst]:.1f} % of its fp32 gradient entries are 0 in bf16"


def test_an_in_place_elu_would_lose_them(net):
    """The check above can fail: Monodepth2's in-place ELU (backward from its output, which rounds to −1 in bf16)
    zeroes the gradient of whole decoder channels."""
    elus = [m for m in net.modules() if isinstance(m, nn.ELU)]
    try:
        for m in elus:
            m.inplace = True
        lost = _lost_share(net)
    finally:
        for m in elus:
            m.inplace = False
    assert max(lost.values()) > 0.05
