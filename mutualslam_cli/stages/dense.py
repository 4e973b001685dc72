"""The dense stage of a run: both models' depth fused along the run's poses, in metres,
scored against the same fusion of GT depth with GT poses.

:func:`run_dense` is what ``mslam run --set dense.enabled=true`` calls after the evaluation;
:func:`~mutualslam_cli.pipeline.fuse_run` runs it on a finished run folder that kept its adapted
weights (``mslam fuse``).
Both read the poses from the run folder's trajectory files, so they give the same meshes and scores.

- **Frames** (:mod:`~mutualslam_cli.stages.dense_frames`): the keyframes (``dense.every: 0``) or every k-th
  frame that has a pose.
- **Poses**: the trajectory of those frames after the global BA when the run has one
  (``traj_*_ba.txt``), else the front end's; each tracking segment brought into the GT frame by the
  Sim(3) aligning that trajectory to GT (Umeyama with scale on the pairs the ATE associates):
  ``T' = [R·R_wc | s·R·c + t]``. Segments with < 3 pairs are not fused.
- **Depth scale**: per model and sequence, ``k = median over the keyframes of median(z_vo / z_pred)``
  over the map points each keyframe observes (the sparse depth the adaptation trains on), then metres
  by the Sim(3) scale of the *front end's* trajectory (the map the ratios were taken in; after BA the
  poses keep their own Sim(3)). The same rule for both models: the adapted model is trained in map
  units, the pre-trained one is in arbitrary units. ``dense.scale.*``: k; ``dense.metric_scale.*``:
  the factor applied (metres per network unit).
- **Scalings** (``dense.scalings``, :mod:`~mutualslam_cli.dense.scaling`): the one factor above
  (``sequence``) scores shape *and* scale consistency at once, and favours the adapted model (trained on
  the same sparse depth). Each model is also fused with per-frame factors, one TSDF per scaling:
  ``frame``: the fused frame's own ``median(z_vo / z_pred)`` times the same metric scale (a frame
  observing no map point, e.g. a non-keyframe with ``dense.every`` > 0, takes the sequence factor;
  counted); ``gt``: ``median(D_gt / D)`` over the frame's valid GT pixels, an **oracle** bound on the
  scale, not on the scores (a frame without GT depth takes the sequence factor; counted). ``sequence``
  vs ``frame`` is the scale jitter the VO sees; ``gt`` leaves the shape alone. Only the sequence meshes
  are written and drawn; without a GT reference the per-frame scalings are not fused.
- **Keys**: ``dense.<score>.<model>`` (sequence scaling, as before), ``dense.frame_scale.<score>.<model>``
  and ``dense.gt_scale.<score>.<model>`` (scores: ``accuracy_m``, ``completeness_m``, ``fscore_5cm``,
  ``precision_5cm``, ``recall_5cm``, ``accuracy_median_m``, ``completeness_median_m``); beside them,
  per per-frame scaling and model, ``…metric_scale_median`` (median factor applied, m per network unit),
  ``…metric_scale_log_std`` (std of ln factor over the frames with their own: the jitter),
  ``…fallback_frames`` and ``…blocks`` / ``…triangles`` / ``…frames_capped``. A scaling left out of
  ``dense.scalings`` has its keys null with the reason.
- **Resolution**: predictions are fused at network resolution with the intrinsics scaled to it (what
  the network predicts; resizing to the image adds pixels, not information, and 2.5× the work at
  640×480); the GT reference at the image's resolution, undistorted like the frames.
- **Reference**: GT depth of the same frames with their GT poses (associated at image time by the
  loader); frames without either are skipped. Without GT depth the predicted meshes are still fused
  and every score is ``null`` with the reason; without GT poses nothing is fused (no metric scale).
"""
from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import cv2
import numpy as np
import torch

from mutualslam_cli.config import RunConfig, with_overrides
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.dense import scaling, tsdf
from mutualslam_cli.dense.picture import dense_picture
from mutualslam_cli.dense.scaling import PREFIX, SCALINGS
from mutualslam_cli.device import module_device
from mutualslam_cli.errors import GeometryError
from mutualslam_cli.geometry import pinhole
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.pixels import lookup_nearest
from mutualslam_cli.results.summary import Summary
from mutualslam_cli.stages.adaptation import Adapted
from mutualslam_cli.stages.context import RunContext
from mutualslam_cli.stages.dense_frames import FusedFrame, front_end_scales, select_frames
from mutualslam_cli.stages.evaluation import eval_batch, predictors_for
from mutualslam_cli.stages.frontend import FrontEnd
from mutualslam_cli.types import Progress
from mutualslam_cli.vo.camera import Undistorter

