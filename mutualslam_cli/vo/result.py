"""What a front end hands to adaptation, BA and evaluation (DESIGN §4).

Every front end returns a :class:`VOResult`: ``svo`` (our monocular VO), ``gt`` (the pose
oracle: our VO's keyframes and tracks with GT poses, points re-triangulated in metres) and
``gt-depth`` (GT poses and points sampled from GT depth, an upper bound). Everything is
numpy so it crosses process boundaries cheaply, and :func:`vo_to_arrays` / :func:`vo_from_arrays`
turn it into plain arrays and back for the VO cache (an ``.npz`` read without pickle: a results
folder shared on a cluster must not be able to run code when read).
"""

from __future__ import annotations

import json
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
    def empty() -> "MapPoints":
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

    def subset(self, keep: np.ndarray) -> "MapPoints":
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
    """

    keyframes: list[Keyframe]
    points: MapPoints
    intrinsics: Intrinsics
    traj_all: Trajectory
    frame_segment: np.ndarray
    covisibility: dict[int, dict[int, int]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

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


# ----------------------------------------------------------------------------- plain arrays (the VO cache)

#: Version of the :func:`vo_to_arrays` layout; :func:`vo_from_arrays` refuses any other.
VO_ARRAYS_VERSION = 1
_FORMAT = "mslam-vo-result"


def _json_default(x: Any) -> Any:
    """numpy scalars and arrays in ``meta`` become Python numbers and lists."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"VOResult.meta value of type {type(x).__name__} is not JSON-like")


