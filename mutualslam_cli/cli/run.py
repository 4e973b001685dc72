"""``mslam run``, ``fuse``, ``eval-depth`` and ``ate``: one sequence, its dense reconstruction,
another network's predictions scored alike, and the ATE of two trajectory files.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.markup import escape
from rich.progress import TaskID
from rich.table import Table

from mutualslam_cli.cli import common
from mutualslam_cli.cli.common import (
    ConfigOpt,
    DataRootOpt,
    DeviceOpt,
    RegistryOpt,
    ResultsOutOpt,
    SetOpt,
    app,
    config_from,
    fmt_value,
    progress_bar,
    progress_figure,
)
from mutualslam_cli.config import with_overrides
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.results.writable import check_output_folder

if TYPE_CHECKING:
    from mutualslam_cli.results.summary import RunSummary
    from mutualslam_cli.types import Info, JSONObject

# --------------------------------------------------------------------------- run


def _render_summary(folder: Path, f: RunSummary) -> None:
    t = Table("metric", "pre-trained", "adapted",
              title=escape(f"{f.get('sequence.name')} · {f.get('scheme')} · seed {f.get('seed')}"))
    rows = [("PCD lsq (%)", "depth.pcd.lsq"), ("PCD median (%)", "depth.pcd.median"), ("e_si", "depth.esi")]
    if f.get("dense.time_s") is not None:  # the dense stage ran
        rows += [("dense accuracy m", "dense.accuracy_m"), ("dense completeness m", "dense.completeness_m"),
                 ("dense F-score @5cm", "dense.fscore_5cm")]
    for label, key in rows:
        t.add_row(label, fmt_value(f.get(f"{key}.pretrained"), 3 if key.startswith("dense") else 2),
                  fmt_value(f.get(f"{key}.adapted"), 3 if key.startswith("dense") else 2))
    for q, label in (("q1", "PCD lsq, first quarter"), ("q4", "PCD lsq, last quarter")):
        if f.get(f"depth.quarter_pcd_lsq.adapted.{q}") is not None:
            t.add_row(label, fmt_value(f.get(f"depth.quarter_pcd_lsq.pretrained.{q}"), 2),
                      fmt_value(f.get(f"depth.quarter_pcd_lsq.adapted.{q}"), 2))
    notes = f.notes
    if notes.get("depth.bwt.vs_pretrained"):
        t.caption = escape(f"note: {notes['depth.bwt.vs_pretrained']}")
    if f.get("depth.pcd.lsq.adapted") is None and notes.get("depth.pcd.lsq.adapted"):
        t.caption = escape(f"no depth score: {notes['depth.pcd.lsq.adapted']}")  # a recording without GT, say
    common.console.print(t)
    t2 = Table("trajectory (keyframes, one Sim(3))", "ATE m", "per segment m")
    for label, leaf in (("front end", "vo"), ("bridged segments", "bridged"), ("after global BA", "ba")):
        if f.get(f"trajectory.ate_rmse_m.{leaf}") is not None:
            t2.add_row(label, fmt_value(f.get(f"trajectory.ate_rmse_m.{leaf}"), 4),
                       fmt_value(f.get(f"trajectory.ate_rmse_m_per_segment.{leaf}"), 4))
    if not t2.row_count:
        t2.caption = escape(f"no ATE: {notes.get('trajectory.ate_rmse_m.vo', 'not computed')}")
    common.console.print(t2)
    t3 = Table("tracked", "segments", "relocalised", "bridged", "merged", "map units", "keyframes", "map points",
               "map e_si", "depth ms", "ms/step")
    cells = [("vo.tracked_fraction", 3), ("vo.segments", 0), ("vo.relocalisations", 0), ("vo.bridges", 0),
             ("vo.merges", 0), ("vo.live.map_units", 0),
             ("vo.keyframes", 3), ("map.points.vo", 3), ("map.esi.vo", 3), ("timing.depth_ms", 1),
             ("timing.finetune_ms", 0)]
    t3.add_row(*(fmt_value(f.get(key), nd) for key, nd in cells))
    common.console.print(t3)
    common.console.print(_stage_table(f))
    common.console.print(f"results: {escape(str(folder))}")


#: The stage table's columns: label → summary key (seconds); the fine-tuning's steps are part of adaptation.
STAGE_COLUMNS = (("front end", "timing.stage_s.frontend"), ("adaptation", "timing.stage_s.adaptation"),
                 ("of it steps", "timing.finetune_steps_s"), ("of it Fisher etc.", "timing.finetune_consolidate_s"),
                 ("of it L_val", "timing.l_val_s"), ("BA", "timing.stage_s.ba"),
                 ("evaluation", "timing.stage_s.evaluation"), ("of it online", "timing.online_scoring_s"),
                 ("dense", "timing.stage_s.dense"), ("other", "timing.stage_s.other"), ("total", "timing.total_s"))


def _stage_table(f: RunSummary) -> Table:
    """Where a run's time went (seconds), on which device, and its cost beyond its optimiser steps."""
    cols = [(label, key) for label, key in STAGE_COLUMNS if f.get(key) is not None]
    t = Table(*(label for label, _ in cols), title="time (s)")
    t.add_row(*(fmt_value(f.number(key), 1) for _, key in cols))
    device = " · ".join(fmt for k, fmt in (("run.device", "{}"), ("run.device_name", "{}"),
                                            ("run.device_memory_gb", "{} GiB"), ("run.cuda_version", "CUDA {}"),
                                            ("run.cudnn_version", "cuDNN {}")) if f.get(k) is not None
                        for fmt in [fmt.format(f.get(k))])
    beyond = f.number("timing.beyond_steps")
    extra = f"; beyond the steps: +{100 * beyond:.0f} %" if beyond else ""
    med, p99, top, over = (f.number(k) for k in ("timing.step_ms.median", "timing.step_ms.p99", "timing.step_ms.max",
                                                  "timing.steps_over_median"))
    if med is not None and p99 is not None and top is not None and over is not None:
        extra += f"; a step: median {med:.0f} ms, p99 {p99:.0f}, max {top:.0f} (steps' sum = {over:.2f} × n × median)"
    t.caption = escape(f"device: {device or '?'}{extra}")
    return t


