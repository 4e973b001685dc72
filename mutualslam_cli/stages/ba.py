"""The culling + global BA stage of a run (paper §III-C): Algorithm 1's requests and the final BA.

:class:`BAStage` gives the adaptation stage the step it calls when Algorithm 1 requests global BA
(the mutual loop, :func:`make_ba_step`), refines the whole map at the end (:func:`final_ba`) and
writes its maps, trajectories and summary keys. The BA itself is
:func:`~mutualslam_cli.backend.ba.global_ba.run_global_ba`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import cv2
import numpy as np
import torch

from mutualslam_cli.adapt.inputs import frame_lookup, keyframe_images
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.backend.ba.global_ba import GlobalBAResult, run_global_ba
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.results.map_ply import write_ply
from mutualslam_cli.results.run_folder import write_trajectories
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.adaptation import Adapted
from mutualslam_cli.stages.loop_inputs import depth_predictor
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.frontend import FrontEnd
from mutualslam_cli.stages.slam_metrics import (
    common_frames_ate,
    esi_of_log_errors,
    evaluate_trajectory,
    map_log_depth_errors,
    point_units,
    set_ate,
)
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo.camera import Undistorter
from mutualslam_cli.vo.result import VOResult
from mutualslam_cli.backend.bridges import units_of

log = logging.getLogger(__name__)

def no_culling_reason(cfg: RunConfig) -> str | None:
    """Why a run's global BA does not cull (``None``: it culls with the adapted network)."""
    if not cfg.ba.enabled:
        return "disabled (ba.enabled=false)"
    if not cfg.ba.culling:
        return "disabled (ba.culling=false): BA without culling"
    if cfg.adapt.scheme == "none":
        return "scheme 'none': no adapted network to cull with"
    return None


def ba_images(seq: Sequence, keyframes: VOResult | Callable[[int], int], scale: float = 1.0,
              keep: int = 0, camera: Intrinsics | None = None) -> Callable[[int], np.ndarray]:
    """``kf_id → (H, W)`` float32 grey in [0, 1] of the keyframes (of a map, or ``kf_id → frame index``),
    undistorted, at ``scale`` × the pinhole camera (area resampling; cached for the run, at most the
    ``keep`` newest ids when ``keep > 0``)."""
    und = Undistorter(seq.intrinsics)
    cam = camera or (keyframes.intrinsics if isinstance(keyframes, VOResult) else seq.intrinsics)
    size = (round(cam.width * scale), round(cam.height * scale))
    frame_of = frame_lookup(keyframes)
    cache: dict[int, np.ndarray] = {}

    def load(kf_id: int) -> np.ndarray:
        if kf_id not in cache:
            grey = cv2.cvtColor(und.image(seq.load_rgb(frame_of(kf_id))), cv2.COLOR_RGB2GRAY)
            cache[kf_id] = cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
            if keep and len(cache) > keep:  # a windowed BA (ba.window) asks for newer keyframes only
                del cache[next(iter(cache))]  # the oldest read
        return cache[kf_id]

    return load


@dataclass
class BALog:
    """What the culling + BA runs of one run did: each run's ``stats`` (Algorithm 1's requests, then
    the final one), the ids of every culled map point and of every point dropped as an outlier."""

    runs: list[dict[str, Any]] = field(default_factory=list)
    culled: set[int] = field(default_factory=set)
    dropped: set[int] = field(default_factory=set)

    def culled_mask(self, ids: np.ndarray) -> np.ndarray:
        """``(P,)`` bool: which of the map-point ``ids`` were culled."""
        return np.isin(ids, np.fromiter(self.culled, np.int64, len(self.culled)))

    def dropped_mask(self, ids: np.ndarray) -> np.ndarray:
        """``(P,)`` bool: which of the map-point ``ids`` the BA dropped as outliers."""
        return np.isin(ids, np.fromiter(self.dropped, np.int64, len(self.dropped)))


def final_ba(seq: Sequence, loop_map: VOResult, net: torch.nn.Module, adapter: OnlineAdapter | None,
             cfg: RunConfig, fast: bool, stage: "BAStage", bridges: list[dict[str, Any]] | None = None) -> VOResult:
    """The final culling + BA of the loop's map over every keyframe (the newest ``ba.window`` with a window)
    with the final network (L_val of those keyframes; none for scheme ``none``); the refined map without
    the culled and dropped points."""
    load = keyframe_images(seq, loop_map, cfg.net.width, cfg.net.height)
    depth_of = depth_predictor(net, load, fast, adapter.buffer if adapter is not None else None)
    last = len(loop_map.keyframes) - 1
    ids = list(range(max(0, last - cfg.ba.window + 1), last + 1)) if cfg.ba.window else None
    val_loss = adapter.per_keyframe_val_loss(ids) if adapter is not None else {}
    return stage.run_ba(loop_map, last, depth_of, val_loss, bridges).kept()


