"""Culling + global BA as a stage (paper §III-C) and its feedback into training (the mutual loop)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synth import make_tum_dir

from mutualslam_cli.backend.ba import global_ba as gba
from mutualslam_cli.bench.ba import perturb, synthetic_problem
from mutualslam_cli.config import BAConfig, VOConfig
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.geometry import se3_inv
from mutualslam_cli.map.result import Keyframe, MapPoints, VOResult
from mutualslam_cli.types import Intrinsics, Trajectory
from mutualslam_cli.vo.depth_oracle import run_oracle

HW = (180, 240)
CFG = BAConfig(d_max=10.0, nearby_targets=False)  # the plane scene lies at 2–3 m: inside the CNN's "effective range";
# its targets are the generator's unoccluded ones (nearby keyframes: test_nearby_targets_*)


@pytest.fixture(scope="module")
def scene():
    """Noise-free plane scene: the true problem and its rendered z-depths (the "CNN")."""
    return synthetic_problem(n_kf=6, n_points=900, hw=HW, seed=0)


def as_vo(prob, times=None, segments=None, traj=None) -> VOResult:
    """A front-end map from a :class:`PhotoBAProblem`: host + its targets are the observations."""
    n = len(prob.T_cw)
    times = np.arange(n) * 0.1 if times is None else times
    segments = np.zeros(n, int) if segments is None else segments
    K = prob.K
    kfs = [Keyframe(k, k, float(times[k]), se3_inv(prob.T_cw[k]), int(segments[k])) for k in range(n)]
    obs = [np.r_[h, prob.obs_kf[prob.obs_pt == i]].astype(np.int64) for i, h in enumerate(prob.host)]
    P = len(prob.host)
    pts = MapPoints(np.arange(P), prob.host.astype(np.int64), prob.pixel.copy(), prob.inv_depth.copy(), np.zeros(P),
                    obs, [np.zeros((len(o), 2)) for o in obs])
    traj = Trajectory(times, np.stack([k.pose for k in kfs])) if traj is None else traj
    return VOResult(kfs, pts, Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], HW[1], HW[0]), traj,
                    np.full(len(traj), 0))


def centre_err(vo: VOResult, prob) -> np.ndarray:
    return np.array([np.linalg.norm(k.pose[:3, 3] - se3_inv(T)[:3, 3]) for k, T in zip(vo.keyframes, prob.T_cw)])


def run(vo, prob, deps, cfg=CFG, cull=True, **kw):
    return gba.run_global_ba(vo, lambda k: prob.images[k], lambda k: deps[k], kw.pop("val_loss", None), cfg,
                             cull=cull, **kw)


def test_recovers_poses_and_inverse_depths(scene):
    prob, deps = scene
    start = perturb(prob, np.random.default_rng(1), trans=0.01, rot_deg=0.3, rho_rel=0.02)
    r = run(as_vo(start), prob, deps)
    st = r.stats
    assert centre_err(as_vo(start), prob)[1:].min() > 5e-3
    assert centre_err(r.vo, prob).max() < 1e-3  # 0.26 mm
    for a, b in zip(r.vo.keyframes, prob.T_cw):  # rotations too (< 0.01°)
        assert np.linalg.norm(a.pose[:3, :3] @ b[:3, :3] - np.eye(3)) < 2e-4
    np.testing.assert_array_equal(r.vo.keyframes[0].pose, se3_inv(prob.T_cw[0]))  # gauge
    moved = r.vo.points.inv_depth != start.inv_depth
    assert moved.sum() == st.n_refined
    assert st.n_refined + st.n_unrefined == len(prob.host)
    err = np.abs(r.vo.points.inv_depth / prob.inv_depth - 1)
    assert np.quantile(err[moved], 0.95) < 5e-3
    assert np.median(err[moved]) < 1e-3
    # points without a valid target are kept as they are, and counted
    np.testing.assert_array_equal(r.vo.points.inv_depth[~moved], start.inv_depth[~moved])
    assert 0 < st.n_unrefined < 0.05 * len(prob.host)
    assert st.n_culled == 0
    assert r.keep.all()
    assert st.n_judged == len(prob.host)
    for costs in st.costs:  # the cost never increases over accepted steps
        assert np.all(np.diff(costs) <= 0)
    assert st.cost < 1e-3 * st.cost0
    assert st.accepted >= 1


def test_culling_removes_gross_outliers_and_keeps_inliers(scene):
    prob, deps = scene
    rng = np.random.default_rng(2)
    start = perturb(prob, np.random.default_rng(1), trans=0.005, rot_deg=0.2, rho_rel=0.02)
    bad = rng.random(len(prob.host)) < 0.1
    start.inv_depth[bad] /= rng.choice([2.0, 0.4], int(bad.sum()))  # depth ×2 or ×0.4
    # the "CNN" at another resolution than the images (depth looked up by pixel scaling)
    half = [d[::2, ::2] for d in deps]
    r = gba.run_global_ba(as_vo(start), lambda k: prob.images[k], lambda k: half[k], None, CFG, cull=True)
    assert (~r.keep[bad]).mean() >= 0.9
    assert r.keep[~bad].mean() >= 0.9
    assert r.stats.n_culled == (~r.keep).sum()
    kept = r.kept()
    assert len(kept.points) == r.keep.sum()
    assert centre_err(r.vo, prob).max() < 1e-3  # outliers gone: the BA converges as without them
    no = run(as_vo(start), prob, deps, cull=False)  # BA without culling culls nothing ...
    assert no.keep.all()
    assert no.stats.n_culled == 0
    assert no.stats.n_judged == 0
    # ... but drops most outliers itself: their blocks are outliers to the photometric test
    assert no.dropped[bad].mean() > 0.5
    assert no.dropped[~bad].mean() < 0.05
    assert no.stats.n_dropped == no.dropped.sum()
    assert len(no.kept().points) == len(prob.host) - no.dropped.sum()
    # an inverse depth the BA would change by more than ×2 keeps its value before BA, counted
    change = np.abs(np.log(no.vo.points.inv_depth / start.inv_depth))
    assert change.max() < np.log(gba.MAX_CHANGE)
    assert no.stats.n_refined + no.stats.n_unrefined + no.stats.n_dropped == len(prob.host)


def test_culls_in_the_best_validated_keyframe_and_keeps_front_end_hosts(scene):
    prob, deps = scene
    vo = as_vo(prob)
    cfg = dataclasses.replace(CFG, iterations=0)
    val = {0: 0.5, 1: 0.9, 2: 0.7, 3: 0.1, 4: 0.3, 5: 0.8}  # L_val per keyframe
    best = np.array([min(o, key=lambda k: val[k]) for o in vo.points.observations])
    # a "CNN" that is right in keyframe 3 (the best validated) and wrong by x3 everywhere else
    wrong = [d * (1.0 if k == 3 else 3.0) for k, d in enumerate(deps)]
    r = run(vo, prob, wrong, cfg, val_loss=val)
    assert r.stats.n_judged_elsewhere == np.sum(best != vo.points.host) > 100
    judged_in_3 = best == 3
    assert judged_in_3.sum() > 50
    assert r.keep[judged_in_3].all()
    assert (~r.keep[~judged_in_3 & (best != 3)]).mean() > 0.9  # judged against a x3 depth: culled
    # the BA parameters stay with the front end's host: same hosts, pixels, inverse depths (0 iterations)
    np.testing.assert_array_equal(r.vo.points.host, vo.points.host)
    np.testing.assert_array_equal(r.vo.points.pixel, vo.points.pixel)
    np.testing.assert_allclose(r.vo.points.inv_depth, vo.points.inv_depth)


def test_partial_ba_later_keyframes_and_frames_follow(scene):
    prob, deps = scene
    start = perturb(prob, np.random.default_rng(3), trans=0.01, rot_deg=0.3, rho_rel=0.0)
    vo0 = as_vo(start)
    # every keyframe pose plus a frame halfway between keyframes 3 and 4
    mid = vo0.keyframes[3].pose.copy()
    mid[:3, 3] = 0.5 * (mid[:3, 3] + vo0.keyframes[4].pose[:3, 3])
    times = np.r_[np.arange(6) * 0.1, 0.35]
    order = np.argsort(times)
    traj = Trajectory(times[order], np.concatenate([np.stack([k.pose for k in vo0.keyframes]), mid[None]])[order])
    vo = as_vo(start, traj=traj)
    r = run(vo, prob, deps, upto=3)
    assert r.stats.keyframes == 4
    # 4 keyframes whose extent (the scale anchor) the perturbation did not keep: 10 mm → < 4 mm
    assert centre_err(vo0, prob)[1:4].min() > 9e-3
    assert centre_err(r.vo, prob)[:4].max() < 4e-3
    T3_old, T3_new = vo.keyframes[3].pose, r.vo.keyframes[3].pose
    for k in (4, 5):  # T_new = T_ref_new · T_ref_old⁻¹ · T, ref = keyframe 3
        np.testing.assert_allclose(r.vo.keyframes[k].pose, T3_new @ np.linalg.inv(T3_old) @ vo.keyframes[k].pose,
                                   atol=1e-12)
    np.testing.assert_allclose(r.vo.traj_all.poses[4], T3_new @ np.linalg.inv(T3_old) @ mid, atol=1e-12)
    for k in range(6):  # frames at keyframe times carry the keyframe's new pose
        i = int(np.flatnonzero(np.isclose(traj.timestamps, 0.1 * k))[0])
        np.testing.assert_allclose(r.vo.traj_all.poses[i], r.vo.keyframes[k].pose, atol=1e-12)
    # points hosted later are untouched (host-relative); points of kfs ≤ 3 lose later observations
    later = vo.points.host > 3
    np.testing.assert_array_equal(r.vo.points.inv_depth[later], vo.points.inv_depth[later])


def test_segments_are_separate_problems(scene):
    prob, deps = scene
    start = perturb(prob, np.random.default_rng(4), trans=0.01, rot_deg=0.3, rho_rel=0.0)
    # a re-initialised front end: keyframes 3-5 are a second segment (same frame here, which is fine)
    keep = ~((prob.host < 3) & np.isin(np.arange(len(prob.host)), prob.obs_pt[prob.obs_kf >= 3])) \
        & ~((prob.host >= 3) & np.isin(np.arange(len(prob.host)), prob.obs_pt[prob.obs_kf < 3]))
    vo = as_vo(start, segments=np.array([0, 0, 0, 1, 1, 1]))
    vo = dataclasses.replace(vo, points=vo.points.subset(keep))
    r = run(vo, prob, deps)
    assert len(r.stats.costs) == 2 * CFG.rounds  # per segment, per round
    for k in (0, 3):  # each segment's first keyframe is its gauge
        np.testing.assert_array_equal(r.vo.keyframes[k].pose, vo.keyframes[k].pose)


def test_a_window_refines_only_the_newest_keyframes(scene):
    """``ba.window = 3``: keyframes 0–2 and their points are untouched, keyframe 3 holds the gauge, only the
    window's images and depths are read, and the window's photometric cost goes down."""
    prob, deps = scene
    vo = as_vo(perturb(prob, np.random.default_rng(5), trans=0.01, rot_deg=0.3, rho_rel=0.02))
    images, depths = set(), set()
    r = gba.run_global_ba(vo, lambda k: images.add(k) or prob.images[k], lambda k: depths.add(k) or deps[k], None,
                          dataclasses.replace(CFG, window=3), cull=True)
    assert r.stats.keyframes == 3
    assert images == {3, 4, 5}
    assert depths
    assert depths <= {3, 4, 5}
    for k in range(4):
        np.testing.assert_array_equal(r.vo.keyframes[k].pose, vo.keyframes[k].pose)
    assert all(not np.array_equal(r.vo.keyframes[k].pose, vo.keyframes[k].pose) for k in (4, 5))
    old = vo.points.host < 3
    np.testing.assert_array_equal(r.vo.points.inv_depth[old], vo.points.inv_depth[old])
    assert (r.vo.points.inv_depth[~old] != vo.points.inv_depth[~old]).sum() > 0.5 * (~old).sum()
    assert r.stats.cost < 0.5 * r.stats.cost0


def test_points_observed_in_a_keyframe_match_a_scan(scene):
    vo = as_vo(scene[0])
    for k in range(len(vo.keyframes)):
        scan = np.flatnonzero([k in o for o in vo.points.observations])
        np.testing.assert_array_equal(vo.points.observed_in(k), scan)
    assert len(vo.points.observed_in(99)) == 0
    assert len(MapPoints.empty().observed_in(0)) == 0


def test_ba_images_keep_only_the_newest_with_a_window(tmp_path):
    from mutualslam_cli.backend.refine import ba_images

    seq = load_sequence(str(make_tum_dir(tmp_path / "seq", n=6)))
    vo = run_oracle(seq, VOConfig(mode="gt-depth", gt_kf_every=1))
    calls = []
    real = seq.load_rgb
    seq.load_rgb = lambda i: calls.append(i) or real(i)
    load = ba_images(seq, vo, keep=2)
    first = [load(k).copy() for k in (0, 1, 2)]
    load(2), load(1)  # cached
    assert len(calls) == 3
    load(0)  # evicted: read again, same pixels
    assert len(calls) == 4
    assert np.array_equal(load(0), first[0])


def test_a_bridge_links_two_segments_into_one_problem(scene):
    """Keyframes 3–5 are a second segment, placed 2 cm off by its bridge. Alone, each segment is its own BA
    and the second keeps its first keyframe's error (its gauge); joined into one unit (``units``), the
    blocks across the gap tie them into one problem with one gauge, and the bridge's error is refined away."""
    prob, deps = scene
    start = perturb(prob, np.random.default_rng(7), trans=0.002, rot_deg=0.05, rho_rel=0.01)
    T = start.T_cw.copy()
    shift = np.eye(4)
    shift[:3, 3] = [0.02, -0.01, 0.0]
    T[3:] = np.stack([se3_inv(shift @ se3_inv(t)) for t in T[3:]])  # the second segment, misplaced together
    start = dataclasses.replace(start, T_cw=T)
    segs = np.array([0, 0, 0, 1, 1, 1])
    apart = run(as_vo(start, segments=segs), prob, deps, cull=False)
    joined = run(as_vo(start, segments=segs), prob, deps, cull=False, units={0: 0, 1: 0})
    assert apart.stats.n_parts == 2
    assert joined.stats.n_parts == 1
    assert centre_err(apart.vo, prob)[3] > 0.015  # the second segment's gauge kept the bridge's error
    assert centre_err(joined.vo, prob)[1:].max() < 5e-3 < 0.25 * centre_err(apart.vo, prob)[3]
    np.testing.assert_array_equal(joined.vo.keyframes[0].pose, se3_inv(start.T_cw[0]))  # one gauge: keyframe 0
