"""The heap-retention switch used by the VO and `mslam run`."""

from __future__ import annotations

import platform
import resource

import cv2
import numpy as np
import pytest

from mutualslam_cli.heap import retain_freed_memory


def test_retain_is_idempotent_and_reports_glibc():
    first = retain_freed_memory()
    assert retain_freed_memory() is first
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert first is True


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc mallopt only")
def test_repeated_image_buffers_stop_faulting_pages():
    """After warm-up, freeing and re-allocating image-sized buffers maps no new pages."""
    assert retain_freed_memory()
    img = (np.random.default_rng(0).random((480, 640)) * 255).astype(np.uint8)

    def work() -> None:
        for _ in range(5):
            cv2.cornerMinEigenVal(img, 3, 3)
            cv2.calcOpticalFlowPyrLK(img, img, np.float32([[100, 100]]).reshape(-1, 1, 2), None)

    work()  # warm-up grows the heap once
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    work()
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0
    # without retention each call faults its ~4 MB of temporaries afresh (~1000 pages per call)
    assert faults < 200, faults
