"""What a front end hands to adaptation, BA and evaluation (DESIGN §4).

Every front end returns a :class:`VOResult`: ``svo`` (our monocular VO), ``gt`` (the pose
oracle: our VO's keyframes and tracks with GT poses, points re-triangulated in metres) and
``gt-depth`` (GT poses and points sampled from GT depth, an upper bound). Everything is
numpy so it crosses process boundaries cheaply. (The per-sequence cache keeps the front end's event
journal, not this: :mod:`~mutualslam_cli.map.journal`.)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mutualslam_cli.geometry import project, se3_inv, transform
from mutualslam_cli.pixels import in_image
from mutualslam_cli.types import Intrinsics, Trajectory


@dataclass
class Keyframe:
    """One keyframe.

    Attributes:
        id: keyframe id, 0-based, in creation order.
        frame_index: index of its frame in the :class:`~mutualslam_cli.datasets.sequence.Sequence`
            (the image is re-read from there at whatever resolution a stage needs).
        timestamp: image time, seconds.
        pose: ``(4, 4)`` ``T_wc`` in the map frame (map units; monocular scale).
        segment: tracking segment (increments after each re-initialisation).
    """

    id: int
    frame_index: int
    timestamp: float
    pose: np.ndarray
    segment: int = 0


@dataclass
class MapPoints:
    """All map points, one row each.

    Attributes:
        ids: ``(P,)`` int64 point ids.
        host: ``(P,)`` int64 host keyframe id (the keyframe the point was created in).
        pixel: ``(P, 2)`` float64 pixel ``(u, v)`` in the host keyframe.
        inv_depth: ``(P,)`` float64 inverse depth in the host keyframe, 1/map units.
        sigma: ``(P,)`` float64 standard deviation of ``inv_depth`` (filter output; from the
            triangulation for ``gt``; 0 for ``gt-depth``).
        observations: list of ``(P_i,)`` int64 arrays: keyframe ids that observe point i
            (host included).
        obs_pixels: list of ``(P_i, 2)`` float64 measured pixels, same order as ``observations``.
    """

    ids: np.ndarray
    host: np.ndarray
    pixel: np.ndarray
    inv_depth: np.ndarray
    sigma: np.ndarray
    observations: list[np.ndarray]
    obs_pixels: list[np.ndarray]

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def empty() -> MapPoints:
        z = np.zeros(0)
        return MapPoints(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), z, z, [], [])

    def observed_in(self, kf_id: int) -> np.ndarray:
        """Ascending indices of the points keyframe ``kf_id`` observes. The index over every keyframe is
        built on the first call (O(observations)), so a call costs O(its points), not O(P)."""
        index = self.__dict__.get("_by_keyframe")
        if index is None:
            lens = np.array([len(o) for o in self.observations], dtype=np.int64)
            kf = np.concatenate(self.observations).astype(np.int64) if lens.sum() else np.zeros(0, np.int64)
            pt = np.repeat(np.arange(len(lens)), lens)
            order = np.lexsort((pt, kf))
            kf, pt = kf[order], pt[order]
            keys, starts = np.unique(kf, return_index=True)
            bounds = np.r_[starts, len(kf)]
            index = {int(k): np.unique(pt[bounds[i]:bounds[i + 1]]) for i, k in enumerate(keys)}
            self.__dict__["_by_keyframe"] = index  # never stale: nothing edits ``observations`` in place
        return index.get(int(kf_id), np.zeros(0, np.int64))

    def subset(self, keep: np.ndarray) -> MapPoints:
        """Rows where the boolean mask ``keep`` is true."""
        idx = np.flatnonzero(keep)
        return MapPoints(
            self.ids[idx], self.host[idx], self.pixel[idx], self.inv_depth[idx], self.sigma[idx],
            [self.observations[i] for i in idx], [self.obs_pixels[i] for i in idx],
        )


@dataclass
class VOResult:
    """The front end's output for one sequence.

    Attributes:
        keyframes: in creation order; ``keyframes[k].id == k``.
        points: the map.
        intrinsics: the (undistorted, pinhole) camera the poses and pixels refer to.
        traj_all: poses of every tracked frame (map frame).
        frame_segment: ``(N_frames,)`` int: tracking segment of each frame, −1 = not tracked.
        covisibility: ``{kf_id: {other_kf_id: shared_points}}``.
        meta: front-end facts (mode, timings, init method, re-initialisations…).
        units: ``{segment: map unit}`` for the segments a bridge or a merge joined to another (one frame and scale:
            :meth:`unit_of_segment`); a segment not in it is a unit of its own. The map's own answer, which every
            reader takes (the BA's parts, the scale-drift windows, the map's e_si).
    """

    keyframes: list[Keyframe]
    points: MapPoints
    intrinsics: Intrinsics
    traj_all: Trajectory
    frame_segment: np.ndarray
    covisibility: dict[int, dict[int, int]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    units: dict[int, int] = field(default_factory=dict)

    def unit_of_segment(self) -> dict[int, int]:
        """``{segment: map unit}`` for every segment of the keyframes (its own where nothing joined it)."""
        return {k.segment: self.units.get(k.segment, k.segment) for k in self.keyframes}

    def joined(self, segment: int, onto: int) -> dict[int, int]:
        """The units after ``segment``'s unit is joined onto ``onto``'s (a bridge or a merge moved it there)."""
        units = self.unit_of_segment()
        old, new = units.get(segment, segment), units.get(onto, onto)
        return {s: (new if u == old else u) for s, u in units.items()} | ({segment: new} if segment not in units
                                                                          else {})

    @property
    def traj_kf(self) -> Trajectory:
        """Keyframe trajectory (map frame)."""
        return Trajectory(
            np.array([k.timestamp for k in self.keyframes]),
            np.stack([k.pose for k in self.keyframes]) if self.keyframes else np.zeros((0, 4, 4)),
        )

    @property
    def tracked_fraction(self) -> float:
        """Share of frames with a pose."""
        return float(np.mean(self.frame_segment >= 0)) if len(self.frame_segment) else float("nan")

    def points_world(self) -> np.ndarray:
        """``(P, 3)`` world positions of the map points from host pose, pixel and inverse depth."""
        out = np.zeros((len(self.points), 3))
        K_inv = np.linalg.inv(self.intrinsics.K())
        order = np.argsort(self.points.host, kind="stable")  # each host's points in index order: O(P log P), not O(K·P)
        hosts, starts = np.unique(self.points.host[order], return_index=True)
        by_id = {kf.id: kf for kf in self.keyframes}
        for h, a, b in zip(hosts, starts, np.r_[starts[1:], len(order)]):
            if int(h) not in by_id:
                continue
            m = order[a:b]
            pix = self.points.pixel[m]
            rays = np.c_[pix, np.ones(len(pix))] @ K_inv.T
            pc = rays / self.points.inv_depth[m, None]
            out[m] = transform(by_id[int(h)].pose, pc)
        return out

    def sparse_depth(self, kf_id: int, points_w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Map points observed in keyframe ``kf_id`` projected into it.

        Returns:
            pixels ``(M, 2)`` and depths ``(M,)`` (map units, > 0, inside the image) — the
            D_sparse of Eq. 6.
        """
        pw = self.points_world() if points_w is None else points_w
        sel = self.points.observed_in(kf_id)
        if not len(sel):
            return np.zeros((0, 2)), np.zeros(0)
        pc = transform(se3_inv(self.keyframes[kf_id].pose), pw[sel])
        pix, z = project(pc, self.intrinsics.K())
        w, h = self.intrinsics.width, self.intrinsics.height
        ok = (z > 1e-6) & in_image(pix, w, h)
        return pix[ok], z[ok]
