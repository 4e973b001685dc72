"""Scheme ``luo`` (Luo et al.'s baseline): the stereo-pair rule, its batches, and that other schemes are unchanged."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_online import SCENE, K, flat, make_net, render

from mutualslam_cli.adapt.buffer import KeyframeBuffer, KeyframeSample
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.adapt.schemes import SCHEMES, get_scheme
from mutualslam_cli.adapt.schemes.luo import is_stereo_pair, stereo_measures
from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.geometry import exp_so3, se3_inv
from mutualslam_cli.online.rows import step_columns

torch.set_num_threads(1)


def pose(t=(0.0, 0.0, 0.0), rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.asarray([rotvec], dtype=np.float64))[0]
    T[:3, 3] = t
    return T


def deg(a: float) -> float:
    return math.radians(a)


# ---------------------------------------------------------------- the pair rule


def test_pure_horizontal_translation_is_a_pair_either_side():
    for tx in (0.1, -0.1, 3.0):
        ratio, rot = stereo_measures(pose(), pose((tx, 0, 0)))
        assert ratio == pytest.approx(1.0)
        assert rot == pytest.approx(0.0, abs=1e-6)
        assert is_stereo_pair(pose(), pose((tx, 0, 0)))


@pytest.mark.parametrize("t", [(0, 0, 0.1), (0, 0.1, 0), (0.05, 0, 0.1), (0.05, 0.05, 0.05)])
def test_forward_vertical_or_mixed_motion_is_not(t):
    assert not is_stereo_pair(pose(), pose(t))


def test_translation_is_judged_in_the_target_camera_frame():
    # Both cameras share an oblique orientation R; the other sits along the target's own x axis.
    R = exp_so3(np.array([[0.4, -0.7, 0.5]]))[0]
    Tt = pose((1.0, 2.0, -0.5))
    Tt[:3, :3] = R
    To = Tt.copy()
    To[:3, 3] = Tt[:3, 3] + R @ np.array([0.2, 0.0, 0.0])
    ratio, rot = stereo_measures(Tt, To)
    assert ratio == pytest.approx(1.0)
    assert rot == pytest.approx(0.0, abs=1e-6)
    # The same world displacement along the world x axis is not along the camera's x axis.
    Tw = Tt.copy()
    Tw[:3, 3] = Tt[:3, 3] + np.array([0.2, 0.0, 0.0])
    assert stereo_measures(Tt, Tw)[0] == pytest.approx(abs(R[0, 0]))
    assert not is_stereo_pair(Tt, Tw)


def test_rotation_angle_and_its_limit():
    for a in (3.0, 10.0, 30.0):
        assert stereo_measures(pose(), pose((0.1, 0, 0), (0, deg(a), 0)))[1] == pytest.approx(a)
    panning = pose((0.1, 0, 0), (0, deg(10.0), 0))  # x baseline but a 10° yaw: rotation-heavy
    assert not is_stereo_pair(pose(), panning)
    assert is_stereo_pair(pose(), panning, max_rotation_deg=10.5)
    assert is_stereo_pair(pose(), pose((0.1, 0, 0), (deg(4.9), 0, 0)))
    assert not is_stereo_pair(pose(), pose((0.1, 0, 0), (deg(5.1), 0, 0)))


def test_ratio_boundary_follows_the_setting():
    T = pose((0.8, 0.6, 0.0))  # |t_x| / ‖t‖ = 0.8 exactly
    assert stereo_measures(pose(), T)[0] == pytest.approx(0.8)
    assert is_stereo_pair(pose(), T, min_horizontal_ratio=0.8 - 1e-9)
    assert not is_stereo_pair(pose(), T, min_horizontal_ratio=0.81)
    oblique = pose((0.6, 0.0, 0.8))  # ratio 0.6
    assert not is_stereo_pair(pose(), oblique)
    assert is_stereo_pair(pose(), oblique, min_horizontal_ratio=0.55)


def test_zero_baseline_is_never_a_pair():
    assert math.isnan(stereo_measures(pose(), pose())[0])
    assert not is_stereo_pair(pose(), pose(), min_horizontal_ratio=0.0, max_rotation_deg=180.0)
    assert is_stereo_pair(pose(), pose((0, 0, 0.1)), min_horizontal_ratio=0.0)  # 0 admits any baseline


# ---------------------------------------------------------------- the scheme on a buffer


def sample(k: int, t=(0.0, 0.0, 0.0), rotvec=(0.0, 0.0, 0.0)) -> KeyframeSample:
    return KeyframeSample(kf_id=k, image=torch.full((3, 4, 6), k / 100.0), K=torch.eye(3), pose=pose(t, rotvec),
                          uv=torch.zeros(2, 2), depth=torch.ones(2))


def test_registry_and_settings():
    assert "luo" in SCHEMES
    assert get_scheme("luo").regularizer is None
    assert get_scheme("luo").make_regularizer(torch.nn.Linear(2, 2), AdaptConfig()) is None
    with pytest.raises(ConfigError) as e:
        get_scheme("lou")
    assert "'luo'" in str(e.value)
    for bad in ({"luo_window": 1}, {"luo_min_horizontal_ratio": 1.5}, {"luo_max_rotation_deg": -1.0}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            get_scheme("luo", AdaptConfig(**bad))


def test_only_recent_targets_no_replay_no_random_draws():
    b = KeyframeBuffer()
    sch, rng = get_scheme("luo"), np.random.default_rng(0)
    for k in range(30):  # every pair is a stereo pair: a camera sliding sideways
        b.add(sample(k, (0.05 * k, 0, 0)), training=True)
        state = rng.bit_generator.state
        batch = sch.select(b, k, rng)
        assert rng.bit_generator.state == state  # nothing is sampled
        assert batch == ([k, k - 1] if k else [])
        for tgt in batch:
            assert set(sch.sources(b, tgt)) <= set(b.recent(3)) - {tgt}
    assert sch.sources(b, 10) == []  # an old keyframe is nobody's target or source any more
    assert sch.sources(b, 29) == [28, 27]
    assert sch.sources(b, 28) == [29, 27]


def test_partners_window_and_validation_keyframes():
    b = KeyframeBuffer()
    b.add(sample(0), training=True)
    b.add(sample(1, (0, 0, 0.1)), training=True)  # forward
    b.add(sample(2, (0.1, 0, 0.1)), training=False)  # validation: a perfect pair with 3, never a source
    b.add(sample(3, (0.1, 0, 0.2)), training=True)  # forward again
    b.add(sample(4, (0.1, 0, 0.0)), training=True)  # x-pair with 0 only (to 3: (0, 0, −0.2))
    three, four = get_scheme("luo"), get_scheme("luo", AdaptConfig(luo_window=4))
    assert b.recent(4) == [4, 3, 1, 0]
    assert three.sources(b, 4) == []
    assert three.select(b, 4, np.random.default_rng(0)) == []
    assert four.sources(b, 4) == [0]
    assert four.select(b, 4, np.random.default_rng(0)) == [4]
    assert three.sources(b, 3) == []
    assert get_scheme("recent").sources(b, 3) == [1, 4]
    b.add(sample(5, (0.1, 0, 0.2), (0, deg(3.0), 0)), training=True)  # 3's place, yawed 3°
    assert three.sources(b, 5) == []  # no baseline to 3, forward to 4


@pytest.mark.parametrize("name", sorted(set(SCHEMES) - {"luo"}))
def test_other_schemes_keep_the_time_adjacent_sources(name):
    b = KeyframeBuffer()
    for k in range(12):
        b.add(sample(k, (0.05 * k, 0, 0)), training=not (k and k % 5 == 0))
    sch = get_scheme(name)
    for k in b.all_ids:
        assert sch.sources(b, k) == b.neighbours(k)


# ---------------------------------------------------------------- the adapter

# Positions of 10 keyframes (no rotation): sideways steps (stereo pairs) mixed with forward and
# vertical ones. Keyframe 5 is Alg. 1's validation keyframe (m = 5).
PATH = [(0, 0, 0), (0.08, 0, 0), (0.08, 0, 0.12), (0.08, 0.10, 0.12), (0.16, 0.10, 0.12), (0.24, 0.10, 0.12),
        (0.24, 0.10, 0.26), (0.32, 0.10, 0.26), (0.32, 0.10, 0.38), (0.40, 0.10, 0.38)]


def mixed_scene(m: int = 40, seed: int = 0) -> list[KeyframeSample]:
    rng = np.random.default_rng(seed)
    out = []
    h, w = SCENE[0].image.shape[1:]
    for k, t in enumerate(PATH):
        T = pose(t)
        img, depth = render(T)
        uv = np.stack([rng.integers(0, w, m), rng.integers(0, h, m)], 1)
        out.append(KeyframeSample(k, torch.tensor(img, dtype=torch.float32), torch.tensor(K, dtype=torch.float32), T,
                                  torch.tensor(uv, dtype=torch.float32),
                                  torch.tensor(depth[uv[:, 1], uv[:, 0]], dtype=torch.float32)))
    return out


MIXED = mixed_scene()


def adapt(scheme: str, scene: list[KeyframeSample], adapter: type[OnlineAdapter] = OnlineAdapter,
          **over) -> OnlineAdapter:
    ad = adapter(make_net(), AdaptConfig(scheme=scheme, steps_per_keyframe=2, **over), K, seed=3)
    for s in scene:
        ad.add_keyframe(s)
    return ad


def test_luo_adapter_trains_on_stereo_pairs_and_records_them():
    ad = adapt("luo", MIXED)
    hist = ad.history
    assert [h.sources for h in hist] == [[], [0], [], [], [3], [], [], [6], [], [8]]
    assert sum(bool(h.sources) for h in hist) == 4  # keyframes that found a stereo partner
    assert [step_columns(h)["sources"] for h in hist][:5] == ["", "0", "", "", "3"]
    # Targets: the recent two that have a partner; 3 finds none and trains nothing.
    assert {h.kf_id: h.batch for h in hist if h.trained} == {1: [1, 0], 2: [1], 4: [4, 3], 6: [4], 7: [7, 6],
                                                              8: [7], 9: [9, 8]}
    assert not hist[3].trained
    assert not hist[0].trained
    assert [h.kf_id for h in hist if h.is_validation] == [5]
    assert hist[5].l_val is not None
    for h in hist:
        if h.trained:
            assert all(math.isfinite(v) for v in h.loss.values())
            assert h.loss["penalty"] == 0.0
    assert ad.regularizer is None
    assert len(ad.finetune_ms) == 7
    assert not torch.equal(flat(ad.net), flat(make_net()))
    # The batch warps each target from its partner (relative pose T_t2s = T_cw(src) · T_wc(tgt)).
    assert ad._make_batch([4, 3]) is None  # out of the window of the 3 most recent by now
    early = adapt("luo", MIXED[:5])
    b = early._make_batch([4, 3])
    assert b is not None
    assert b.ids == [4, 3]
    assert len(b.sources) == 1
    assert torch.equal(b.sources[0][0], early.buffer.get(3).image)
    assert torch.equal(b.sources[0][1], early.buffer.get(4).image)
    np.testing.assert_allclose(b.T_t2s[0][0].numpy(), se3_inv(pose(PATH[3])) @ pose(PATH[4]), atol=1e-6)


def test_luo_settings_reach_the_adapter():
    loose = adapt("luo", MIXED, luo_min_horizontal_ratio=0.5)  # admits (0.08, 0, 0.12)-like steps
    strict = adapt("luo", MIXED)
    assert sum(bool(h.sources) for h in loose.history) > sum(bool(h.sources) for h in strict.history)


class _NeighbourSources:
    """A scheme whose photometric sources are always ``buffer.neighbours`` (Eq. 3): the batches as
    they were before schemes chose their sources."""

    def __init__(self, scheme):
        self._scheme = scheme

    def __getattr__(self, name):
        return getattr(self._scheme, name)

    def sources(self, buffer, kf_id):
        return buffer.neighbours(kf_id)


class OldBatches(OnlineAdapter):
    """The adapter with the sources of :class:`_NeighbourSources`."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.scheme = _NeighbourSources(self.scheme)


