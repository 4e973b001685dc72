"""The heap-retention switch used by the VO and `mslam run`."""

from __future__ import annotations

import platform
import resource
import subprocess
import sys

import pytest

from mutualslam_cli.allocator import retain_freed_memory


def test_retain_is_idempotent_and_reports_glibc():
    first = retain_freed_memory()
    assert retain_freed_memory() is first
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert first is True


# Runs in a fresh process: warm-up, then one more round of the same image-sized work, counting the
# page faults of that round. OpenCV on one thread, so which thread's arena serves a buffer does not
# depend on the machine's core count or scheduling.
_PROBE = """
import resource, sys
import cv2, numpy as np
from mutualslam_cli.allocator import retain_freed_memory
cv2.setNumThreads(1)
assert retain_freed_memory()
img = (np.random.default_rng(0).random((480, 640)) * 255).astype(np.uint8)
def work():
    for _ in range(5):
        cv2.cornerMinEigenVal(img, 3, 3)
        cv2.calcOpticalFlowPyrLK(img, img, np.float32([[100, 100]]).reshape(-1, 1, 2), None)
work()
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
work()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc mallopt only")
def test_repeated_image_buffers_stop_faulting_pages():
    """After warm-up, freeing and re-allocating image-sized buffers maps (almost) no new pages.

    The bound is a share of what the round allocates, in this machine's pages: each
    ``cornerMinEigenVal`` makes a float32 response and a 3-channel float32 covariance image
    (4 × 480 × 640 × 4 bytes); without retention each call would fault them afresh."""
    out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    faults = int(out.stdout.strip())
    pages_per_round = 5 * 4 * 480 * 640 * 4 // resource.getpagesize()
    assert faults < 0.05 * pages_per_round, (faults, pages_per_round)
