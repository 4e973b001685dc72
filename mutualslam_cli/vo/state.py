"""Mutable bookkeeping of tracking: the active tracks and what the front end carries from frame to frame.

:class:`Tracks` holds one row per feature currently tracked by KLT (map-point tracks and
depth-filter seeds alike, aligned arrays so every per-frame step is vectorised);
:class:`TrackerState` the rest of the tracker's state. The map itself (keyframes, points) is
:mod:`mutualslam_cli.map`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_SEED_KEYS = ("a", "b", "mu", "sigma2", "z_range")


@dataclass
class Tracks:
    """Aligned per-track arrays (N rows).

    Attributes:
        raw: ``(N, 2)`` float32 raw pixels in the current frame (what KLT tracks).
        px: ``(N, 2)`` undistorted pinhole pixels in the current frame.
        xn: ``(N, 2)`` normalised coordinates in the current frame.
        pid: ``(N,)`` map point id, −1 for a seed.
        host: ``(N,)`` host keyframe of the seed (unused for map points).
        f_h: ``(N, 3)`` unit bearing of the seed in its host.
        px_h: ``(N, 2)`` undistorted pixel of the seed in its host.
        seed: depth-filter state (``a, b, mu, sigma2, z_range``), each ``(N,)``.
        kf_px: ``(N, 2)`` undistorted pixel at the last keyframe (parallax test).
        at_kf: ``(N,)`` bool, the track existed at the last keyframe.
        obs: per-track list of ``(kf_id, px)`` keyframe observations gathered while a seed.
    """

    raw: np.ndarray
    px: np.ndarray
    xn: np.ndarray
    pid: np.ndarray
    host: np.ndarray
    f_h: np.ndarray
    px_h: np.ndarray
    seed: dict[str, np.ndarray]
    kf_px: np.ndarray
    at_kf: np.ndarray
    obs: list[list[tuple[int, np.ndarray]]]

    @staticmethod
    def empty() -> Tracks:
        z2 = np.zeros((0, 2))
        return Tracks(np.zeros((0, 2), np.float32), z2, z2, np.zeros(0, np.int64), np.zeros(0, np.int64),
                      np.zeros((0, 3)), z2, {k: np.zeros(0) for k in _SEED_KEYS}, z2, np.zeros(0, bool), [])

    def __len__(self) -> int:
        return len(self.pid)

    def select(self, keep: np.ndarray) -> Tracks:
        """Rows where the bool mask (or index array) ``keep`` selects."""
        idx = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep)
        return Tracks(self.raw[idx], self.px[idx], self.xn[idx], self.pid[idx], self.host[idx],
                      self.f_h[idx], self.px_h[idx], {k: v[idx] for k, v in self.seed.items()},
                      self.kf_px[idx], self.at_kf[idx], [self.obs[i] for i in idx])

    def extend(self, other: Tracks) -> Tracks:
        """Concatenation of two track sets."""
        cat = np.concatenate
        return Tracks(cat([self.raw, other.raw]).astype(np.float32), cat([self.px, other.px]),
                      cat([self.xn, other.xn]), cat([self.pid, other.pid]), cat([self.host, other.host]),
                      cat([self.f_h, other.f_h]), cat([self.px_h, other.px_h]),
                      {k: cat([self.seed[k], other.seed[k]]) for k in _SEED_KEYS},
                      cat([self.kf_px, other.kf_px]), cat([self.at_kf, other.at_kf]), self.obs + other.obs)


@dataclass
class InitReference:
    """The reference frame of an initialisation (``TrackerState.ref`` while ``mode == "init"``).

    Attributes:
        frame: its index; gray: ``(H, W)`` uint8 its grey image.
        raw0: ``(N, 2)`` float32 raw pixels of the features detected in it.
        raw: ``(n, 2)`` where the features still tracked are in the current frame (raw pixels); alive: ``(n,)``
            their rows in ``raw0``.
        hist: per frame tracked since, ``(frame, alive, raw)`` as they stood then (PnP for the frames in between).
    """

    frame: int
    gray: np.ndarray
    raw0: np.ndarray
    raw: np.ndarray
    alive: np.ndarray
    hist: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)


@dataclass
class TrackerState:
    """What the front end (:class:`~mutualslam_cli.vo.frontend.FrontEnd`) carries from one frame to the next
    besides its map: one declared object its parts share (and :mod:`~mutualslam_cli.vo.checkpoint` saves).

    Attributes:
        mode: ``"init"`` (bringing up a segment) or ``"tracking"``.
        segment: the current tracking segment (−1 before the first).
        ref: the initialisation's reference frame (``init`` only, :class:`InitReference`): its grey image, its
            features and their tracks so far; ``None`` otherwise.
        T_cw: ``(4, 4)`` pose of the last tracked frame (world to camera, map units).
        vel: ``(4, 4)`` the last frame-to-frame motion (camera frames); vel_dt: the time it took (s; 0:
            unknown); t_prev: timestamp of the last tracked frame (s).
        tracks: the KLT tracks, map points and depth-filter seeds (:class:`Tracks`).
        n_at_kf: tracks alive at the last keyframe; last_kf: the keyframe frames are tracked against.
        n_tracked: PnP inliers of the last tracked frame; n_reprojected: points re-attached so far (n_reused:
            of them, points from outside the newest keyframes, ``vo.reuse_map``).
        old_share_sum, old_share_frames: the sum over tracked frames of the share of their tracked map points first
            seen more than :data:`~mutualslam_cli.vo.frontend.OLD_AGE_KFS` keyframes before, and the frames summed.
        rescued: weak frames whose pose :mod:`~mutualslam_cli.vo.rescue` found, by how (``seeds``, ``wide``).
        ba_due: the frame at which the windowed BA in flight is applied.
        lost_at: the frame of the last tracking loss (−1: none).
        kf_imgs: grey images of the newest ``core_kfs`` keyframes (reprojection sources).
        prev_pyr: the previous frame's KLT pyramid; frame: the last frame processed.
        timing: seconds per stage so far; wall_s: seconds in ``process`` so far.
    """

    mode: str = "init"
    segment: int = -1
    ref: InitReference | None = None
    T_cw: np.ndarray = field(default_factory=lambda: np.eye(4))
    vel: np.ndarray = field(default_factory=lambda: np.eye(4))
    vel_dt: float = 0.0
    t_prev: float = 0.0
    tracks: Tracks = field(default_factory=Tracks.empty)
    n_at_kf: int = 0
    last_kf: int = -1
    n_tracked: int = 0
    n_reprojected: int = 0
    n_reused: int = 0
    n_fused: int = 0
    rescued: dict[str, int] = field(default_factory=dict)
    old_share_sum: float = 0.0
    old_share_frames: int = 0
    ba_due: int = 0
    lost_at: int = -1
    kf_imgs: dict[int, np.ndarray] = field(default_factory=dict)
    prev_pyr: np.ndarray | None = None  # a tracking.Pyramid
    frame: int = -1
    timing: dict[str, float] = field(default_factory=dict)
    wall_s: float = 0.0