log = logging.getLogger(__name__)

MODELS = ("pretrained", "adapted")
_SCORES = ("accuracy_m", "completeness_m", "fscore_5cm")
_EXTRA = ("precision_5cm", "recall_5cm", "accuracy_median_m", "completeness_median_m")
#: Per-frame scalings' factor statistics, ``dense.<scaling>_scale.<stat>.<model>`` (module docstring).
_STATS = ("metric_scale_median", "metric_scale_log_std", "fallback_frames")
#: The dense scores, ``dense.<score>.<model>`` (DESIGN §8 style: null with a reason when absent).
DENSE_KEYS = tuple(f"dense.{k}.{m}" for k in _SCORES for m in MODELS)
#: Further per-model keys stored beside them.
EXTRA_KEYS = tuple(f"dense.{k}.{m}" for k in _EXTRA for m in MODELS)
#: Per scaling, its score keys ``<prefix><score>.<model>`` (``sequence``: ``DENSE_KEYS + EXTRA_KEYS``).
SCALED_KEYS = {s: tuple(f"{PREFIX[s]}{k}.{m}" for k in _SCORES + _EXTRA for m in MODELS) for s in SCALINGS}
#: Frames decoded and predicted at once in the prediction pass.
_GROUP = 8
#: Fewer frames to predict than this: PyTorch, not the evaluation's OpenVINO runtime. Converting a model
#: to OpenVINO costs ~4 s and saves ~50 ms per 640×192 frame here (130 vs 180 ms, one thread, bf16): it
#: pays from ~80 frames (the keyframes of the shared windows are 13–60).
OPENVINO_MIN_FRAMES = 80


# ----------------------------------------------------------------------------- the stage


def run_stage(run: RunContext, fe: FrontEnd, net0: torch.nn.Module, adapted: Adapted, fast: bool) -> None:
    """:func:`run_dense` of a run with ``dense.enabled``: both models along the run's poses."""
    with run.timed("dense"):
        run_dense(run.folder, run.seq, fe.vo,
                  {"pretrained": net0, "adapted": None if run.cfg.adapt.scheme == "none" else adapted.net},
                  run.cfg, fast, run.summary, run.progress)


def run_dense(folder: Path, seq: Sequence, vo: VOResult, nets: Mapping[str, torch.nn.Module | None], cfg: RunConfig,
              fast: bool, summary: Summary, progress: Progress | None = None) -> None:
    """Fuse, score and draw (module docstring); writes ``mesh_{pretrained,adapted,gt}.ply`` and
    ``dense.png`` into ``folder`` and the ``dense.*`` keys into ``summary``.

    Args:
        folder: the run folder (its ``traj_*.txt`` give the poses).
        vo: the run's front-end result (keyframes, map points, segments).
        nets: ``pretrained`` and ``adapted`` networks (``adapted`` None: scheme ``none``).
        progress: ``progress("dense", {"done", "total", "phase"})``.
    """
    t0 = time.perf_counter()
    dc = cfg.dense
    for key in [k for k in summary.values if k.startswith(tuple(PREFIX[s] for s in SCALINGS if s != "sequence"))]:
        summary.values.pop(key)  # none stale (the sequence keys below are all rewritten)
    for key in DENSE_KEYS + EXTRA_KEYS:
        summary.values.pop(key, None)
    for name in ("mesh_pretrained.ply", "mesh_adapted.ply", "mesh_gt.ply", "dense.png"):  # none stale
        (folder / name).unlink(missing_ok=True)
    summary.set("dense.block_cap", dc.block_count)
    summary.set("dense.memory_cap_mb", tsdf.block_memory_bytes(dc.block_resolution, dc.block_count) / 1e6)
    for s in SCALINGS:
        if s not in dc.scalings:
            for key in SCALED_KEYS[s] + tuple(f"{PREFIX[s]}{k}.{m}" for k in _STATS for m in MODELS):
                summary.absent(key, f"dense.scalings leaves out {s!r} ({scaling.DESCRIPTION[s]})")
    try:
        _run(folder, seq, vo, nets, cfg, fast, summary, progress)
    except GeometryError as e:  # nothing to bring into metres: every key null with the reason
        for key in (k for s in SCALINGS if s in dc.scalings for k in SCALED_KEYS[s]):
            summary.absent(key, str(e))
    summary.set("dense.time_s", time.perf_counter() - t0)
    log.info("dense: F@5cm pre-trained %s, adapted %s (%.1f s)", summary.values.get("dense.fscore_5cm.pretrained"),
             summary.values.get("dense.fscore_5cm.adapted"), summary.values["dense.time_s"])