#: ``summary.json`` keys of culling and global BA (DESIGN §8).
BA_KEYS = ("trajectory.ate_rmse_m.ba", "trajectory.credit.ba", "trajectory.ate_rmse_m.all_frames_ba",
           "trajectory.ate_rmse_m_per_segment.ba",
           "trajectory.ate_rmse_m_per_segment.all_frames_ba", "map.points.culled", "map.points.ba", "map.esi.culled",
           "map.esi.ba", "timing.ba_s")


class BAStage:
    """Culling + global BA of a run: :meth:`run_ba` at Algorithm 1's requests (the adaptation loop hands the
    refined map back to the front end: the mutual loop), then :meth:`finish` once at the end.

    Attributes:
        record: what each culling + BA did (:class:`BALog`).
        final: the map after culling + BA once :meth:`finish` ran (``None``: no such map, ``why_no_final`` says why).
    """

    def __init__(self, run: RunContext) -> None:
        self.run = run
        self.record = BALog()
        cfg = run.cfg
        self._frame_of: dict[int, int] = {}  # keyframe → frame, of the maps BA has seen (the map grows)
        self.images = ba_images(run.seq, self._frame_of.__getitem__, cfg.ba.image_scale, keep=cfg.ba.window,
                                camera=run.seq.intrinsics)
        self.cull = no_culling_reason(cfg) is None
        self.final: VOResult | None = None
        self.why_no_final = "culling + global BA not finished"

    def run_ba(self, vo: VOResult, kf_id: int, depth_of: Callable[[int], np.ndarray],
               val_loss: Mapping[int, float], bridges: list[dict[str, Any]] | None = None) -> GlobalBAResult:
        """Culling (unless ``ba.culling=false`` or scheme ``none``) + global BA of ``vo``'s keyframes ≤ ``kf_id``
        (segments the ``bridges`` joined as one map), recorded into :attr:`record`."""
        self._frame_of.update((k.id, k.frame_index) for k in vo.keyframes)
        units = units_of(sorted({k.segment for k in vo.keyframes}), bridges or [])
        r = run_global_ba(vo, self.images, depth_of, val_loss, self.run.cfg.ba, cull=self.cull, upto=kf_id,
                          units=units)
        self.record.culled.update(vo.points.ids[~r.keep].tolist())
        self.record.dropped.update(vo.points.ids[r.dropped].tolist())
        self.record.runs.append({"kf_id": kf_id, **{k: x for k, x in r.stats.items() if k != "costs"}})
        log.info("global BA after keyframe %d: %d culled, %d dropped, %d refined (%d unrefined), cost %.4g -> %.4g, "
                 "%.2f s", kf_id, r.stats["n_culled"], r.stats["n_dropped"], r.stats["n_refined"],
                 r.stats["n_unrefined"], r.stats["cost0"], r.stats["cost"], r.stats["seconds"])
        return r

    def finish(self, adapted: Adapted, fe: FrontEnd, fast: bool) -> None:
        """The map after culling + BA, by ``ba.final``: ``always`` — one more culling + BA of the loop's
        map over every keyframe with the final network; ``on_request`` — the loop's map after the BAs
        Algorithm 1 requested (no after-BA figures when it requested none: the keys are null with
        Algorithm 1's reason, L_val vs τ). Writes ``map_culled.ply`` (the front end's map without the
        culled points), ``map_ba.ply``, ``traj_{kf,all}_ba.txt``, the keys of :data:`BA_KEYS`, ``ba.*``
        and, with injected outliers, ``map.outliers.*`` and ``map.inliers.kept``."""
        run, cfg = self.run, self.run.cfg
        run.summary.set("ba.requested", adapted.requested)
        vo_ba, why = None, None
        if not cfg.ba.enabled:
            why = "disabled (ba.enabled=false)"
        elif cfg.ba.final == "always":
            with run.timed("ba"):
                vo_ba = final_ba(run.seq, adapted.map, adapted.net, adapted.adapter, cfg, fast, self, adapted.bridges)
        elif self.record.runs:
            vo_ba = adapted.map
            last = self.record.runs[-1]["kf_id"]
            if last < len(vo_ba.keyframes) - 1:
                run.summary.notes["trajectory.ate_rmse_m.ba"] = (
                    f"ba.final=on_request: the map after the BAs Algorithm 1 requested; keyframes after {last} "
                    f"(of {len(vo_ba.keyframes)}) were tracked after the last one and not refined by any")
        else:
            why = "ba.final=on_request and " + (adapted.why_no_request(cfg.adapt.tau_val, cfg.adapt.patience)
                                                if adapted.adapter is not None else
                                                f"scheme {cfg.adapt.scheme!r} runs no Algorithm 1")
        self.final, self.why_no_final = vo_ba, why or ""
        if vo_ba is None:
            self._absent(why)
        else:
            self._write(vo_ba, fe, adapted)
        self._credit(fe, adapted, vo_ba, why)
        if len(fe.injected):
            culled = self.record.culled_mask(fe.vo.points.ids) if self.record.runs and no_culling_reason(cfg) is None \
                else None
            _summarise_outliers(run.summary, fe.vo.points.ids, fe.injected, culled,
                                self.record.dropped_mask(fe.vo.points.ids) if self.record.runs else None)

    def _credit(self, fe: FrontEnd, adapted: Adapted, vo_ba: VOResult | None, why: str | None) -> None:
        """Table 4's columns on the same frames, one Sim(3) each (``trajectory.credit.*``): the front end on
        its own (``vo``), joined by the run's bridges and nothing else (``bridged``), after culling + BA
        (``ba``); ``frames``: how many frames every column tracked."""
        ates, n, no = common_frames_ate(self.run.seq, {"vo": fe.vo, "bridged": adapted.bridged, "ba": vo_ba},
                                        self.run.cfg.eval.ate_max_dt)
        summary = self.run.summary
        summary.set("trajectory.credit.frames", n)
        for k, v in ates.items():
            summary.set(f"trajectory.credit.{k}", v, no or (why if k == "ba" else "not computed"))

    def _absent(self, why: str) -> None:
        summary = self.run.summary
        for key in BA_KEYS + BA_RUN_KEYS:
            summary.absent(key, why)
        summary.set("ba.runs", 0)

    def _write(self, vo_ba: VOResult, fe: FrontEnd, adapted: Adapted) -> None:
        run, summary = self.run, self.run.summary
        vo, err = fe.vo, fe.map_errors
        keep = ~self.record.culled_mask(vo.points.ids)
        no_culling = no_culling_reason(run.cfg)
        err_ba = map_log_depth_errors(run.seq, vo_ba)
        if no_culling is None:
            write_ply(run.folder / "map_culled.ply", vo.points_world()[keep], err[keep])
        write_ply(run.folder / "map_ba.ply", vo_ba.points_world(), err_ba)
        write_trajectories(run.folder, vo_ba.traj_kf, vo_ba.traj_all, suffix="_ba")
        set_ate(summary, evaluate_trajectory(run.seq, vo_ba, run.cfg.eval.ate_max_dt),
                {"kf": "ba", "all": "all_frames_ba"})
        if no_culling:
            summary.absent("map.points.culled", no_culling)
            summary.absent("map.esi.culled", no_culling)
        else:
            summary.set("map.points.culled", int(keep.sum()))
            summary.set("map.esi.culled", esi_of_log_errors(err[keep], point_units(vo)[keep])[0],
                        "no kept map point has GT depth at its host pixel")
        units = units_of(sorted({k.segment for k in vo_ba.keyframes}), adapted.bridges or [])
        summary.set("map.points.ba", len(vo_ba.points))
        summary.set("map.esi.ba", esi_of_log_errors(err_ba, point_units(vo_ba, units))[0],
                    "no map point has GT depth at its host pixel after BA")
        summary.set("timing.ba_s", run.timings.get("ba", 0.0))  # Algorithm 1's requests and the final one
        runs = self.record.runs
        summary.set("ba.runs", len(runs))
        summary.set("ba.points_dropped", len(self.record.dropped))
        for key in BA_RUN_KEYS[1:]:
            summary.set(key, runs[-1][key.rsplit(".", 1)[1]])


