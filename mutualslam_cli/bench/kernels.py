"""Which oneDNN kernels one fine-tuning step runs: the ISA of each convolution (AMX, AVX512-BF16, AVX2…)
and its data type, read from oneDNN's verbose log of a step in a child process.

On an AMX CPU the bf16 convolutions and their backward should run ``…avx512_core_amx`` kernels; a
convolution in ``f32`` under the fast path is a fall-back (the loss's 3×3 box filter of SSIM is fp32 on
purpose: losses stay fp32). Reorders (layout changes between PyTorch's and oneDNN's blocked formats)
are counted with their time.
"""

from __future__ import annotations

import collections
import contextlib
import os
import subprocess
import sys
from typing import TypedDict

_STEP = """
import torch
from mutualslam_cli.adapt.depthnet import DepthNet, make_adam, prepare
from mutualslam_cli.bench.finetune import finetune_step, make_step_batch
torch.set_num_threads(1)
net = prepare(DepthNet(), {fast})
opt = make_adam(net.parameters(), lr=1e-4)
batch = make_step_batch(640, 192)
finetune_step(net, opt, batch, {fast})
print("STEP-DONE", flush=True)
finetune_step(net, opt, batch, {fast})
"""


class KernelCounts(TypedDict):
    """:func:`parse_verbose`'s counts and summed times (ms)."""

    convolutions: dict[str, int]
    convolution_dtypes: dict[str, int]
    convolution_ms: float
    reorder_ms: float


class KernelNote(TypedDict):
    """Why :func:`step_kernels` has no counts."""

    note: str


def parse_verbose(lines: list[str]) -> KernelCounts:
    """Counts from ``onednn_verbose`` ``exec`` lines: ``convolutions`` {implementation: n},
    ``convolution_dtypes`` {source dtype: n}, ``convolution_ms`` and ``reorder_ms`` (their summed time)."""
    impl: collections.Counter[str] = collections.Counter()
    dtypes: collections.Counter[str] = collections.Counter()
    ms = {"convolution": 0.0, "reorder": 0.0}
    for line in lines:
        f = line.strip().split(",")
        if len(f) < 8 or not f[0].startswith("onednn_verbose") or "exec" not in f:
            continue
        i = f.index("exec")
        kind, name = f[i + 2], f[i + 3]
        if kind in ms:
            with contextlib.suppress(ValueError):  # a verbose line without a time
                ms[kind] += float(f[-1])
        if kind == "convolution":
            impl[name] += 1
            src = next((x for x in f if x.startswith("src:")), "src:?")
            dtypes[src.split(":")[1]] += 1
    return {"convolutions": dict(impl), "convolution_dtypes": dict(dtypes),
            "convolution_ms": ms["convolution"], "reorder_ms": ms["reorder"]}


def step_kernels(fast: bool = True, timeout_s: float = 300.0) -> KernelCounts | KernelNote:
    """:func:`parse_verbose` of the second of two fine-tuning steps (the first creates the primitives), one
    thread; ``{"note": …}`` when the child fails or oneDNN logs nothing (a build without verbose mode)."""
    env = {**os.environ, "ONEDNN_VERBOSE": "1", "DNNL_VERBOSE": "1"}
    r = subprocess.run([sys.executable, "-c", _STEP.format(fast=bool(fast))], capture_output=True, text=True,
                       env=env, timeout=timeout_s)
    if r.returncode != 0:
        return {"note": f"oneDNN probe failed: {r.stderr.strip().splitlines()[-1:]}"}
    out = parse_verbose(r.stdout.split("STEP-DONE", 1)[-1].splitlines())
    return out if out["convolutions"] else {"note": "oneDNN wrote no verbose log (not the oneDNN path?)"}
