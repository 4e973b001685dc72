"""Keep freed heap memory in the process (glibc ``mallopt``) so per-frame buffers are reused.

The front end allocates and frees image-sized buffers every frame (KLT pyramids, gradient
images, float copies). With glibc's defaults those come from fresh ``mmap``/``brk`` pages and
are handed back to the kernel on ``free``: every frame then pays hundreds of page faults
(measured on tum_fr1_xyz: ~390 faults and ~4 ms of CPU per frame, 0.2 faults once tuned).
Raising the mmap, trim and top-pad thresholds keeps those pages mapped and reused.

The settings are process-wide and only change *when* memory is returned to the OS, never what
a computation returns. On non-glibc platforms this is a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD_BYTES = 32 << 20
"""Allocations below this come from the heap (glibc's maximum for the dynamic threshold)."""

TOP_PAD_BYTES = 64 << 20
"""Extra heap obtained per ``brk`` growth."""

TRIM_THRESHOLD_BYTES = 256 << 20
"""Free memory at the top of the heap kept before it is returned to the kernel."""

_done: bool | None = None


def retain_freed_memory() -> bool:
    """Apply the thresholds above once per process.

    Returns:
        ``True`` when glibc accepted them (now or on an earlier call), ``False`` elsewhere.
    """
    global _done
    if _done is not None:
        return _done
    _done = False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        log.debug("no glibc mallopt (%s): heap thresholds unchanged", name)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = all(mallopt(k, v) == 1 for k, v in ((_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
                                              (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
                                              (_M_TOP_PAD, TOP_PAD_BYTES)))
    _done = ok
    return ok