@app.command()
def run(
    seq: str = typer.Argument(..., help="datasets.yaml name or sequence folder."),
    scheme: str | None = typer.Option(None, "--scheme", help="Adaptation scheme (default from config: replay+ewc)."),
    vo: str | None = typer.Option(
        None, "--vo", help="svo | gt (pose oracle: our VO's tracks with GT poses) | "
                           "gt-depth (GT poses and GT sparse depth: an upper bound)."),
    weights: Path | None = typer.Option(None, "--weights", help="Folder with Monodepth2 encoder.pth/depth.pth."),
    seed: int | None = typer.Option(None, "--seed"),
    out: Path | None = ResultsOutOpt,
    force: bool = typer.Option(False, "--force", help="Recompute a complete run."),
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
    data_root: str | None = DataRootOpt,
    registry: Path | None = RegistryOpt,
    device: str | None = DeviceOpt,
    rgb_topic: str | None = typer.Option(None, "--rgb-topic", help="Bag: colour image topic (Image or "
                                            "CompressedImage; default the only non-depth image topic)."),
    depth_topic: str | None = typer.Option(None, "--depth-topic", help="Bag: depth topic (16UC1 mm or 32FC1 m; "
                                              "default none)."),
    camera_info_topic: str | None = typer.Option(None, "--camera-info-topic", help="Bag: CameraInfo topic "
                                                    "(default the one beside the colour topic)."),
    pose_topic: str | None = typer.Option(None, "--pose-topic", help="Bag: GT poses (PoseStamped, "
                                             "TransformStamped or Odometry; camera-to-world)."),
    gt: Path | None = typer.Option(None, "--gt", help="GT trajectory file (TUM: timestamp tx ty tz qx qy qz qw)."),
    camera: Path | None = typer.Option(None, "--camera", help="Camera file: OpenCV calibration YAML, ROS "
                                          "camera YAML, or a line 'fx fy cx cy \\[k1 k2 p1 p2 k3]'."),
    fps: float | None = typer.Option(None, "--fps", help="Image folder without timestamps in the file names: "
                                        "frames per second (default 30)."),
) -> None:
    """One sequence, one scheme: front end → adaptation → evaluation → results/<seq>/<scheme>/seed<k>/.

    SEQ may also be a ROS 1/2 bag, a video, or an image folder with --camera: converted once into a
    TUM-layout folder under <out>/_cache/recordings. Without GT, every GT metric is null with its reason."""
    from mutualslam_cli.adapt.schemes import get_scheme
    from mutualslam_cli.datasets.recordings.recording import RecordingOptions
    from mutualslam_cli.pipeline import run_sequence

    cfg = config_from(config, sets, data_root, device)
    over: dict[str, JSONObject | int | None] = {"adapt": {"scheme": scheme} if scheme else None,
                             "vo": {"mode": vo} if vo else None,
                             "net": {"weights": str(weights)} if weights else None, "seed": seed}
    cfg = with_overrides(cfg, **{k: v for k, v in over.items() if v is not None})
    get_scheme(cfg.adapt.scheme, cfg.adapt)  # unknown name or bad setting → ConfigError, before any work
    check_output_folder(out if out is not None else cfg.out)  # a file, read-only: one line, before the bars
    with progress_bar() as p:
        tasks: dict[str, TaskID] = {}

        def cb(stage: str, info: Info) -> None:
            total = progress_figure(info.get("total", info.get("n_frames")))
            if stage not in tasks:
                tasks[stage] = p.add_task({"convert": "convert recording", "vo": "front end", "adapt": "adapt",
                                           "eval": "evaluate", "dense": "dense"}.get(stage, stage),
                                          total=total, info="")
            if stage != "convert" and "convert" in tasks:  # the conversion is over: its bar stops its clock
                tid = tasks.pop("convert")
                p.update(tid, total=next(t.completed for t in p.tasks if t.id == tid))
            frame = progress_figure(info.get("frame"))
            done = progress_figure(info["done"]) if "done" in info else (frame if frame is not None else -1.0) + 1
            if stage == "vo":
                text = f"kf {info.get('keyframes', 0)} · pts {info.get('tracked', 0)} · {info.get('state', '')}"
                if info.get("fps"):
                    text += f" · {info['fps']:.0f} fps"
            elif stage == "adapt":
                lv = info.get("l_val")
                lv = None if lv is None or lv != lv else lv
                what = "validate" if info.get("is_validation") else ("fine-tune" if info.get("trained") else "wait")
                text = (f"{what} · loss {fmt_value(info.get('loss_total'), 4)} · L_val {fmt_value(lv, 4)}"
                        f" · converged {info.get('n_converged', 0)}")
            else:
                text = str(info.get("phase", ""))
            p.update(tasks[stage], completed=done, total=total, info=text)

        rec = RecordingOptions(rgb_topic, depth_topic, camera_info_topic, pose_topic, gt, camera, fps)
        r = run_sequence(seq, cfg, out=out, command=sys.argv, force=force, progress=cb, registry=registry,
                         recording=rec)
    if r.skipped:
        common.console.print(f"[yellow]already complete[/] (use --force to recompute): {r.folder}")
    _render_summary(r.folder, r.summary)


