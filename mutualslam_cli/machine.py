"""The CPU a figure was measured on: model, the SIMD flags that decide which kernels numpy, OpenCV,
torch and OpenVINO run, and the kind DESIGN §10 sets its speed targets by."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TypedDict

#: SIMD flags of /proc/cpuinfo worth naming next to timings (numpy, OpenCV and torch pick kernels by them).
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512vl", "avx512_vnni", "avx512_bf16",
              "amx_tile", "amx_bf16", "amx_int8")

#: The CPU kinds of DESIGN §10, most capable first: (name, flags it needs).
KINDS = (("AMX", ("amx_bf16",)), ("AVX512-BF16", ("avx512_bf16",)), ("AVX2", ("avx2",)))


class CpuInfo(TypedDict):
    """:func:`cpu_info`: the model and flags (``None`` where unknown), the kind and the core count."""

    cpu_model: str | None
    cpu_flags: list[str] | None
    cpu_kind: str
    cpu_count: int | None


def cpu_info(cpuinfo: str | None = None) -> CpuInfo:
    """``cpu_model``, ``cpu_flags`` (those of :data:`SIMD_FLAGS` the CPU has), ``cpu_kind``
    (:func:`cpu_kind`) and ``cpu_count``; model and flags ``None`` where /proc/cpuinfo cannot be read.

    Args:
        cpuinfo: the text of /proc/cpuinfo (default: read it).
    """
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return {"cpu_model": None, "cpu_flags": None, "cpu_kind": "unknown", "cpu_count": os.cpu_count()}
    first = cpuinfo.split("\n\n", 1)[0]  # the first processor's block
    info = {k.strip(): v.strip() for k, v in (line.split(":", 1) for line in first.splitlines() if ":" in line)}
    have = set(info.get("flags", "").split())
    flags = [f for f in SIMD_FLAGS if f in have]
    return {"cpu_model": info.get("model name"), "cpu_flags": flags, "cpu_kind": cpu_kind(flags),
            "cpu_count": os.cpu_count()}


def cpu_kind(flags: list[str] | None) -> str:
    """``AMX``, ``AVX512-BF16``, ``AVX2`` or ``other`` (``unknown`` without flags): the first kind of
    :data:`KINDS` whose flags are all present."""
    if flags is None:
        return "unknown"
    return next((name for name, need in KINDS if set(need) <= set(flags)), "other")


def memory_gb() -> float | None:
    """The machine's physical memory in GiB (``None`` where it cannot be read)."""
    try:
        import psutil

        return round(psutil.virtual_memory().total / 1024**3, 2)
    except Exception:  # a missing figure is recorded as such
        return None