def _ragged(parts: list[np.ndarray], dtype: type, tail: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate ``parts`` (each ``(n_i, *tail)``); returns ``(flat (sum n_i, *tail), offsets (P+1,))``."""
    offsets = np.zeros(len(parts) + 1, np.int64)
    offsets[1:] = np.cumsum([len(a) for a in parts])
    if not parts:
        return np.zeros((0, *tail), dtype), offsets
    return np.concatenate([np.asarray(a, dtype).reshape(-1, *tail) for a in parts]), offsets


def vo_to_arrays(vo: VOResult) -> dict[str, np.ndarray]:
    """A :class:`VOResult` as a flat dict of numeric arrays (for ``np.savez``; no object arrays).

    Layout (``K`` keyframes, ``P`` points, ``O`` observations in all, ``N`` tracked frames):
    ``header`` uint8 UTF-8 JSON (format, version, intrinsics, ``meta``); ``kf_id``, ``kf_frame_index``,
    ``kf_segment`` ``(K,)`` int64, ``kf_timestamp`` ``(K,)`` float64 s, ``kf_pose`` ``(K, 4, 4)``;
    ``pt_ids``, ``pt_host`` ``(P,)`` int64, ``pt_pixel`` ``(P, 2)``, ``pt_inv_depth``, ``pt_sigma``
    ``(P,)``; ``obs_offsets`` ``(P+1,)`` int64 with point ``i``'s observations at
    ``obs_kf[o[i]:o[i+1]]`` (int64 keyframe ids) and ``obs_pixels[o[i]:o[i+1]]`` ``(O, 2)``;
    ``traj_t`` ``(N,)``, ``traj_poses`` ``(N, 4, 4)``; ``frame_segment``; ``covis_keys`` ``(C,)`` and
    ``covis_pairs`` ``(M, 3)`` int64 rows ``(kf, other_kf, shared_points)``, both in insertion order.

    ``meta`` must be JSON-like: numpy scalars come back as Python numbers, tuples as lists.
    """
    intr = vo.intrinsics
    header = {
        "format": _FORMAT, "version": VO_ARRAYS_VERSION,
        "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy, "width": intr.width,
                       "height": intr.height, "dist": None if intr.dist is None else list(intr.dist)},
        "meta": vo.meta,
    }
    text = json.dumps(header, default=_json_default)
    kfs, pts = vo.keyframes, vo.points
    obs_kf, offsets = _ragged(pts.observations, np.int64, ())
    obs_px, offsets_px = _ragged(pts.obs_pixels, np.float64, (2,))
    if not np.array_equal(offsets, offsets_px):
        raise ValueError("MapPoints.observations and obs_pixels differ in length for some point")
    pairs = [(a, b, n) for a, row in vo.covisibility.items() for b, n in row.items()]
    return {
        "header": np.frombuffer(text.encode("utf-8"), np.uint8),
        "kf_id": np.array([k.id for k in kfs], np.int64),
        "kf_frame_index": np.array([k.frame_index for k in kfs], np.int64),
        "kf_timestamp": np.array([k.timestamp for k in kfs], np.float64),
        "kf_pose": np.stack([k.pose for k in kfs]).astype(np.float64) if kfs else np.zeros((0, 4, 4)),
        "kf_segment": np.array([k.segment for k in kfs], np.int64),
        "pt_ids": pts.ids, "pt_host": pts.host, "pt_pixel": pts.pixel,
        "pt_inv_depth": pts.inv_depth, "pt_sigma": pts.sigma,
        "obs_offsets": offsets, "obs_kf": obs_kf, "obs_pixels": obs_px,
        "traj_t": vo.traj_all.timestamps, "traj_poses": vo.traj_all.poses,
        "frame_segment": np.asarray(vo.frame_segment),
        "covis_keys": np.array(list(vo.covisibility), np.int64),
        "covis_pairs": np.array(pairs, np.int64).reshape(-1, 3),
    }


def _expect(ok: bool, what: str) -> None:
    if not ok:
        raise ValueError(f"invalid VO arrays: {what}")


def vo_from_arrays(a: Any) -> VOResult:
    """Inverse of :func:`vo_to_arrays`; ``a`` is that dict or an open ``np.load`` archive.

    Raises:
        ValueError: another format or version, a header that is not JSON, or arrays whose sizes disagree.
        KeyError: a missing array or header field.
    """
    header = json.loads(bytes(np.asarray(a["header"], np.uint8)).decode("utf-8"))
    _expect(isinstance(header, dict) and header.get("format") == _FORMAT,
            f"format {header.get('format') if isinstance(header, dict) else None!r}, expected {_FORMAT!r}")
    _expect(header.get("version") == VO_ARRAYS_VERSION,
            f"version {header.get('version')!r}, expected {VO_ARRAYS_VERSION}")
    arr = {k: np.asarray(a[k]) for k in (
        "kf_id", "kf_frame_index", "kf_timestamp", "kf_pose", "kf_segment", "pt_ids", "pt_host", "pt_pixel",
        "pt_inv_depth", "pt_sigma", "obs_offsets", "obs_kf", "obs_pixels", "traj_t", "traj_poses",
        "frame_segment", "covis_keys", "covis_pairs")}
    n_kf, n_pt = len(arr["kf_id"]), len(arr["pt_ids"])
    _expect(all(len(arr[k]) == n_kf for k in ("kf_frame_index", "kf_timestamp", "kf_pose", "kf_segment"))
            and arr["kf_pose"].shape[1:] == (4, 4), "keyframe arrays disagree")
    _expect(all(len(arr[k]) == n_pt for k in ("pt_host", "pt_pixel", "pt_inv_depth", "pt_sigma"))
            and arr["pt_pixel"].shape[1:] == (2,), "point arrays disagree")
    off = arr["obs_offsets"]
    _expect(off.shape == (n_pt + 1,) and off[0] == 0 and np.all(np.diff(off) >= 0)
            and off[-1] == len(arr["obs_kf"]) == len(arr["obs_pixels"]) and arr["obs_pixels"].shape[1:] == (2,),
            "observation offsets do not match the observations")
    _expect(arr["covis_pairs"].ndim == 2 and arr["covis_pairs"].shape[1] == 3, "covisibility is not (M, 3)")
    ih = header["intrinsics"]
    intr = Intrinsics(ih["fx"], ih["fy"], ih["cx"], ih["cy"], ih["width"], ih["height"],
                      None if ih["dist"] is None else tuple(ih["dist"]))
    keyframes = [Keyframe(int(i), int(f), float(t), p.copy(), int(s)) for i, f, t, p, s in zip(
        arr["kf_id"], arr["kf_frame_index"], arr["kf_timestamp"], arr["kf_pose"], arr["kf_segment"])]
    cut = off[1:-1]
    points = MapPoints(arr["pt_ids"], arr["pt_host"], arr["pt_pixel"], arr["pt_inv_depth"], arr["pt_sigma"],
                       np.split(arr["obs_kf"], cut) if n_pt else [],
                       np.split(arr["obs_pixels"], cut) if n_pt else [])
    covis: dict[int, dict[int, int]] = {int(k): {} for k in arr["covis_keys"]}
    for k, other, n in arr["covis_pairs"].tolist():
        covis.setdefault(k, {})[other] = n
    return VOResult(keyframes, points, intr, Trajectory(arr["traj_t"], arr["traj_poses"]), arr["frame_segment"],
                    covis, header["meta"])
