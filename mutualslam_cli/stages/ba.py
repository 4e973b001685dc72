"""The final culling + global BA of a run (paper §III-C) and the outputs of every culling + BA it made.

:class:`BAStage` holds the run's :class:`~mutualslam_cli.backend.refine.MapBA` — the culling + BA the
adaptation loop calls at Algorithm 1's requests and after loop closures
(:func:`~mutualslam_cli.backend.refine.refine_map`: the mutual loop) — refines the whole map at the end
(:func:`final_ba`) and writes its maps, trajectories and summary keys.
"""

from __future__ import annotations

import numpy as np
import torch

from mutualslam_cli.adapt.inputs import keyframe_images
from mutualslam_cli.adapt.online import OnlineAdapter
from mutualslam_cli.backend.ba.global_ba import BAStats, window_start
from mutualslam_cli.backend.refine import MapBA
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.metrics.slam import (
    common_frames_ate,
    esi_of_log_errors,
    evaluate_trajectory,
    map_log_depth_errors,
    point_units,
)
from mutualslam_cli.online.labels import depth_predictor
from mutualslam_cli.results.map_ply import write_ply
from mutualslam_cli.results.run_folder import write_trajectories
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.adaptation import Adapted
from mutualslam_cli.stages.ate_keys import set_ate
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.frontend import FrontEnd


def no_culling_reason(cfg: RunConfig) -> str | None:
    """Why a run's global BA does not cull (``None``: it culls with the adapted network)."""
    if not cfg.ba.enabled:
        return "disabled (ba.enabled=false)"
    if not cfg.ba.culling:
        return "disabled (ba.culling=false): BA without culling"
    if cfg.adapt.scheme == "none":
        return "scheme 'none': no adapted network to cull with"
    return None


def final_ba(seq: Sequence, loop_map: VOResult, net: torch.nn.Module, adapter: OnlineAdapter | None,
             cfg: RunConfig, fast: bool, ba: MapBA) -> VOResult:
    """The final culling + BA of the loop's map over every keyframe (the newest ``ba.window`` with a window)
    with the final network (L_val of those keyframes; none for scheme ``none``); the refined map without
    the culled and dropped points."""
    load = keyframe_images(seq, loop_map, cfg.net.width, cfg.net.height)
    depth_of = depth_predictor(net, load, fast, adapter.buffer if adapter is not None else None)
    last = len(loop_map.keyframes) - 1
    ids = list(range(window_start(last, cfg.ba.window), last + 1)) if cfg.ba.window else None
    val_loss = adapter.per_keyframe_val_loss(ids) if adapter is not None else {}
    return ba.run_ba(loop_map, last, depth_of, val_loss).kept()


#: ``summary.json`` keys of culling and global BA (DESIGN §8).
BA_KEYS = ("trajectory.ate_rmse_m.ba", "trajectory.credit.ba", "trajectory.credit_kf.ba",
           "trajectory.ate_rmse_m.all_frames_ba",
           "trajectory.ate_rmse_m_per_segment.ba",
           "trajectory.ate_rmse_m_per_segment.all_frames_ba", "map.points.culled", "map.points.ba", "map.esi.culled",
           "map.esi.ba", "timing.ba_s")