#: ``summary.json`` keys of the last culling + BA of a run (its counts, ``ba.last.*``) and the points
#: the BAs dropped as outliers (``ba.points_dropped``).
BA_RUN_KEYS = ("ba.points_dropped",) + tuple(
    f"ba.last.{k}" for k in ("keyframes", "n_culled", "n_judged_elsewhere", "n_refined", "n_unrefined", "n_diverged",
                             "n_dropped", "n_targets", "n_nearby_targets", "n_blocks", "n_outlier_blocks",
                             "iterations", "cost0", "cost"))


def _summarise_outliers(summary: Summary, ids: np.ndarray, injected: np.ndarray, culled: np.ndarray | None,
                        dropped: np.ndarray | None) -> None:
    """``map.outliers.{injected,culled,dropped}`` and ``map.inliers.kept`` of a run with ``vo.inject_outliers``.

    Args:
        ids: ``(P,)`` ids of every map point; injected: ids of the corrupted ones.
        culled: ``(P,)`` bool, culled points (``None``: this run did not cull).
        dropped: ``(P,)`` bool, points a BA dropped as outliers (``None``: no BA ran).
    """
    bad = np.isin(ids, injected)
    summary.set("map.outliers.injected", int(bad.sum()))
    if dropped is None:
        summary.absent("map.outliers.dropped", "no global BA ran")
    else:
        summary.set("map.outliers.dropped", float(dropped[bad].mean()) if bad.any() else None, "no outlier injected")
    if culled is None:
        why = "no culling in this run (ba.enabled=false, ba.culling=false, scheme 'none', or no BA ran)"
        summary.absent("map.outliers.culled", why)
        summary.absent("map.inliers.kept", why)
        return
    summary.set("map.outliers.culled", float(culled[bad].mean()) if bad.any() else None, "no outlier injected")
    summary.set("map.inliers.kept", float((~culled[~bad]).mean()) if (~bad).any() else None,
                "every point is an outlier")
