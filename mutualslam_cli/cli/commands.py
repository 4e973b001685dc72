"""The ``mslam`` command line (typer + rich). Thin: parse, call the library, render.

One error boundary (:mod:`~mutualslam_cli.cli.common`): an :class:`~mutualslam_cli.errors.MslamError`
becomes one red line and exit code 1; anything else is a bug and keeps its traceback (including the
project's programming errors :class:`~mutualslam_cli.errors.ShapeError` and
:class:`~mutualslam_cli.errors.TransitionError`, which are deliberately not ``MslamError``).
Commands: ``datasets``, ``synth``, ``ate``, ``pretrain``, ``run``, ``fuse``, ``eval-depth`` here; ``ablate`` and
``report`` in :mod:`~mutualslam_cli.cli.grid`.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from mutualslam_cli.cli import common
from mutualslam_cli.cli.common import (
    ConfigOpt,
    DataRootOpt,
    RegistryOpt,
    ResultsOutOpt,
    SetOpt,
    _boundary,
    _config,
    _fmt,
    _progress,
    app,
)
from mutualslam_cli.config import with_overrides
from mutualslam_cli.errors import ConfigError, MslamError

# --------------------------------------------------------------------------- datasets


@app.command()
@_boundary
def datasets(
    name: Optional[str] = typer.Argument(None, help="A datasets.yaml name or a sequence folder (with --check)."),
    check: bool = typer.Option(False, "--check", help="Verify files, intrinsics, GT coverage, fy sign, and decode "
                               "every RGB and depth image (truncated, corrupt or odd-sized files fail)."),
    sample: int = typer.Option(0, "--sample", min=0, help="With --check: decode only the images of N frames "
                               "spread over each sequence (a quick check); 0 = every frame."),
    registry: Optional[Path] = RegistryOpt,
    data_root: Optional[str] = DataRootOpt,
    config: Optional[Path] = ConfigOpt,
    sets: Optional[list[str]] = SetOpt,
) -> None:
    """List datasets.yaml entries, or check one sequence (or all) with --check.

    --check decodes every image, so a bad file fails now (exit code 1, naming it) rather than in
    the middle of a long run; --sample N makes it quick."""
    from mutualslam_cli.datasets.check import check_sequence
    from mutualslam_cli.datasets.registry import list_datasets

    cfg = _config(config, sets, data_root)
    specs = list_datasets(registry, data_root=cfg.data.data_root)
    if not check:
        t = Table("name", "format", "found", "fx fy cx cy", "depth/m", title="datasets.yaml")
        for s in specs:
            intr = " ".join(f"{v:g}" for v in s.intrinsics.as_list()) if s.intrinsics else "family/data"
            t.add_row(s.name, s.format, "yes" if Path(s.root).is_dir() else "[dim]no[/]", intr, f"{s.depth_scale:g}")
        common.console.print(t)
        common.console.print("roots: relative to --data-root / $MSLAM_DATA (see datasets.yaml); "
                             "`--check NAME` verifies one")
        return
    targets = [name] if name else [s.name for s in specs if Path(s.root).is_dir()]
    if not targets:
        raise MslamError("no dataset folder exists under the data root; set MSLAM_DATA or --data-root")
    for n in targets:
        with _progress() as p:
            task = p.add_task(f"decode {Path(n).name}", total=None, info="")

            def cb(stage: str, info: dict[str, Any], task: Any = task) -> None:
                p.update(task, completed=info["done"], total=info["total"], info=Path(info["file"]).name)

            try:
                r = check_sequence(n, sample=sample, data_root=cfg.data.data_root, registry_path=registry, progress=cb)
            finally:
                p.remove_task(task)  # the table replaces the bar; an error is one line, not a bar and a line
        t = Table("check", "value", title=f"{r.name} ({r.format})", title_justify="left")
        intr = " ".join(f"{v:g}" for v in r.intrinsics[:4])
        rows = [
            ("root", r.root), ("frames", str(r.frames)), ("time span", f"{r.time_span_s:.2f}"),
            ("frames with depth", str(r.frames_with_depth)),
            ("GT coverage", f"{r.frames_with_gt} frames ({r.gt_coverage_pct:.1f} %)"),
            ("intrinsics fx fy cx cy", intr + (" + distortion" if len(r.intrinsics) > 4 else "")),
            ("image size", "×".join(map(str, r.image_size))), ("depth scale", f"{r.depth_scale:g} = 1 m"),
            ("median depth", _fmt(r.median_depth_m, 2) + " m"),
            ("images decoded", f"{r.images_decoded} ("
             + ("every frame)" if r.frames_decoded == r.frames else f"{r.frames_decoded} of {r.frames} frames)")),
        ]
        if r.fy_sign is not None:
            errs = ", ".join(f"{k}: {v:.3g}" for k, v in (r.fy_sign_errors or {}).items())
            rows.append(("fy sign", f"{r.fy_sign:+d}" + (f" (photometric error {errs})" if errs else "")))
        rows.append(("warnings", "; ".join(r.warnings) or "none"))
        for k, v in rows:
            t.add_row(k, v)
        common.console.print(t)


# --------------------------------------------------------------------------- synth


@app.command()
@_boundary
def synth(
    out: Path = typer.Argument(..., help="Output folder (TUM layout)."),
    scene: str = typer.Option("room", "--scene", help="room | planar | far"),
    frames: int = typer.Option(120, "--frames", "-n", min=2),
    size: str = typer.Option("640x480", "--size", help="WIDTHxHEIGHT"),
    seed: Optional[int] = typer.Option(None, "--seed", help="Default: the config's seed."),
    domain: str = typer.Option("target", "--domain", help="target | source (pre-training domain)"),
    config: Optional[Path] = ConfigOpt,
    sets: Optional[list[str]] = SetOpt,
) -> None:
    """Render a synthetic RGB-D sequence with exact depth and poses, in TUM layout."""
    from mutualslam_cli.datasets import synthetic

    seed = _config(config, sets).seed if seed is None else seed
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size {size!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
    if scene not in synthetic.SCENES:
        raise ConfigError(f"--scene {scene!r}: unknown scene; valid scenes: {', '.join(synthetic.SCENES)}")
    if domain not in ("target", "source"):
        raise ConfigError(f"--domain {domain!r}: expected target or source")
    with _progress() as p:
        task = p.add_task(f"render {scene}", total=frames, info="")
        it = synthetic.iter_render(scene, frames, w, h, seed, domain)

        def tracked():
            for item in it:
                yield item
                p.advance(task)

        path = synthetic.write_tum(tracked(), out, scene=scene, width=w, height=h, seed=seed, domain=domain)
    common.console.print(f"wrote {frames} frames ({w}×{h}, scene {scene}, seed {seed}) to {path}")


# --------------------------------------------------------------------------- ate


@app.command()
@_boundary
def ate(
    ref: Path = typer.Argument(..., help="Reference TUM trajectory (timestamp tx ty tz qx qy qz qw)."),
    est: Path = typer.Argument(..., help="Estimated TUM trajectory."),
    align: str = typer.Option("sim3", "--align", help="sim3 | se3 | none"),
    max_dt: Optional[float] = typer.Option(None, "--max-dt",
                                           help="Association threshold, s (default eval.ate_max_dt)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object (units in the keys) instead of a table."),
    config: Optional[Path] = ConfigOpt,
    sets: Optional[list[str]] = SetOpt,
) -> None:
    """ATE of two TUM-format trajectories (the pipeline's own code path)."""
    import json

    from mutualslam_cli.datasets.associate import read_tum_trajectory
    from mutualslam_cli.metrics.trajectory import ate as ate_fn

    max_dt = _config(config, sets).eval.ate_max_dt if max_dt is None else max_dt
    if align not in ("sim3", "se3", "none"):
        raise ConfigError(f"--align {align!r}: expected sim3, se3 or none")
    r = ate_fn(read_tum_trajectory(ref), read_tum_trajectory(est), align=align, max_dt=max_dt)  # type: ignore[arg-type]
    if as_json:
        stats = {f"ate_{k}_m": getattr(r, k) for k in ("rmse", "mean", "median", "max")}
        out = {"ref": str(ref), "est": str(est), "align": align, "max_dt_s": max_dt, "pairs": r.n_pairs,
               "scale": r.scale, **stats}
        typer.echo(json.dumps({k: v if not isinstance(v, float) or v == v else None for k, v in out.items()}))
        return
    t = Table("pairs", "align", "scale", "rmse m", "mean m", "median m", "max m", title=f"ATE {est.name} vs {ref.name}")
    t.add_row(str(r.n_pairs), align, f"{r.scale:.6f}", f"{r.rmse:.6f}", f"{r.mean:.6f}", f"{r.median:.6f}",
              f"{r.max:.6f}")
    common.console.print(t)


# --------------------------------------------------------------------------- pretrain


@app.command()
@_boundary
def pretrain(
    out: Optional[Path] = typer.Option(None, "--out",
                                       help="Folder for encoder.pth/depth.pth (default: the default model)."),
    steps: int = typer.Option(1150, "--steps", min=1, help="Training steps (the shipped model: 1150)."),
    batch_size: int = typer.Option(4, "--batch-size", min=1),
    seed: Optional[int] = typer.Option(None, "--seed", help="Default: the config's seed."),
    threads: int = typer.Option(1, "--threads", min=1, help="torch threads (results depend on it slightly)."),
    max_minutes: Optional[float] = typer.Option(None, "--max-minutes", help="Stop early and save after this long."),
    quick: bool = typer.Option(False, "--quick", help="A few steps at small size (smoke test)."),
    pose: bool = typer.Option(False, "--pose", help="Train scheme comoda's pose network instead "
                              "(pose_encoder.pth/pose.pth, from the depth encoder in --out or the default)."),
    config: Optional[Path] = ConfigOpt,
    sets: Optional[list[str]] = SetOpt,
) -> None:
    """Train the default depth network on the synthetic source domain (stand-in for KITTI pre-training)."""
    from mutualslam_cli.adapt import pretrain as pt
    from mutualslam_cli.adapt.weights import default_weights_dir

    cfg = _config(config, sets)
    seed = cfg.seed if seed is None else seed
    out = out or default_weights_dir()
    if pose:
        _pretrain_pose(cfg, out, steps, batch_size, seed, threads, max_minutes, quick)
        return
    kwargs: dict[str, Any] = {"width": cfg.net.width, "height": cfg.net.height, "steps": steps,
                              "batch_size": batch_size, "seed": seed, "threads": threads,
                              "max_minutes": max_minutes, "drop_fc": True, "pool_size": 240, "eval_frames": 6}
    if quick:
        kwargs.update(pt.QUICK)
    with _progress() as p:
        task = p.add_task("pretrain", total=kwargs["steps"], info="")

        def cb(info: dict) -> None:
            p.update(task, completed=info.get("step", 0), info=f"loss {info.get('loss', float('nan')):.4f}")

        summary = pt.pretrain(out, progress=cb, **kwargs)
    common.console.print(f"saved the pre-trained model to {out} ({summary.get('time_s', 0):.0f} s, "
                  f"{summary.get('steps_done', summary.get('steps'))} steps)")


def _pretrain_pose(cfg: Any, out: Path, steps: int, batch_size: int, seed: int, threads: int,
                   max_minutes: Optional[float], quick: bool) -> None:
    """``mslam pretrain --pose``: the pose network, initialised from the depth encoder found in ``out``."""
    from mutualslam_cli.adapt.pretrain_pose import pretrain_pose
    from mutualslam_cli.adapt.weights import default_weights_dir, load_monodepth2

    init = load_monodepth2(out if (out / "encoder.pth").is_file() else default_weights_dir())
    w, h, steps = (64, 32, min(steps, 3)) if quick else (cfg.net.width, cfg.net.height, steps)
    with _progress() as p:
        task = p.add_task("pretrain pose", total=steps, info="")

        def cb(info: dict) -> None:
            p.update(task, completed=info["step"], info=f"loss {info['loss']:.4f}")

        rec = pretrain_pose(out, steps, w, h, batch_size, seed=seed, init=init, max_minutes=max_minutes,
                            threads=threads, half=True, progress=cb)
    common.console.print(f"saved the pose network to {out} ({rec['time_s']:.0f} s, {rec['steps_done']} steps, "
                         f"final loss {rec['loss_curve'][-1]['loss']:.4f})")


# --------------------------------------------------------------------------- run


def _render_summary(folder: Path, s: dict[str, Any]) -> None:
    from mutualslam_cli.results.summary import flatten

    f = flatten(s)
    t = Table("metric", "pre-trained", "adapted",
              title=f"{f.get('sequence.name')} · {f.get('scheme')} · seed {f.get('seed')}")
    rows = [("PCD lsq (%)", "depth.pcd.lsq"), ("PCD median (%)", "depth.pcd.median"), ("e_si", "depth.esi")]
    if f.get("dense.time_s") is not None:  # the dense stage ran
        rows += [("dense accuracy m", "dense.accuracy_m"), ("dense completeness m", "dense.completeness_m"),
                 ("dense F-score @5cm", "dense.fscore_5cm")]
    for label, key in rows:
        t.add_row(label, _fmt(f.get(f"{key}.pretrained"), 3 if key.startswith("dense") else 2),
                  _fmt(f.get(f"{key}.adapted"), 3 if key.startswith("dense") else 2))
    common.console.print(t)
    t2 = Table("ATE kf m", "ATE all m", "tracked", "keyframes", "map points", "map e_si", "depth ms", "ms/step")
    t2.add_row(_fmt(f.get("trajectory.ate_rmse_m.vo"), 4), _fmt(f.get("trajectory.ate_rmse_m.all_frames"), 4),
               _fmt(f.get("vo.tracked_fraction"), 3), _fmt(f.get("vo.keyframes")), _fmt(f.get("map.points.vo")),
               _fmt(f.get("map.esi.vo"), 3), _fmt(f.get("timing.depth_ms"), 1), _fmt(f.get("timing.finetune_ms"), 0))
    common.console.print(t2)
    common.console.print(f"results: {folder}")


@app.command()
@_boundary
def run(
    seq: str = typer.Argument(..., help="datasets.yaml name or sequence folder."),
    scheme: Optional[str] = typer.Option(None, "--scheme", help="Adaptation scheme (default from config: replay+ewc)."),
    vo: Optional[str] = typer.Option(
        None, "--vo", help="svo | gt (pose oracle: our VO's tracks with GT poses) | "
                           "gt-depth (GT poses and GT sparse depth: an upper bound)."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="Folder with Monodepth2 encoder.pth/depth.pth."),
    seed: Optional[int] = typer.Option(None, "--seed"),
    out: Optional[Path] = ResultsOutOpt,
    force: bool = typer.Option(False, "--force", help="Recompute a complete run."),
    config: Optional[Path] = ConfigOpt,
    sets: Optional[list[str]] = SetOpt,
    data_root: Optional[str] = DataRootOpt,
    registry: Optional[Path] = RegistryOpt,
) -> None:
    """One sequence, one scheme: front end → adaptation → evaluation → results/<seq>/<scheme>/seed<k>/."""
    from mutualslam_cli.adapt.schemes import get_scheme
    from mutualslam_cli.pipeline import run_sequence

    cfg = _config(config, sets, data_root)
    over = {"adapt": {"scheme": scheme} if scheme else None, "vo": {"mode": vo} if vo else None,
            "net": {"weights": str(weights)} if weights else None, "seed": seed}
    cfg = with_overrides(cfg, **{k: v for k, v in over.items() if v is not None})  # type: ignore[arg-type]
    get_scheme(cfg.adapt.scheme, cfg.adapt)  # unknown name or bad setting → ConfigError, before any work
    with _progress() as p:
        tasks: dict[str, Any] = {}

        def cb(stage: str, info: dict[str, Any]) -> None:
            total = info.get("total", info.get("n_frames"))
            if stage not in tasks:
                tasks[stage] = p.add_task({"vo": "front end", "adapt": "adapt", "eval": "evaluate",
                                           "dense": "dense"}.get(stage, stage),
                                          total=total, info="")
            done = info.get("done", (info.get("frame", -1) + 1))
            if stage == "vo":
                text = f"kf {info.get('keyframes', 0)} · pts {info.get('tracked', 0)} · {info.get('state', '')}"
                if info.get("fps"):
                    text += f" · {info['fps']:.0f} fps"
            elif stage == "adapt":
                lv = info.get("l_val")
                lv = None if lv is None or lv != lv else lv
                what = "validate" if info.get("is_validation") else ("fine-tune" if info.get("trained") else "wait")
                text = (f"{what} · loss {_fmt(info.get('loss_total'), 4)} · L_val {_fmt(lv, 4)}"
                        f" · converged {info.get('n_converged', 0)}")
            else:
                text = info.get("phase", "")
            p.update(tasks[stage], completed=done, total=total, info=text)

        r = run_sequence(seq, cfg, out=out, command=sys.argv, force=force, progress=cb, registry=registry)
    if r.skipped:
        common.console.print(f"[yellow]already complete[/] (use --force to recompute): {r.folder}")
    _render_summary(r.folder, r.summary)


# --------------------------------------------------------------------------- fuse


@app.command()
@_boundary
def fuse(
    run_dir: Path = typer.Argument(..., help="A finished run folder (<out>/<seq>/<scheme>/seed<k>) with weights/."),
    sets: Optional[list[str]] = SetOpt,
    registry: Optional[Path] = RegistryOpt,
) -> None:
    """Dense reconstruction of a finished run: TSDF meshes of both models' depth, scored against GT depth
    fused with GT poses (needs the run's adapted weights: --set eval.save_weights=true)."""
    from mutualslam_cli.results.summary import flatten
    from mutualslam_cli.pipeline import fuse_run

    with _progress() as p:
        tasks: list[Any] = []  # the bar appears with the first step: an error before it is one line

        def cb(stage: str, info: dict[str, Any]) -> None:
            if stage == "dense":  # a front end recomputed (no VO cache) reports as "vo": not this bar
                tasks[:] = tasks or [p.add_task("dense", total=info["total"], info="")]
                p.update(tasks[0], completed=info["done"], total=info["total"], info=info.get("phase", ""))

        s = fuse_run(run_dir, sets or [], registry, command=sys.argv, progress=cb)
    f = flatten(s)
    t = Table("metric", "pre-trained", "adapted", title=f"{f.get('sequence.name')} · dense ({f.get('dense.source')})")
    for label, key in (("accuracy m", "accuracy_m"), ("completeness m", "completeness_m"),
                       ("F-score @5cm", "fscore_5cm")):
        t.add_row(label, _fmt(f.get(f"dense.{key}.pretrained"), 4), _fmt(f.get(f"dense.{key}.adapted"), 4))
    common.console.print(t)
    common.console.print(f"meshes and dense.png in {run_dir} ({_fmt(f.get('dense.time_s'), 1)} s)")


# --------------------------------------------------------------------------- eval-depth


@app.command("eval-depth")
@_boundary
def eval_depth(
    seq: str = typer.Argument(..., help="datasets.yaml name or sequence folder."),
    predictions: Path = typer.Argument(..., help="Folder with one prediction per frame (.npy, .npz, 16-bit .png, "
                                       ".pfm), named by the RGB file's stem or by the frame's timestamp."),
    name: str = typer.Option(..., "--name", help="The model's name: its row in the report (not a scheme's name)."),
    kind: str = typer.Option("depth", "--kind", help="depth | inverse | relative-inverse (MiDaS: aligned per "
                             "frame by least-squares scale and shift in inverse depth)."),
    scale: float = typer.Option(1.0, "--scale", help="Multiplies every stored value (e.g. 0.0002 for 16-bit PNG "
                                "depth at 5000 per metre)."),
    ext: Optional[str] = typer.Option(None, "--ext", help="Read only this format when the folder holds several "
                                      "(MiDaS writes .pfm and .png: --ext pfm)."),
    key: Optional[str] = typer.Option(None, "--key", help="The array inside .npz files that hold several."),
    out: Optional[Path] = ResultsOutOpt,
    force: bool = typer.Option(False, "--force", help="Rescore a complete result."),
    config: Optional[Path] = ConfigOpt,
    sets: Optional[list[str]] = SetOpt,
    data_root: Optional[str] = DataRootOpt,
    registry: Optional[Path] = RegistryOpt,
) -> None:
    """Score another network's depth predictions exactly as `run` scores ours → results/<seq>/<NAME>/seed0/."""
    from mutualslam_cli.results.summary import flatten
    from mutualslam_cli.stages.external import eval_depth as score_external

    cfg = _config(config, sets, data_root)
    with _progress() as p:
        task = p.add_task(f"score {name}", total=None, info="")
        r = score_external(seq, predictions, name, kind, cfg, scale=scale, out=out, ext=ext, npz_key=key,
                           command=sys.argv, force=force, registry=registry,
                           progress=lambda done, total: p.update(task, completed=done, total=total))
    if r.skipped:
        common.console.print(f"[yellow]already complete[/] (use --force to rescore): {r.folder}")
    f = flatten(r.summary)
    t = Table("PCD lsq (%)", "PCD median (%)", "PCD none (%)", "e_si", "frames",
              title=f"{f.get('sequence.name')} · {name} ({f.get('external.kind')}, external, no adaptation)")
    t.add_row(*(_fmt(f.get(f"depth.{k}.adapted"), 2) for k in ("pcd.lsq", "pcd.median", "pcd.none")),
              _fmt(f.get("depth.esi.adapted"), 3), _fmt(f.get("depth.frames_evaluated")))
    common.console.print(t)
    common.console.print(f"results: {r.folder}")