def _run(folder: Path, seq: Sequence, vo: VOResult, nets: Mapping[str, torch.nn.Module | None], cfg: RunConfig,
         fast: bool, summary: Summary, progress: Progress | None) -> None:
    dc = cfg.dense
    if seq.gt is None or len(seq.gt) == 0:
        raise GeometryError("sequence has no GT poses: no Sim(3) to bring the run into metres")
    fused, sim_scales, note = select_frames(seq, vo, folder, dc.every, cfg.eval.ate_max_dt)
    if not fused:
        raise GeometryError(f"no frame to fuse ({note})")
    present = {m: net for m in MODELS if (net := nets.get(m)) is not None}
    models = list(present)
    scalings = [s for s in SCALINGS if s in dc.scalings]
    seg_count = {s: sum(f.segment == s for f in fused) for s in sim_scales}
    summary.set("dense.sim3_scale", sim_scales[max(seg_count, key=lambda s: (seg_count[s], -s))])
    summary.set("dense.segments", len(sim_scales))
    summary.set("dense.frames", len(fused))
    summary.set("dense.source", note)
    n_ref = sum(seq.frames[f.frame].depth_path is not None and seq.frames[f.frame].pose is not None for f in fused)
    summary.set("dense.frames_reference", n_ref)
    no_ref = None if n_ref else "sequence has no GT depth at the fused frames: no reference surface"
    total = len(fused) * (len(models) * len(scalings) + 1) + len(vo.keyframes)
    done = [0]

    def tick(phase: str) -> None:
        done[0] += 1
        if progress:
            progress("dense", {"done": done[0], "total": total, "phase": phase})

    meshes: dict[str, tsdf.Mesh] = {}
    with tempfile.TemporaryDirectory(prefix=".dense-", dir=folder) as tmp:
        preds, rgbs, scales, own = _predict(Path(tmp), seq, vo, fused, present, cfg, fast, tick)
        ref, own["gt"] = _reference(folder, seq, fused, preds, n_ref > 0, "gt" in scalings, cfg, summary, tick)
        if ref is not None:
            meshes["gt"] = ref
        K_net = vo.intrinsics.scaled(cfg.net.width, cfg.net.height).K()
        for m in models:
            k, metric = scales[m]
            summary.set(f"dense.scale.{m}", k, "no keyframe observes a map point with a positive prediction")
            summary.set(f"dense.metric_scale.{m}", metric, "no keyframe in an aligned segment observes a map point")
            for s in scalings:
                factors, why = _factors(s, m, own, metric, len(fused), summary)
                if factors is None or (s != "sequence" and no_ref):  # without a reference only the sequence
                    done[0] += len(fused)                                # meshes are fused (written, drawn)
                    _score(None, ref, s, m, cfg, summary, no_ref or why)
                    continue
                vol = _volume(cfg)
                for j in range(len(fused)):
                    vol.integrate(preds[m][j] * float(factors[j]), K_net, fused[j].T_metric, rgbs[j])
                    tick(f"fuse {m} ({s} scale)")
                mesh = _finish(vol, folder / f"mesh_{m}.ply" if s == "sequence" else None, PREFIX[s], m, cfg, summary)
                del vol  # one grid at a time (its memory is allocated whole)
                _score(mesh, ref, s, m, cfg, summary, no_ref)
                if s == "sequence":
                    meshes[m] = mesh
    for m in MODELS:
        if m not in models:
            for s in scalings:
                _score(None, None, s, m, cfg, summary, no_ref or f"no {m} model in this run")
    if cfg.adapt.scheme == "none" and "pretrained" in meshes:
        stats = [f"{PREFIX[s]}{x}.adapted" for s in scalings if s != "sequence" for x in _STATS]
        for key in [k for s in scalings for k in SCALED_KEYS[s] if k.endswith(".adapted")] + stats:
            src = key[: -len("adapted")] + "pretrained"
            summary.values[key] = summary.values.get(src)
            summary.notes[key] = "scheme 'none': the adapted model is the pre-trained model"
    _picture(folder / "dense.png", meshes, fused, seq, summary, cfg)