# --------------------------------------------------------------------------- fuse


@app.command()
def fuse(
    run_dir: Path = typer.Argument(..., help="A finished run folder (<out>/<seq>/<scheme>/seed<k>) with weights/."),
    sets: list[str] | None = SetOpt,
    registry: Path | None = RegistryOpt,
) -> None:
    """Dense reconstruction of a finished run: TSDF meshes of both models' depth, scored against GT depth
    fused with GT poses (needs the run's adapted weights: --set eval.save_weights=true)."""
    from mutualslam_cli.pipeline import fuse_run

    with progress_bar() as p:
        tasks: list[TaskID] = []  # the bar appears with the first step: an error before it is one line

        def cb(stage: str, info: Info) -> None:
            if stage == "dense":  # a front end recomputed (no VO cache) reports as "vo": not this bar
                tasks[:] = tasks or [p.add_task("dense", total=progress_figure(info["total"]), info="")]
                p.update(tasks[0], completed=progress_figure(info["done"]), total=progress_figure(info["total"]),
                         info=info.get("phase", ""))

        f = fuse_run(run_dir, sets or [], registry, command=sys.argv, progress=cb)
    t = Table("scale", "metric", "pre-trained", "adapted",
              title=escape(f"{f.get('sequence.name')} · dense ({f.get('dense.source')})"))
    for scale, prefix in (("sequence (VO)", "dense."), ("per frame (VO)", "dense.frame_scale."),
                          ("per frame (GT, oracle)", "dense.gt_scale.")):
        if f.get(f"{prefix}fscore_5cm.adapted") is None and prefix != "dense.":
            continue  # a scaling not fused (dense.scalings) or without a GT reference
        for label, key in (("accuracy m", "accuracy_m"), ("completeness m", "completeness_m"),
                           ("F-score @5cm", "fscore_5cm")):
            t.add_row(scale if key == "accuracy_m" else "", label, fmt_value(f.get(f"{prefix}{key}.pretrained"), 4),
                      fmt_value(f.get(f"{prefix}{key}.adapted"), 4))
    common.console.print(t)
    common.console.print(f"meshes and dense.png in {run_dir} ({fmt_value(f.get('dense.time_s'), 1)} s)")


# --------------------------------------------------------------------------- eval-depth


