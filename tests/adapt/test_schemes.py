"""Schemes registry, batch selection and the keyframe buffer (replay, neighbours, eviction, BA feedback)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import torch

from mutualslam_cli.adapt.buffer import KeyframeBuffer, KeyframeSample
from mutualslam_cli.adapt.schemes import SCHEMES, get_scheme
from mutualslam_cli.errors import ConfigError, KeyframeError, ShapeError


def sample(k: int, m: int = 3) -> KeyframeSample:
    return KeyframeSample(kf_id=k, image=torch.full((3, 4, 6), k / 100.0), K=torch.eye(3), pose=np.eye(4),
                          uv=torch.zeros(m, 2), depth=torch.full((m,), 1.0 + k))


def filled(n: int, capacity: int = 0, val_every: int = 0) -> KeyframeBuffer:
    b = KeyframeBuffer(capacity, seed=0)
    for k in range(n):
        b.add(sample(k), training=not (val_every and k > 0 and k % val_every == 0))
    return b


def test_registry_names_and_unknown():
    assert set(SCHEMES) == {"none", "recent", "replay", "ewc", "replay+ewc", "replay+mas", "replay+si", "luo", "comoda"}
    with pytest.raises(ConfigError) as e:
        get_scheme("replay+foo")
    assert "replay+ewc" in str(e.value)
    assert "'luo'" in str(e.value)
    assert "replay+foo" in str(e.value)


@pytest.mark.parametrize(("name", "reg"), [("none", None), ("recent", None), ("replay", None), ("ewc", "ewc"),
                                      ("replay+ewc", "ewc"), ("replay+mas", "mas"), ("replay+si", "si"),
                                      ("luo", None)])
def test_scheme_regularizer(name, reg):
    assert get_scheme(name).regularizer == reg


def test_recent_selects_two_newest_training():
    b = filled(11, val_every=5)  # ids 5, 10 are validation
    rng = np.random.default_rng(0)
    assert get_scheme("recent").select(b, 9, rng) == [9, 8]
    b.add(sample(11), training=True)
    assert get_scheme("recent").select(b, 11, rng) == [11, 9]
    assert get_scheme("ewc").select(b, 11, rng) == [11, 9]
    assert get_scheme("none").select(b, 11, rng) == []


def test_replay_uniform_over_older_training_and_seeded():
    b = filled(12, val_every=5)
    sch = get_scheme("replay")
    draws = [sch.select(b, 11, np.random.default_rng(s)) for s in range(3)]
    again = [sch.select(b, 11, np.random.default_rng(s)) for s in range(3)]
    assert draws == again
    rng = np.random.default_rng(1)
    counts = Counter(sch.select(b, 11, rng)[1] for _ in range(4000))
    older = [0, 1, 2, 3, 4, 6, 7, 8, 9]  # training ids < 11 (0..10 minus 5, 10)
    assert sorted(counts) == older
    freq = np.array([counts[k] for k in older]) / 4000
    assert np.all(np.abs(freq - 1 / 9) < 0.025)


def test_replay_first_keyframes():
    b = filled(1)
    assert get_scheme("replay").select(b, 0, np.random.default_rng(0)) == [0]
    b.add(sample(1), training=True)
    assert get_scheme("replay").select(b, 1, np.random.default_rng(0)) == [1, 0]


def test_neighbours_skip_validation_keyframes():
    b = filled(12, val_every=5)
    assert b.neighbours(4) == [3, 6]
    assert b.neighbours(6) == [4, 7]
    assert b.neighbours(0) == [1]
    assert b.neighbours(11) == [9]
    assert b.neighbours(5) == []  # validation keyframe: not a training target
    assert b.validation_ids == [5, 10]


@pytest.mark.parametrize("cap", [3, 5, 8])
def test_capacity_never_exceeded_and_reservoir_uniform(cap):
    hits = Counter()
    for seed in range(300):
        b = KeyframeBuffer(cap, seed=seed)
        for k in range(40):
            b.add(sample(k), training=True)
            train = b.training_ids
            # replay candidates (reservoir) + recent window of two never exceed the capacity
            assert len(b.replay_candidates(k + 1)) <= cap
            assert len(train) <= 3 * cap
            assert {k - 1, k} & set(train) == {k - 1, k} - {-1}
        hits.update(x for x in b._train_res.items)
    # reservoir over ids 0..37: roughly uniform inclusion
    freq = np.array([hits[k] for k in range(38)]) / (300 * (cap - 2))
    assert freq.max() < 3 / 38
    assert freq.min() > 0.2 / 38


def test_capacity_replay_sources_kept():
    b = filled(30, capacity=4)
    for k in b.replay_candidates(29):
        assert b.neighbours(k)  # every replay candidate keeps ≥ 1 photometric source


def test_bad_capacity():
    with pytest.raises(ConfigError):
        KeyframeBuffer(2)


def test_update_poses_and_sparse_feed_back():
    b = filled(4)
    T = np.eye(4)
    T[0, 3] = 1.5
    assert b.update_poses({2: T, 99: T}) == 1
    assert np.array_equal(b.get(2).pose, T)
    assert np.array_equal(b.get(1).pose, np.eye(4))
    assert np.array_equal(b.pose(2), T)  # the pose alone (scheme luo's pair rule reads it)
    b.pose(2)[0, 3] = 9.0  # a copy: the stored pose is untouched
    assert b.pose(2)[0, 3] == 1.5
    with pytest.raises(KeyframeError):
        b.pose(99)
    assert b.update_sparse({3: (torch.ones(5, 2), torch.full((5,), 7.0))}) == 1
    assert b.get(3).uv.shape == (5, 2)
    assert float(b.get(3).depth[0]) == 7.0
    with pytest.raises(ShapeError):
        b.update_poses({1: np.eye(3)})
    with pytest.raises(ShapeError):
        b.update_sparse({1: (torch.ones(5, 2), torch.ones(4))})


def test_bad_sample_and_order():
    b = KeyframeBuffer()
    bad = sample(0)
    bad.uv = torch.zeros(3, 3)
    with pytest.raises(ShapeError):
        b.add(bad, training=True)
    b.add(sample(3), training=True)
    with pytest.raises(KeyframeError):
        b.add(sample(2), training=True)


def test_buffer_holds_one_uint8_copy_of_each_image():
    # an 8-bit image at network resolution (what the pipeline stores) is kept once, as uint8: 3·H·W bytes
    h, w = 48, 64
    b = KeyframeBuffer()
    for k in range(10):
        img = torch.randint(0, 256, (3, h, w)).float() / 255.0
        b.add(KeyframeSample(k, img, torch.eye(3), np.eye(4), torch.zeros(5, 2), torch.ones(5)), training=True)
        assert torch.equal(b.get(k).image, img)
    meta = 10 * (9 * 4 + 5 * 2 * 4 + 5 * 4)  # K, uv, depth (float32) of each keyframe
    assert b.nbytes == 10 * 3 * h * w + meta
