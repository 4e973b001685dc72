"""The sequence-scaling sketch is numpy's linear quantiles, to the bit (cached evaluations stay valid)."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.metrics.ratios import SKETCH_POINTS, ratio_sketch


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n", [1, 2, 3, 100, 2049, 50000])
def test_sketch_equals_numpy_quantile(dtype, n):
    rng = np.random.default_rng(n)
    x = (rng.normal(size=n) * 0.4).astype(dtype)
    if n > 1000:
        x[: n // 3] = x[0]  # ties, as planar GT surfaces give
    ref = np.quantile(x, np.linspace(0.0, 1.0, SKETCH_POINTS)).astype(np.float32)
    assert np.array_equal(ratio_sketch(x), ref)