def _factors(s: str, m: str, own: dict[str, dict[str, np.ndarray]], metric: float | None, n: int,
             summary: Summary) -> tuple[np.ndarray | None, str | None]:
    """Factor (m per network unit) of each fused frame under scaling ``s`` for model ``m``, with the
    scaling's statistics in ``summary``; ``(None, reason)`` when some frame has none."""
    if s == "sequence":
        return (None, summary.notes.get(f"dense.metric_scale.{m}")) if metric is None else (np.full(n, metric), None)
    p = PREFIX[s]
    factors, n_fb = scaling.with_fallback(own[s][m], metric)
    summary.set(f"{p}fallback_frames.{m}", n_fb)
    summary.set(f"{p}metric_scale_log_std.{m}", scaling.log_spread(own[s][m]),
                "fewer than 2 fused frames have their own scale")
    why = (None if factors is not None else
           f"{n_fb} fused frames have no {scaling.DESCRIPTION[s]} and there is no sequence scale to fall back on "
           f"({summary.notes.get(f'dense.metric_scale.{m}', 'none')})")
    summary.set(f"{p}metric_scale_median.{m}", None if factors is None else scaling.median_factor(factors),
                why or "no factor")
    return factors, why


def _volume(cfg: RunConfig) -> tsdf.TSDFVolume:
    dc = cfg.dense
    return tsdf.TSDFVolume(dc.voxel_size, dc.trunc_voxels, dc.depth_min, dc.depth_max, dc.block_resolution,
                           dc.block_count)


def _finish(vol: tsdf.TSDFVolume, path: Path | None, prefix: str, name: str, cfg: RunConfig,
            summary: Summary) -> tsdf.Mesh:
    """Extract one mesh and write it (``path`` not None); record its blocks, triangles and capped frames
    as ``<prefix>{blocks,triangles,frames_capped}.<name>``."""
    mesh = vol.mesh(cfg.dense.weight_threshold)
    if path is not None:
        tsdf.write_mesh(path, mesh)
    summary.set(f"{prefix}blocks.{name}", vol.blocks)
    summary.set(f"{prefix}triangles.{name}", len(mesh.triangles))
    summary.set(f"{prefix}frames_capped.{name}", vol.frames["existing_only"] + vol.frames["skipped"])
    return mesh


def _reference(folder: Path, seq: Sequence, fused: list[FusedFrame], preds: dict[str, np.ndarray], fuse: bool,
               gt_scale: bool, cfg: RunConfig, summary: Summary,
               tick: Callable[[str], None]) -> tuple[tsdf.Mesh | None, dict[str, np.ndarray]]:
    """One pass over the GT depth of the fused frames: their fusion with the GT poses (``fuse``; written
    to ``mesh_gt.ply``) and, with ``gt_scale``, each model's per-frame factor ``median(D_gt / D)``
    (:func:`~mutualslam_cli.dense.scaling.gt_factor`; ``(N,)``, NaN without GT depth)."""
    gt_own = {m: np.full(len(fused), np.nan) for m in preds}
    vol = _volume(cfg) if fuse else None
    und, K_img = Undistorter(seq.intrinsics), pinhole(seq.intrinsics).K()
    for j, f in enumerate(fused):
        fr = seq.frames[f.frame]
        depth = seq.load_depth(f.frame) if (fuse and fr.pose is not None) or gt_scale else None
        if depth is not None:
            depth = und.depth(depth)
            if vol is not None and fr.pose is not None:
                vol.integrate(depth, K_img, fr.pose, und.image(seq.load_rgb(f.frame)))
            if gt_scale:
                for m in preds:
                    gt_own[m][j] = scaling.gt_factor(preds[m][j], depth, cfg.eval.max_depth)
        tick("fuse GT")
    mesh = None if vol is None else _finish(vol, folder / "mesh_gt.ply", "dense.", "gt", cfg, summary)
    return mesh, gt_own