class BAStage:
    """Culling + global BA of a run: :attr:`map_ba` at Algorithm 1's requests and loop closures (the adaptation
    loop hands the refined map back to the front end: the mutual loop), then :meth:`finish` once at the end.

    Attributes:
        map_ba: the run's culling + BA (:class:`~mutualslam_cli.backend.refine.MapBA`); record: its log.
        final: the map after culling + BA once :meth:`finish` ran (``None``: no such map, ``why_no_final`` says why).
    """

    def __init__(self, run: RunContext) -> None:
        self.run = run
        self.map_ba = MapBA(run.seq, run.cfg.ba, cull=no_culling_reason(run.cfg) is None)
        self.record = self.map_ba.record
        self.final: VOResult | None = None
        self.why_no_final = "culling + global BA not finished"

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
                vo_ba = final_ba(run.seq, adapted.map, adapted.net, adapted.adapter, cfg, fast, self.map_ba)
        elif self.record.runs:
            vo_ba = adapted.map
            last = self.record.runs[-1].kf_id
            if last < len(vo_ba.keyframes) - 1:
                run.summary.notes["trajectory.ate_rmse_m.ba"] = (
                    f"ba.final=on_request: the map after the BAs Algorithm 1 requested; keyframes after {last} "
                    f"(of {len(vo_ba.keyframes)}) were tracked after the last one and not refined by any")
        else:
            why = "ba.final=on_request and " + (adapted.why_no_request(cfg.adapt.tau_val, cfg.adapt.patience)
                                                if adapted.adapter is not None else
                                                f"scheme {cfg.adapt.scheme!r} runs no Algorithm 1")
        self.final, self.why_no_final = vo_ba, why or ""
        if vo_ba is None:  # no final BA: why says why (set on each branch that leaves vo_ba None)
            self._absent(self.why_no_final)
        else:
            self._write(vo_ba, fe, adapted)
        self._credit(fe, adapted, vo_ba, why)
        if len(fe.injected):
            culled = self.record.culled_mask(fe.vo.points.ids) if self.record.runs and no_culling_reason(cfg) is None \
                else None
            _summarise_outliers(run.summary, fe.vo.points.ids, fe.injected, culled,
                                self.record.dropped_mask(fe.vo.points.ids) if self.record.runs else None)

    def _credit(self, fe: FrontEnd, adapted: Adapted, vo_ba: VOResult | None, why: str | None) -> None:
        """Table 4's columns on the same frames, one Sim(3) each: the front end on its own (``vo``), joined by the
        run's bridges and nothing else (``bridged``), the run's own map as it ended before ``ba.final``'s last BA
        (``live``: its bridges, merges, and the BAs and loop closures Algorithm 1 made — with ``ba.enabled=false``
        and ``loop.enabled=false`` the front end + bridges + merges alone), after culling + BA (``ba``).
        ``trajectory.credit.*`` over every frame every column tracked, ``trajectory.credit_kf.*`` over the
        keyframes every column has; ``frames``: how many."""
        maps = {"vo": fe.vo, "bridged": adapted.bridged, "live": adapted.map, "ba": vo_ba}
        summary = self.run.summary
        for group, kf in (("credit", False), ("credit_kf", True)):
            ates, n, no = common_frames_ate(self.run.seq, maps, self.run.cfg.eval.ate_max_dt, keyframes=kf)
            summary.set(f"trajectory.{group}.frames", n)
            for k, v in ates.items():
                why_k = why if k == "ba" and why is not None else "not computed"
                summary.set(f"trajectory.{group}.{k}", v, no or why_k)

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
        units = vo_ba.unit_of_segment()
        summary.set("map.points.ba", len(vo_ba.points))
        summary.set("map.esi.ba", esi_of_log_errors(err_ba, point_units(vo_ba, units))[0],
                    "no map point has GT depth at its host pixel after BA")
        summary.set("timing.ba_s", run.timings.get("ba", 0.0))  # Algorithm 1's requests and the final one
        runs = self.record.runs
        summary.set("ba.runs", len(runs))
        summary.set("ba.points_dropped", len(self.record.dropped))
        for key, value in _last_run(runs[-1].stats).items():
            summary.set(key, value)


def _last_run(s: BAStats) -> dict[str, int | float]:
    """The ``summary.json`` keys ``ba.last.*`` of a run's last culling + BA ``s``: its counts and costs."""
    return {"ba.last.keyframes": s.keyframes, "ba.last.n_culled": s.n_culled,
            "ba.last.n_judged_elsewhere": s.n_judged_elsewhere, "ba.last.n_refined": s.n_refined,
            "ba.last.n_unrefined": s.n_unrefined, "ba.last.n_diverged": s.n_diverged, "ba.last.n_dropped": s.n_dropped,
            "ba.last.n_targets": s.n_targets, "ba.last.n_nearby_targets": s.n_nearby_targets,
            "ba.last.n_blocks": s.n_blocks, "ba.last.n_outlier_blocks": s.n_outlier_blocks,
            "ba.last.iterations": s.iterations, "ba.last.cost0": s.cost0, "ba.last.cost": s.cost}


#: ``summary.json`` keys of the last culling + BA of a run (its counts, ``ba.last.*``: :func:`_last_run`) and the
#: points the BAs dropped as outliers (``ba.points_dropped``).
BA_RUN_KEYS = ("ba.points_dropped",) + tuple(_last_run(BAStats()))


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