@app.command("eval-depth")
def eval_depth(
    seq: str = typer.Argument(..., help="datasets.yaml name or sequence folder."),
    predictions: Path = typer.Argument(..., help="Folder with one prediction per frame (.npy, .npz, 16-bit .png, "
                                       ".pfm), named by the RGB file's stem or by the frame's timestamp."),
    name: str = typer.Option(..., "--name", help="The model's name: its row in the report (not a scheme's name)."),
    kind: str = typer.Option("depth", "--kind", help="depth | inverse | relative-inverse (MiDaS: aligned per "
                             "frame by least-squares scale and shift in inverse depth)."),
    scale: float = typer.Option(1.0, "--scale", help="Multiplies every stored value (e.g. 0.0002 for 16-bit PNG "
                                "depth at 5000 per metre)."),
    ext: str | None = typer.Option(None, "--ext", help="Read only this format when the folder holds several "
                                      "(MiDaS writes .pfm and .png: --ext pfm)."),
    key: str | None = typer.Option(None, "--key", help="The array inside .npz files that hold several."),
    out: Path | None = ResultsOutOpt,
    force: bool = typer.Option(False, "--force", help="Rescore a complete result."),
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
    data_root: str | None = DataRootOpt,
    registry: Path | None = RegistryOpt,
) -> None:
    """Score another network's depth predictions exactly as `run` scores ours → results/<seq>/<NAME>/seed0/."""
    from mutualslam_cli.eval_depth import eval_depth as score_external

    cfg = config_from(config, sets, data_root)
    check_output_folder(out if out is not None else cfg.out)  # a file, read-only: one line, before the bar
    with progress_bar() as p:
        task = p.add_task(f"score {name}", total=None, info="")
        r = score_external(seq, predictions, name, kind, cfg, scale=scale, out=out, ext=ext, npz_key=key,
                           command=sys.argv, force=force, registry=registry,
                           progress=lambda done, total: p.update(task, completed=done, total=total))
    if r.skipped:
        common.console.print(f"[yellow]already complete[/] (use --force to rescore): {r.folder}")
    f = r.summary
    t = Table("PCD lsq (%)", "PCD median (%)", "PCD none (%)", "e_si", "frames",
              title=escape(f"{f.get('sequence.name')} · {name} ({f.get('external.kind')}, external, no adaptation)"))
    t.add_row(*(fmt_value(f.get(f"depth.{k}.adapted"), 2) for k in ("pcd.lsq", "pcd.median", "pcd.none")),
              fmt_value(f.get("depth.esi.adapted"), 3), fmt_value(f.get("depth.frames_evaluated")))
    common.console.print(t)
    common.console.print(f"results: {escape(str(r.folder))}")


# --------------------------------------------------------------------------- ate


@app.command()
def ate(
    ref: Path = typer.Argument(..., help="Reference TUM trajectory (timestamp tx ty tz qx qy qz qw)."),
    est: Path = typer.Argument(..., help="Estimated TUM trajectory."),
    align: str = typer.Option("sim3", "--align", help="sim3 | se3 | none"),
    max_dt: float | None = typer.Option(None, "--max-dt",
                                           help="Association threshold, s (default eval.ate_max_dt)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object (units in the keys) instead of a table."),
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
) -> None:
    """ATE of two TUM-format trajectories (the pipeline's own code path)."""
    import json

    from mutualslam_cli.datasets.associate import read_tum_trajectory
    from mutualslam_cli.metrics.trajectory import ate as ate_fn

    max_dt = config_from(config, sets).eval.ate_max_dt if max_dt is None else max_dt
    if align not in ("sim3", "se3", "none"):
        raise ConfigError(f"--align {align!r}: expected sim3, se3 or none")
    r = ate_fn(read_tum_trajectory(ref), read_tum_trajectory(est), align=align, max_dt=max_dt)  # type: ignore[arg-type]
    if as_json:
        stats = {f"ate_{k}_m": getattr(r, k) for k in ("rmse", "mean", "median", "max")}
        out = {"ref": str(ref), "est": str(est), "align": align, "max_dt_s": max_dt, "pairs": r.n_pairs,
               "scale": r.scale, **stats}
        typer.echo(json.dumps({k: v if not isinstance(v, float) or v == v else None for k, v in out.items()}))
        return
    t = Table("pairs", "align", "scale", "rmse m", "mean m", "median m", "max m",
              title=escape(f"ATE {est.name} vs {ref.name}"))
    t.add_row(str(r.n_pairs), align, f"{r.scale:.6f}", f"{r.rmse:.6f}", f"{r.mean:.6f}", f"{r.median:.6f}",
              f"{r.max:.6f}")
    common.console.print(t)
