"""The culling + global BA stage of a run (paper §III-C): Algorithm 1's requests and the final BA.

:class:`BAStage` gives the adaptation stage the step it calls when Algorithm 1 requests global BA
(the mutual loop, :func:`make_ba_step`), refines the whole map at the end (:func:`final_ba`) and
writes its maps, trajectories and summary keys. The BA itself is
:func:`~mutualslam_cli.ba.global_ba.run_global_ba`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import cv2
import numpy as np
import torch

from mutualslam_cli.adapt.inputs import keyframe_images
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.ba.global_ba import run_global_ba
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.results.map_ply import write_ply
from mutualslam_cli.results.run_folder import write_trajectories
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.adaptation import Adapted, GlobalBA, depth_predictor
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.frontend import FrontEnd
from mutualslam_cli.stages.slam_metrics import esi_of_log_errors, evaluate_trajectory, map_log_depth_errors, set_ate
from mutualslam_cli.vo.camera import Undistorter
from mutualslam_cli.vo.result import VOResult

log = logging.getLogger(__name__)

#: Global BA image resolution, relative to the VO camera. Half: an LM iteration costs the same at
#: any resolution (it scales with points × targets), the images take 4× less memory (300 TUM
#: keyframes: 92 MB instead of 370 MB), the area-averaged images widen the convergence basin, and
#: on tum_fr1_xyz (16 keyframes, 659 points, GT depth as the CNN) it gave keyframe ATE 13.2 mm and
#: map e_si 0.113 where full resolution gave 13.9 mm and 0.118, in about the same time (0.5 s on an
#: idle core). Not the network resolution: 640×192 squeezes a 4:3 image vertically by 2.5.
BA_SCALE = 0.5


def no_culling_reason(cfg: RunConfig) -> str | None:
    """Why a run's global BA does not cull (``None``: it culls with the adapted network)."""
    if not cfg.ba.enabled:
        return "disabled (ba.enabled=false)"
    if not cfg.ba.culling:
        return "disabled (ba.culling=false): BA without culling"
    if cfg.adapt.scheme == "none":
        return "scheme 'none': no adapted network to cull with"
    return None


def ba_images(seq: Sequence, vo: VOResult, scale: float = BA_SCALE) -> Callable[[int], np.ndarray]:
    """``kf_id → (H, W)`` float32 grey in [0, 1] of the keyframes, undistorted, at ``scale`` × the
    VO camera (area resampling; cached for the run)."""
    und = Undistorter(seq.intrinsics)
    size = (round(vo.intrinsics.width * scale), round(vo.intrinsics.height * scale))
    cache: dict[int, np.ndarray] = {}

    def load(kf_id: int) -> np.ndarray:
        if kf_id not in cache:
            grey = cv2.cvtColor(und.image(seq.load_rgb(vo.keyframes[kf_id].frame_index)), cv2.COLOR_RGB2GRAY)
            cache[kf_id] = cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        return cache[kf_id]

    return load


@dataclass
class BALog:
    """What the culling + BA runs of one run did: each run's ``stats`` (triggers, then the final
    one) and the ids of every culled map point."""

    runs: list[dict[str, Any]] = field(default_factory=list)
    culled: set[int] = field(default_factory=set)

    def culled_mask(self, ids: np.ndarray) -> np.ndarray:
        """``(P,)`` bool: which of the map-point ``ids`` were culled."""
        return np.isin(ids, np.fromiter(self.culled, np.int64, len(self.culled)))


def make_ba_step(seq: Sequence, vo: VOResult, cfg: RunConfig, record: BALog) -> GlobalBA:
    """The :data:`~mutualslam_cli.stages.adaptation.GlobalBA` step of a run (culling unless
    ``ba.culling=false`` or scheme ``none``), recording into ``record``."""
    images = ba_images(seq, vo)
    cull = no_culling_reason(cfg) is None

    def step(v: VOResult, kf_id: int, depth_of: Callable[[int], np.ndarray],
             val_loss: Mapping[int, float]) -> VOResult:
        r = run_global_ba(v, images, depth_of, val_loss, cfg.ba, cull=cull, upto=kf_id)
        record.culled.update(v.points.ids[~r.keep].tolist())
        record.runs.append({"kf_id": kf_id, **{k: x for k, x in r.stats.items() if k != "costs"}})
        log.info("global BA after keyframe %d: %d culled, %d refined (%d unrefined), cost %.4g -> %.4g, %.2f s",
                 kf_id, r.stats["n_culled"], r.stats["n_refined"], r.stats["n_unrefined"], r.stats["cost0"],
                 r.stats["cost"], r.stats["seconds"])
        return r.kept()

    return step


