"""The dense stage's depth scalings (:mod:`mutualslam_cli.dense.scaling`): per-frame factors in closed form,
fallbacks, the jitter statistic and the ``dense.scalings`` setting. The stage end to end, with predictions
that are GT depth times a per-frame factor: ``tests/dense/test_dense.py``."""

from __future__ import annotations

import numpy as np
import pytest

from mutualslam_cli.config import load_config
from mutualslam_cli.dense import scaling
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.report import dense as report_dense


def test_gt_factor_is_the_median_ratio_over_valid_pixels():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.5, 4.0, (48, 64))
    gt[:10] = 0.0  # missing GT
    gt[10:12] = 20.0  # beyond max_depth: left out
    pred = gt / 2.5
    pred[40:, :] = 0.0  # no prediction there
    assert scaling.gt_factor(pred, gt, max_depth=10.0) == pytest.approx(2.5, rel=1e-12)
    # a few wild pixels do not move the median
    noisy = pred.copy()
    noisy[20, :5] = 100.0
    assert scaling.gt_factor(noisy, gt, 10.0) == pytest.approx(2.5, rel=1e-12)
    # the prediction is resized to the GT's resolution first (bilinear): a constant scene keeps its ratio
    assert scaling.gt_factor(np.full((24, 32), 0.5), np.full((48, 64), 2.0)) == pytest.approx(4.0)
    assert np.isnan(scaling.gt_factor(pred, np.zeros_like(gt)))


def test_fallback_and_spread():
    own = np.array([2.0, np.nan, 0.5, -1.0, 1.0])
    f, n = scaling.with_fallback(own, 3.0)
    assert n == 2
    assert f.tolist() == [2.0, 3.0, 0.5, 3.0, 1.0]
    assert scaling.with_fallback(own, None) == (None, 2)
    f, n = scaling.with_fallback(np.array([1.0, 2.0]), None)  # nothing missing: no fallback needed
    assert n == 0
    assert f.tolist() == [1.0, 2.0]
    # spread: std of ln over the frames with their own factor
    assert scaling.log_spread(own) == pytest.approx(np.std(np.log([2.0, 0.5, 1.0])))
    assert np.isnan(scaling.log_spread(np.array([1.0, np.nan])))
    assert scaling.median_factor(own) == 1.0
    assert np.isnan(scaling.median_factor(np.array([np.nan])))


def test_scalings_setting():
    assert load_config().dense.scalings == ["sequence", "frame", "gt"]  # all three by default
    assert load_config(overrides=["dense.scalings=[sequence, gt]"]).dense.scalings == ["sequence", "gt"]
    for bad in ("[gt]", "[sequence, sequence]"):
        with pytest.raises(ConfigError, match=r"dense.scalings"):
            load_config(overrides=[f"dense.scalings={bad}"])
    with pytest.raises(ConfigError, match=r"dense.scalings\[1\]"):
        load_config(overrides=["dense.scalings=[sequence, keyframe]"])
    assert set(scaling.PREFIX) == set(scaling.SCALINGS) == set(scaling.DESCRIPTION)
    assert report_dense.PREFIX == scaling.PREFIX  # the report reads the keys the stage writes
    assert scaling.PREFIX["sequence"] == "dense."  # the headline keys stay dense.<metric>.<model>
