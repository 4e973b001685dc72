"""The adapted network in the front end (:mod:`mutualslam_cli.vo.depth_prior`): the scale check, depth seeds,
the windowed BA's scale prior, and a front end that asks the network only about frames it has seen."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synth import make_tum_dir

from mutualslam_cli.config import CONFIG_DIR, load_config
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.vo.local_ba import BAProblem, solve
from mutualslam_cli.vo.scale_check import MIN_REL_SIGMA, ScaleCheck
from mutualslam_cli.vo.source import FrontEndSource

SIZE = (64, 48)


def _uv(rng, n=200):
    return np.c_[rng.uniform(0, SIZE[0] - 1, n), rng.uniform(0, SIZE[1] - 1, n)]


def test_the_scale_check_sees_the_map_drift_the_network_does_not(rng):
    truth = rng.uniform(1.0, 3.0, (SIZE[1], SIZE[0]))  # the scene's depth (m); the network says half of it
    check = ScaleCheck(lambda frame: truth / 2.0, SIZE)
    uv = _uv(rng)
    z = truth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
    for kf, s in enumerate([1.0, 1.0, 1.0, 1.3]):  # the map's unit: 1 m, then 1.3 m per metre (drift)
        rec = check.keyframe(kf, 10 * kf, 0, uv, s * z)
    assert rec.ratio == pytest.approx(2.6, rel=1e-6)
    assert rec.ref == pytest.approx(2.0)
    assert rec.drift == pytest.approx(1.3)
    assert check.keyframe(9, 90, 1, uv, z).ref != check.keyframe(10, 91, 1, uv, z).ref  # another unit: its own
    assert check.summary()["drift_max"] == pytest.approx(1.3)
    # too few points with a prediction: no check, nothing recorded
    n = len(check.checks)
    assert check.keyframe(11, 92, 0, uv[:5], z[:5]) is None
    assert len(check.checks) == n


def test_depth_seeds_start_at_the_networks_depth_in_the_maps_unit(rng):
    truth = rng.uniform(1.0, 3.0, (SIZE[1], SIZE[0]))
    noisy = truth * np.exp(rng.normal(0, 0.2, truth.shape))  # the network: right on average, 20 % off per pixel
    check = ScaleCheck(lambda frame: noisy / 4.0, SIZE)
    uv = _uv(rng)
    z = truth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
    rec = check.keyframe(0, 0, 0, uv, z)
    assert rec.ratio == pytest.approx(4.0, rel=0.05)
    assert rec.rel_sigma == pytest.approx(0.2, rel=0.25)
    assert rec.rel_sigma >= MIN_REL_SIGMA
    px = np.array([[10.0, 20.0], [40.0, 5.0]])
    f_z = np.array([0.9, 0.8])
    mu, sigma2 = check.seeds(rec, px, f_z)
    d = noisy[[20, 5], [10, 40]]
    np.testing.assert_allclose(mu, f_z / (rec.ratio * d / 4.0))  # inverse distance along the bearing
    np.testing.assert_allclose(np.sqrt(sigma2), mu * rec.rel_sigma)


def _two_view_problem(prior: float | None):
    """Two keyframes 1 cm apart (a fixed host and a free one) seeing points at 2 m: depth barely observable."""
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-1, 1, 60), rng.uniform(-0.7, 0.7, 60), rng.uniform(1.8, 2.2, 60)]
    T0 = np.eye(4)
    T1 = np.eye(4)
    T1[:3, 3] = [-0.01, 0, 0]
    ray = np.c_[X[:, :2] / X[:, 2:3], np.ones(60)]
    Xc = X + T1[:3, 3]
    obs = Xc[:, :2] / Xc[:, 2:3] + rng.normal(0, 0.002, (60, 2))
    prob = BAProblem(np.stack([T0, T1]), np.array([False, True]), np.zeros(60, int), ray, 1.0 / (1.3 * X[:, 2]),
                     np.arange(60), np.ones(60, int), obs)
    if prior is not None:  # the network's depth at the reference scale: the true one here
        prob.prior_rho, prob.prior_w = 1.0 / X[:, 2], 0.002 / 0.3
    return prob, X


def test_the_scale_prior_holds_points_the_views_cannot_place():
    free, X = _two_view_problem(None)
    held, _ = _two_view_problem(1.0)
    _, rho_free, _ = solve(free, huber=0.004, iters=10)
    _, rho_held, _ = solve(held, huber=0.004, iters=10)
    err = lambda rho: np.median(np.abs(np.log(1.0 / rho / X[:, 2])))  # noqa: E731
    assert err(rho_free) > 0.15  # 1 cm of baseline cannot undo a 30 % depth error
    assert err(rho_held) < 0.5 * err(rho_free)
    # without a prior the problem is the one it always was: the same numbers
    bare = dataclasses.replace(free, prior_rho=np.full(60, np.nan), prior_w=1.0)
    np.testing.assert_array_equal(solve(bare, huber=0.004, iters=10)[1], rho_free)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return load_sequence(make_tum_dir(tmp_path_factory.mktemp("depth_prior"), scene="room", n=30, width=320,
                                      height=240))


@pytest.mark.parametrize("on", [False, True])
def test_the_front_end_asks_the_network_only_about_its_keyframes_as_they_come(seq, on, tmp_path):
    flag = str(on).lower()
    cfg = load_config(CONFIG_DIR / "smoke.yaml", ["vo.mode=svo", "vo.max_fts=300", "vo.kf_min_parallax_px=8",
                                                  f"vo.depth_seeds={flag}", f"vo.scale_prior={flag}"])
    asked: list[tuple[int, int]] = []
    source = FrontEndSource(seq, cfg, tmp_path, live_feedback=True)

    def hint(frame: int) -> np.ndarray:
        asked.append((frame, source.frame + 1))  # the frame asked about, the frame being processed
        return np.full((240, 320), 2.0)

    source.use_network(hint)
    source.run_all()
    vo = source.result()
    source.close()
    if not on:
        assert asked == []
        assert source.changed_at is None
        return
    kf_frames = [k.frame_index for k in vo.keyframes]
    assert asked
    assert all(f == now for f, now in asked)
    assert {f for f, _ in asked} <= set(kf_frames)
    assert source.changed_at == asked[0][0] - 1  # the journal is the network-free front end up to there
    assert vo.meta["scale_check"]["checks"] >= 1
    T = se3_inv(vo.keyframes[-1].pose)
    assert np.isfinite(T).all()
