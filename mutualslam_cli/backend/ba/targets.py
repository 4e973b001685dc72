"""Which keyframes a map point's residual blocks go to, in one map unit of the global BA
(:mod:`~mutualslam_cli.backend.ba.global_ba` states the policy: existing observations first, then keyframes
nearby in space that pass the robust test), and which keyframes those blocks tie together
(:func:`connected_parts`: each part is one problem with a gauge of its own).

Everything is in the unit's local indices: keyframe ``j`` of :class:`UnitScene`, point ``i``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mutualslam_cli.backend.ba.problem import PhotoBAProblem
from mutualslam_cli.backend.ba.residuals import DSO_PATTERN, SQUARE3, PatchData, classify, residuals
from mutualslam_cli.config import BAConfig
from mutualslam_cli.pixels import in_image

#: Pixels at the border of the BA image where a projection is invalid (the solver's margin).
MARGIN = 2.0
#: A nearby keyframe is a target only if the point's depth there is within this factor of its host depth
#: (the pattern is compared fronto-parallel: a large change of scale makes it a different patch).
MAX_DEPTH_RATIO = 1.5
#: Nearby keyframes (by camera centre) tried per point beyond its existing observations.
NEARBY = 8


def pattern_of(cfg: BAConfig) -> np.ndarray:
    """The residual pattern ``(S, 2)`` the config names."""
    return DSO_PATTERN if cfg.pattern == "dso" else SQUARE3


@dataclass
class UnitScene:
    """One map unit's keyframes and candidate points as the BA sees them.

    Attributes:
        stack: ``(K, H, W)`` float32 grey images at the BA resolution.
        K: ``(3, 3)`` intrinsics at that resolution.
        T_cw: ``(K, 4, 4)`` world-to-camera poses; ab: ``(K, 2)`` affine brightness.
        host: ``(P,)`` local host keyframe; pix: ``(P, 2)`` host pixels on the BA grid; rho: ``(P,)``
            inverse depths in the host.
        obs: per point, ``(n_i,)`` local keyframes that observe it (host included).
        segment: ``(K,)`` each keyframe's tracking segment (a unit joins segments by bridges).
    """

    stack: np.ndarray
    K: np.ndarray
    T_cw: np.ndarray
    ab: np.ndarray
    host: np.ndarray
    pix: np.ndarray
    rho: np.ndarray
    obs: list[np.ndarray]
    segment: np.ndarray | None = None

    @property
    def border(self) -> float:
        return MARGIN + 2  # the pattern reaches 2 px from its centre

    @property
    def shape(self) -> tuple[int, int]:
        return self.stack.shape[1], self.stack.shape[2]

    def project(self, pt: np.ndarray, kf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels ``(N, 2)``, depths ``(N,)`` in keyframes ``kf`` and host depths ``(N,)`` of points ``pt``."""
        K, h = self.K, self.host[pt]
        ray = np.c_[(self.pix[pt] - K[:2, 2]) / np.diag(K)[:2], np.ones(len(pt))] / self.rho[pt, None]
        T_th = self.T_cw[kf] @ np.linalg.inv(self.T_cw[h])
        X = np.einsum("nij,nj->ni", T_th[:, :3, :3], ray) + T_th[:, :3, 3]
        z = X[:, 2]
        uv = (X[:, :2] / np.where(z > 1e-9, z, 1.0)[:, None]) * np.diag(K)[:2] + K[:2, 2]
        return uv, z, 1.0 / self.rho[pt]

    def inside(self, uv: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: pixels where the whole pattern lies on the image."""
        H, W = self.shape
        return in_image(uv, W, H, self.border)

    def problem(self, obs_pt: np.ndarray, obs_kf: np.ndarray, points: np.ndarray | None = None,
                free: np.ndarray | None = None, anchor: np.ndarray | None = None) -> PhotoBAProblem:
        """The photometric BA problem of the blocks ``(obs_pt, obs_kf)`` (each block's point and target keyframe)
        over ``points`` (default: every point; ``obs_pt`` then indexes into ``points``)."""
        p = np.arange(len(self.host)) if points is None else points
        return PhotoBAProblem(self.stack, self.K, self.T_cw, self.ab, self.host[p], self.pix[p], self.rho[p], obs_pt,
                              obs_kf, free, anchor)


def first_per_point(p: np.ndarray, k: np.ndarray, n: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``n`` (per point, or one number) of the pairs ``(p, k)``, already grouped by point."""
    if len(p) == 0:
        return p, k
    rank = np.arange(len(p)) - np.searchsorted(p, p)  # position within the point's run
    take = rank < (n[p] if isinstance(n, np.ndarray) else n)
    return p[take], k[take]


def existing_targets(scene: UnitScene, max_targets: int) -> tuple[np.ndarray, np.ndarray]:
    """``(obs_pt, obs_kf)``, one entry per block (point, target keyframe): per point its observing keyframes where
    it projects inside, nearest keyframe index first, at most ``max_targets``."""
    obs = scene.obs
    cand_p = np.repeat(np.arange(len(scene.host)), [len(o) for o in obs]).astype(np.int64)
    cand_k = np.concatenate(obs).astype(np.int64) if obs else np.zeros(0, np.int64)
    uv, z, _ = scene.project(cand_p, cand_k)
    h = scene.host[cand_p]
    sel = np.flatnonzero((z > 1e-9) & (cand_k != h) & scene.inside(uv))
    order = sel[np.lexsort((cand_k[sel], np.abs(cand_k[sel] - h[sel]), cand_p[sel]))]
    return first_per_point(cand_p[order], cand_k[order], max_targets)


def nearby_targets(scene: UnitScene, obs_pt: np.ndarray, obs_kf: np.ndarray,
                   cfg: BAConfig) -> tuple[np.ndarray, np.ndarray]:
    """More targets for points with fewer than ``max_targets`` than the blocks ``(obs_pt, obs_kf)`` give them:
    keyframes near the host in space where the point projects inside, at a similar depth, and whose block passes
    the robust test now; ``(near_pt, near_kf)`` like :func:`existing_targets`."""
    nk, P = len(scene.T_cw), len(scene.host)
    have = np.bincount(obs_pt, minlength=P)
    want = np.maximum(cfg.max_targets - have, 0)
    if nk < 3 or not want.any():
        return obs_pt[:0], obs_kf[:0]
    T_cw = scene.T_cw
    c = -np.einsum("kji,kj->ki", T_cw[:, :3, :3], T_cw[:, :3, 3])
    near = np.argsort(np.linalg.norm(c[:, None] - c[None], axis=2), axis=1, kind="stable")[:, 1:NEARBY + 1]
    pts = np.flatnonzero(want > 0)
    cand_p = np.repeat(pts, near.shape[1])
    cand_k = near[scene.host[pts]].ravel()
    taken = set((obs_pt.astype(np.int64) * nk + obs_kf).tolist())
    fresh = ~np.isin(cand_p * nk + cand_k, list(taken)) & (cand_k != scene.host[cand_p])
    cand_p, cand_k = cand_p[fresh], cand_k[fresh]
    uv, z, zh = scene.project(cand_p, cand_k)
    ratio = z / zh
    sel = (z > 1e-9) & (ratio < MAX_DEPTH_RATIO) & (ratio > 1 / MAX_DEPTH_RATIO) & scene.inside(uv)
    cand_p, cand_k = cand_p[sel], cand_k[sel]
    if not len(cand_p):
        return obs_pt[:0], obs_kf[:0]
    d = PatchData(scene.problem(cand_p, cand_k), pattern_of(cfg), MARGIN)
    passed = np.zeros(len(cand_p), bool)
    res = residuals(d, scene.T_cw, scene.ab, scene.rho)
    passed[d.order] = classify(d, res.values, res.valid, res.counted, cfg.huber_grey / 255, cfg.outlier_grey / 255)
    cand_p, cand_k = cand_p[passed], cand_k[passed]  # still in nearest-first order within each point
    return first_per_point(cand_p, cand_k, want)


def connected_parts(n_kf: int, hosts: np.ndarray, targets: np.ndarray) -> list[np.ndarray]:
    """The keyframes ``0 … n_kf−1`` the blocks (host ``hosts[b]``, target ``targets[b]``) tie together, as
    ascending index arrays, the part of keyframe 0 first; keyframes in no block are left out."""
    parent = np.arange(n_kf)

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in set(zip(hosts.tolist(), targets.tolist())):
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    used = np.unique(np.r_[hosts, targets]).astype(np.int64)
    roots = np.array([find(a) for a in used], np.int64)
    return [used[roots == r] for r in np.unique(roots)]