@pytest.mark.parametrize("scheme", ["recent", "replay+ewc"])
def test_other_schemes_train_bit_identically_to_the_old_batches(scheme):
    new, old = adapt(scheme, SCENE[:8]), adapt(scheme, SCENE[:8], OldBatches)
    assert [h.batch for h in new.history] == [h.batch for h in old.history]
    assert [h.loss for h in new.history] == [h.loss for h in old.history]
    assert torch.equal(flat(new.net), flat(old.net))


def test_old_batches_would_change_luo():
    """The comparison above has teeth: with the old sources, ``luo`` trains differently."""
    new, old = adapt("luo", MIXED), adapt("luo", MIXED, OldBatches)
    assert not torch.equal(flat(new.net), flat(old.net))


def test_run_summary_counts_luo_keyframes_with_a_stereo_partner(tiny_run):
    import pandas as pd

    from mutualslam_cli.config import CONFIG_DIR, load_config
    from mutualslam_cli.pipeline import run_sequence

    tmp, seq = tiny_run
    # a wide rule (any baseline, any rotation) so this toy sequence's keyframes find partners
    cfg = load_config(CONFIG_DIR / "smoke.yaml", [f"net.weights={tmp / 'weights'}", "adapt.scheme=luo",
                                                  "adapt.luo_min_horizontal_ratio=0", "adapt.luo_max_rotation_deg=180",
                                                  "ba.enabled=false"])
    r = run_sequence(seq, cfg, out=tmp / "luo_count", command=["test"])
    flat = r.summary.flat()
    kf = pd.read_csv(r.folder / "keyframes.csv")
    training = kf[~kf["is_validation"]]
    assert flat["adaptation.training_keyframes"] == len(training)
    assert flat["adaptation.luo_keyframes_with_partner"] == int(training["sources"].notna().sum())
    assert 0 < flat["adaptation.luo_keyframes_with_partner"] < len(training)  # the first keyframe has none
    assert flat["adaptation.keyframes_trained"] == int(kf["trained"].sum()) > 0
