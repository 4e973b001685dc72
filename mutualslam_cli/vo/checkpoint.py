"""Resuming the front end mid-sequence from a cached journal (DESIGN §9).

A run replays the per-sequence journal up to its first event that depends on the network (a bridge,
a BA's feedback); from there its front end must run live, in the state it had at that frame. The
map and frame records are the journal's events replayed (:class:`~mutualslam_cli.map.state.MapState`);
what is left — the KLT tracks and their depth-filter seeds, the current pose and motion, counters,
which keyframe images the reprojection and the relocalisation hold, the windowed BA in flight (its
problem, solved again) — is a :func:`capture` taken at a frame where the front end tracks (no
initialisation under way), every few keyframes. :func:`restore` rebuilds a
:class:`~mutualslam_cli.vo.frontend.FrontEnd` from both; keyframe images are decoded again and their ORB
features recomputed (deterministic), the previous frame's pyramid rebuilt. Plain arrays and JSON: read without pickle.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import fields

import numpy as np

from mutualslam_cli.config import VOConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.journal import Event
from mutualslam_cli.vo.frontend import FrontEnd
from mutualslam_cli.vo.local_ba import BAProblem
from mutualslam_cli.vo.state import Tracks
from mutualslam_cli.vo.tracking import build_pyramid

#: The scalar fields of :class:`~mutualslam_cli.vo.state.TrackerState` (the rest: arrays, tracks, images).
_SCALARS = ("mode", "segment", "vel_dt", "t_prev", "n_at_kf", "last_kf", "n_tracked", "n_reprojected", "n_reused",
            "n_fused", "old_share_sum", "old_share_frames", "ba_due", "lost_at", "frame", "wall_s")
_TRACK_ARRAYS = ("raw", "px", "xn", "pid", "host", "f_h", "px_h", "kf_px", "at_kf")


def resumable(fe: FrontEnd) -> bool:
    """Whether ``fe``'s state after its last frame can be captured (tracking, no initialisation under way)."""
    st = fe.st
    return st.mode == "tracking" and st.ref is None and st.frame >= 0


def capture(fe: FrontEnd) -> dict[str, np.ndarray]:
    """``fe``'s :class:`~mutualslam_cli.vo.state.TrackerState` and windowed BA in flight, as arrays (``header``:
    uint8 JSON of the scalars; keyframe images by id, decoded again on restore)."""
    if not resumable(fe):
        raise ValueError("the front end is not at a resumable frame")
    st, tr = fe.st, fe.st.tracks
    header: dict[str, object] = {k: getattr(st, k) for k in _SCALARS}  # written as JSON (numpy scalars as floats)
    header.update(timing=st.timing, rescued=st.rescued, ba_stats=fe.mapper.stats, kf_imgs=sorted(st.kf_imgs),
                  reloc=None if fe.reloc is None else {"keyframes": sorted(fe.reloc.images),
                                                        "rejected": fe.reloc.rejected})
    out = {"header": np.frombuffer(json.dumps(header, default=float).encode("utf-8"), np.uint8),
           "T_cw": st.T_cw.copy(), "vel": st.vel.copy()}
    for k in _TRACK_ARRAYS:
        out[f"tr.{k}"] = np.asarray(getattr(tr, k)).copy()
    for k, v in tr.seed.items():
        out[f"tr.seed.{k}"] = v.copy()
    job = fe.mapper.job  # a windowed BA in flight: its problem, solved again on restore (deterministic)
    if job is not None:
        out.update({"job.kf": np.array([job.kf], np.int64), "job.kfs": np.array(job.kfs, np.int64),
                    "job.free": job.free, "job.pids": np.array(job.pids, np.int64),
                    "job.o_id": np.array(job.o_id, np.int64).reshape(-1, 2)})
        out.update({f"job.prob.{f.name}": np.asarray(getattr(job.prob, f.name)) for f in fields(BAProblem)
                    if getattr(job.prob, f.name) is not None})  # no scale prior: the field's default
    out["tr.obs_n"] = np.array([len(o) for o in tr.obs], np.int64)
    out["tr.obs_kf"] = np.array([k for o in tr.obs for k, _ in o], np.int64)
    out["tr.obs_px"] = np.array([p for o in tr.obs for _, p in o], np.float64).reshape(-1, 2)
    return out


def restore(seq: Sequence, cfg: VOConfig, seed: int, events: list[Event], ckpt: Mapping[str, np.ndarray]) -> FrontEnd:
    """A front end in the state ``ckpt`` (a :func:`capture`) describes, with its map rebuilt from
    ``events`` (the journal up to the captured frame). New events go to a fresh journal."""
    fe = FrontEnd(seq, cfg, seed)
    journal = fe.journal
    fe.state_map.journal = None  # the replay is the past: not journaled again
    for e in events:
        fe.state_map.apply(e)
    fe.state_map.journal = journal
    h = json.loads(bytes(np.asarray(ckpt["header"], np.uint8)).decode("utf-8"))
    st = fe.st
    for k in _SCALARS:
        setattr(st, k, type(getattr(st, k))(h[k]))
    st.timing = {k: float(v) for k, v in h["timing"].items()}
    st.rescued = {k: int(v) for k, v in h["rescued"].items()}
    st.T_cw, st.vel = np.array(ckpt["T_cw"]), np.array(ckpt["vel"])
    fe.mapper.stats = list(h["ba_stats"])
    gray_of = {k: seq.load_gray(fe.state_map.map.kf_frame[k]) for k in set(h["kf_imgs"]) | set((h["reloc"] or {}).get(
        "keyframes", []))}
    st.kf_imgs = {k: gray_of[k] for k in h["kf_imgs"]}
    if fe.reloc is not None and h["reloc"] is not None:
        for k in h["reloc"]["keyframes"]:
            fe.reloc.add_keyframe(k, gray_of[k])
        fe.reloc.rejected = int(h["reloc"]["rejected"])
    tr = Tracks.empty()
    for k in _TRACK_ARRAYS:
        setattr(tr, k, np.array(ckpt[f"tr.{k}"]))
    tr.seed = {k: np.array(ckpt[f"tr.seed.{k}"]) for k in tr.seed}
    n = np.asarray(ckpt["tr.obs_n"])
    cut = np.cumsum(n)[:-1]
    kfs = np.split(np.asarray(ckpt["tr.obs_kf"]), cut) if len(n) else []
    pxs = np.split(np.asarray(ckpt["tr.obs_px"]), cut) if len(n) else []
    tr.obs = [[(int(k), p) for k, p in zip(ks.tolist(), px)] for ks, px in zip(kfs, pxs)]
    st.tracks = tr
    if "job.kf" in ckpt:
        # every field as saved, an array: prior_w (a float) comes back 0-d and is made a float below
        prob = BAProblem(**{f.name: np.array(ckpt[f"job.prob.{f.name}"]) for f in fields(BAProblem)  # type: ignore[arg-type]
                            if f"job.prob.{f.name}" in ckpt})
        prob.prior_w = float(prob.prior_w)
        fe.mapper.resume(int(ckpt["job.kf"][0]), [int(k) for k in ckpt["job.kfs"]], np.array(ckpt["job.free"]),
                         [int(p) for p in ckpt["job.pids"]], [(int(p), int(k)) for p, k in ckpt["job.o_id"]], prob)
    st.prev_pyr = build_pyramid(seq.load_gray(st.frame), cfg.klt_window, cfg.klt_levels)
    fe.journal.frame = st.frame
    return fe