def _predict(tmp: Path, seq: Sequence, vo: VOResult, fused: list[FusedFrame], nets: dict[str, torch.nn.Module],
             cfg: RunConfig, fast: bool, tick: Callable[[str], None]) -> tuple[dict, np.ndarray, dict, dict]:
    """One pass over the keyframes and the fused frames: each model's depth of the fused frames and
    their RGB at network resolution, kept in memory-mapped files under ``tmp`` (memory stays flat in
    the sequence length), each model's scale ``(k, metres per network unit)`` (module docstring), and
    ``{"frame": {model: (N,)}}``: each fused frame's own metric factor (NaN: it observes no map point)."""
    w, h = cfg.net.width, cfg.net.height
    slot = {f.frame: j for j, f in enumerate(fused)}
    kf_of = {k.frame_index: k for k in vo.keyframes}
    need = sorted(set(slot) | set(kf_of))
    preds = {m: np.lib.format.open_memmap(tmp / f"{m}.npy", "w+", np.float32, (len(fused), h, w)) for m in nets}
    rgbs = np.lib.format.open_memmap(tmp / "rgb.npy", "w+", np.uint8, (len(fused), h, w, 3))
    if len(need) < OPENVINO_MIN_FRAMES:
        cfg = with_overrides(cfg, net={"runtime": "torch"})
    predictors = predictors_for(seq, nets, cfg, fast)
    vo_scale = front_end_scales(seq, vo, cfg)
    pw = vo.points_world()
    ratios: dict[str, list[tuple[float, float]]] = {m: [] for m in nets}
    own = {m: np.full(len(fused), np.nan) for m in nets}
    und = Undistorter(seq.intrinsics)
    bs = eval_batch(cfg, module_device(next(iter(nets.values()))))
    for start in range(0, len(need), _GROUP):
        chunk = need[start:start + _GROUP]
        frames = [und.image(seq.load_rgb(i)) for i in chunk]
        out = {m: np.concatenate([predict(frames[b:b + bs]) for b in range(0, len(chunk), bs)])
               for m, predict in predictors.items()}
        for j, i in enumerate(chunk):
            if i in slot:
                rgbs[slot[i]] = cv2.resize(frames[j], (w, h), interpolation=cv2.INTER_AREA)
                for m in nets:
                    preds[m][slot[i]] = out[m][j]
            kf = kf_of.get(i)
            if kf is not None:
                uv, z = vo.sparse_depth(kf.id, pw)
                for m in nets:
                    d = lookup_nearest(out[m][j], uv, (vo.intrinsics.width, vo.intrinsics.height))
                    ok = d > 0  # False outside (NaN)
                    if ok.any():
                        r = float(np.median(z[ok] / d[ok]))  # z_vo / z_pred, map units per network unit
                        ratios[m].append((r, r * vo_scale[kf.segment] if kf.segment in vo_scale else np.nan))
                        if i in slot:
                            own[m][slot[i]] = ratios[m][-1][1]
                tick("predict")
    scales = {}
    for m in nets:
        rs = np.array(ratios[m], np.float64).reshape(-1, 2)
        metric = rs[np.isfinite(rs[:, 1]), 1]
        scales[m] = (float(np.median(rs[:, 0])) if len(rs) else None, float(np.median(metric)) if len(metric) else None)
    return preds, rgbs, scales, {"frame": own}


def _score(mesh: tsdf.Mesh | None, ref: tsdf.Mesh | None, s: str, m: str, cfg: RunConfig, summary: Summary,
           why: str | None) -> None:
    """The scores of model ``m``'s mesh under scaling ``s`` against the GT mesh, ``<prefix><score>.<m>``
    (all null with ``why``, or with the scoring error, when there is nothing to score)."""
    if why is None and (mesh is None or ref is None):
        why = "no mesh to score"
    if why is None and mesh is not None and ref is not None:  # both there (else why is set above)
        try:
            r = tsdf.score_surfaces(mesh, ref, cfg.dense.voxel_size)
        except GeometryError as e:
            why = str(e)
    p = PREFIX[s]
    if why is not None:
        for key in _SCORES + _EXTRA:
            summary.absent(f"{p}{key}.{m}", why)
        return
    for key, val in (("accuracy_m", r.accuracy_m), ("completeness_m", r.completeness_m), ("fscore_5cm", r.fscore),
                     ("precision_5cm", r.precision), ("recall_5cm", r.recall),
                     ("accuracy_median_m", r.accuracy_median_m), ("completeness_median_m", r.completeness_median_m)):
        summary.set(f"{p}{key}.{m}", val)


def _picture(path: Path, meshes: dict[str, tsdf.Mesh], fused: list[FusedFrame], seq: Sequence,
             summary: Summary, cfg: RunConfig) -> None:
    """``dense.png`` (:func:`~mutualslam_cli.dense.picture.dense_picture`) from the GT poses of the fused frames."""
    if meshes:
        gt = [pose for f in fused if (pose := seq.frames[f.frame].pose) is not None]
        scores = {m: {k: summary.number(f"dense.{k}.{m}") for k in ("fscore_5cm", "accuracy_m", "completeness_m")}
                  for m in meshes}
        dense_picture(path, meshes, np.stack(gt) if gt else np.stack([f.T_metric for f in fused]), scores,
                      f"{seq.name}: TSDF meshes ({cfg.dense.voxel_size * 100:g} cm voxels, "
                      f"{scaling.DESCRIPTION['sequence']}), same viewpoint",
                      cfg.dense.render_width, max(cfg.threads, 0), mirror=seq.intrinsics.fy < 0)