def final_ba(seq: Sequence, vo: VOResult, loop_map: VOResult, net: torch.nn.Module,
             adapter: OnlineAdapter | None, cfg: RunConfig, fast: bool, step: GlobalBA) -> VOResult:
    """The final culling + BA of the loop's map over every keyframe with the final network
    (L_val of every stored keyframe; none for scheme ``none``)."""
    load = keyframe_images(seq, vo, cfg.net.width, cfg.net.height)
    depth_of = depth_predictor(net, load, fast, adapter.buffer if adapter is not None else None)
    val_loss = adapter.per_keyframe_val_loss() if adapter is not None else {}
    return step(loop_map, len(loop_map.keyframes) - 1, depth_of, val_loss)


#: ``summary.json`` keys of culling and global BA (DESIGN §8).
BA_KEYS = ("trajectory.ate_rmse_m.ba", "trajectory.ate_rmse_m.all_frames_ba", "trajectory.ate_rmse_m_per_segment.ba",
           "trajectory.ate_rmse_m_per_segment.all_frames_ba", "map.points.culled", "map.points.ba", "map.esi.culled",
           "map.esi.ba", "timing.ba_s")


class BAStage:
    """Culling + global BA of a run: :attr:`step` at Algorithm 1's requests (handed to the
    adaptation stage: the mutual loop), then :meth:`finish` once at the end.

    Attributes:
        step: the :data:`~mutualslam_cli.stages.adaptation.GlobalBA` step, ``None`` with ``ba.enabled=false``.
        record: what each culling + BA did (:class:`BALog`).
    """

    def __init__(self, run: RunContext, fe: FrontEnd) -> None:
        self.run, self.fe = run, fe
        self.record = BALog()
        self.step = make_ba_step(run.seq, fe.vo, run.cfg, self.record) if run.cfg.ba.enabled else None

    def finish(self, adapted: Adapted, fast: bool) -> None:
        """The final culling + BA of the loop's map with the final network: ``map_culled.ply`` (the front
        end's map without the culled points), ``map_ba.ply``, ``traj_{kf,all}_ba.txt``, the keys of
        :data:`BA_KEYS`, ``ba.*`` and, with injected
        outliers, ``map.outliers.*`` and ``map.inliers.kept``."""
        run, fe, cfg = self.run, self.fe, self.run.cfg
        if self.step is None:
            for key in BA_KEYS:
                run.summary.absent(key, "disabled (ba.enabled=false)")
            run.summary.set("ba.triggers", 0)
            run.summary.set("ba.requested", adapted.requested)
        else:
            with run.timed("ba"):
                vo_ba = final_ba(run.seq, fe.vo, adapted.map, adapted.net, adapted.adapter, cfg, fast, self.step)
            self._write(vo_ba, adapted.requested)
        if len(fe.injected):
            culled = self.record.culled_mask(fe.vo.points.ids) if no_culling_reason(cfg) is None else None
            _summarise_outliers(run.summary, fe.vo.points.ids, fe.injected, culled)

    def _write(self, vo_ba: VOResult, requested: int) -> None:
        run, fe, summary = self.run, self.fe, self.run.summary
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
            summary.set("map.esi.culled", esi_of_log_errors(err[keep])[0],
                        "no kept map point has GT depth at its host pixel")
        summary.set("map.points.ba", len(vo_ba.points))
        summary.set("map.esi.ba", esi_of_log_errors(err_ba)[0], "no map point has GT depth at its host pixel after BA")
        summary.set("timing.ba_s", run.timings.get("ba", 0.0))  # Algorithm 1's triggers and the final one
        runs = self.record.runs
        summary.set("ba.triggers", len(runs) - 1)
        summary.set("ba.requested", requested)
        for key in ("n_judged_elsewhere", "n_refined", "n_unrefined", "n_diverged", "n_targets", "iterations",
                    "cost0", "cost"):
            summary.set(f"ba.final.{key}", runs[-1][key])


def _summarise_outliers(summary: Summary, ids: np.ndarray, injected: np.ndarray, culled: np.ndarray | None) -> None:
    """``map.outliers.{injected,culled}`` and ``map.inliers.kept`` of a run with ``vo.inject_outliers``.

    Args:
        ids: ``(P,)`` ids of every map point; injected: ids of the corrupted ones.
        culled: ``(P,)`` bool, culled points (``None``: this run did not cull).
    """
    bad = np.isin(ids, injected)
    summary.set("map.outliers.injected", int(bad.sum()))
    if culled is None:
        why = "no culling in this run (ba.enabled=false, ba.culling=false or scheme 'none')"
        summary.absent("map.outliers.culled", why)
        summary.absent("map.inliers.kept", why)
        return
    summary.set("map.outliers.culled", float(culled[bad].mean()) if bad.any() else None, "no outlier injected")
    summary.set("map.inliers.kept", float((~culled[~bad]).mean()) if (~bad).any() else None,
                "every point is an outlier")
