"""``mslam datasets``, ``synth`` and ``pretrain``: the sequences, synthetic ones, and the default network."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import typer
from rich.table import Table

from mutualslam_cli.cli import common
from mutualslam_cli.cli.common import (
    ConfigOpt,
    DataRootOpt,
    RegistryOpt,
    SetOpt,
    app,
    config_from,
    fmt_value,
    progress_bar,
    progress_figure,
    shown,
)
from mutualslam_cli.errors import ConfigError, DatasetError, MslamError

if TYPE_CHECKING:
    import numpy as np
    from rich.progress import TaskID

    from mutualslam_cli.config import RunConfig
    from mutualslam_cli.datasets.check import CheckReport
    from mutualslam_cli.datasets.download.limits import UnpackLimits
    from mutualslam_cli.types import Info, SequenceSpec

# --------------------------------------------------------------------------- datasets

datasets_app = typer.Typer(cls=common.Commands, invoke_without_command=True, no_args_is_help=False)
app.add_typer(datasets_app, name="datasets")

SampleOpt = typer.Option(0, "--sample", min=0, help="Decode only the images of N frames spread over each sequence "
                         "(a quick check); 0 = every frame.")


@dataclass(frozen=True)
class _Shared:
    """The options every ``mslam datasets`` sub-command takes, given before the sub-command
    (``mslam datasets --registry R check``) or after it (``mslam datasets check --registry R``): after wins."""

    registry: Path | None = None
    data_root: str | None = None
    config: Path | None = None
    sets: tuple[str, ...] = ()

    def over(self, registry: Path | None, data_root: str | None, config: Path | None,
             sets: list[str] | None) -> _Shared:
        """These options with a sub-command's own on top (``--set`` adds to the list)."""
        return _Shared(registry or self.registry, data_root or self.data_root, config or self.config,
                       self.sets + tuple(sets or ()))

    def data_root_of(self) -> str | None:
        """The data root of the run config (``--config``, ``--set``, ``--data-root``)."""
        return config_from(self.config, list(self.sets), self.data_root).data.data_root


def _shared(ctx: typer.Context, registry: Path | None, data_root: str | None, config: Path | None,
            sets: list[str] | None) -> _Shared:
    """The shared options of ``ctx``'s sub-command, over those given to ``mslam datasets`` itself."""
    given = ctx.obj if isinstance(ctx.obj, _Shared) else _Shared()  # a sub-context inherits its parent's obj
    return given.over(registry, data_root, config, sets)


@datasets_app.callback()
def datasets(
    ctx: typer.Context,
    registry: Path | None = RegistryOpt,
    data_root: str | None = DataRootOpt,
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
) -> None:
    """The sequences of datasets.yaml: list them, check them, download the public ones.

    `mslam datasets` alone lists them, as `mslam datasets list` does. Options given here, before the
    sub-command, apply to it; the sub-command's own options win."""
    ctx.obj = _Shared(registry, data_root, config, tuple(sets or ()))
    if ctx.invoked_subcommand is None:
        _list(ctx.obj)


@datasets_app.command("list")
def list_(
    ctx: typer.Context,
    registry: Path | None = RegistryOpt,
    data_root: str | None = DataRootOpt,
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
) -> None:
    """List the entries of datasets.yaml: format, whether the folder exists, intrinsics and depth scale."""
    _list(_shared(ctx, registry, data_root, config, sets))


def _list(opts: _Shared) -> None:
    """The table of the registry's entries."""
    from mutualslam_cli.datasets.registry import list_datasets

    specs = list_datasets(opts.registry, data_root=opts.data_root_of())
    t = Table("name", "format", "found", "fx fy cx cy", "depth/m", title="datasets.yaml")
    for s in specs:
        intr = " ".join(f"{v:g}" for v in s.intrinsics.as_list()) if s.intrinsics else "family/data"
        t.add_row(s.name, s.format, "yes" if Path(s.root).is_dir() else "[dim]no[/]", intr, f"{s.depth_scale:g}")
    common.console.print(t)
    common.console.print("roots: relative to --data-root / $MSLAM_DATA (see datasets.yaml); "
                         "`mslam datasets check NAME` verifies one, `mslam datasets download NAME…` fetches one")


@datasets_app.command()
def check(
    ctx: typer.Context,
    name: list[str] | None = typer.Argument(None, help="datasets.yaml names or sequence folders (default: every "
                                               "entry whose folder exists)."),
    sample: int = SampleOpt,
    registry: Path | None = RegistryOpt,
    data_root: str | None = DataRootOpt,
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
) -> None:
    """Verify sequences: files, intrinsics, GT coverage, fy sign, and every RGB and depth image decoded.

    A truncated, corrupt or odd-sized image fails now (exit code 1, naming it) rather than in the middle of a
    long run; --sample N makes the check quick."""
    from mutualslam_cli.datasets.registry import list_datasets

    opts = _shared(ctx, registry, data_root, config, sets)
    root = opts.data_root_of()
    targets = list(name or []) or [s.name for s in list_datasets(opts.registry, data_root=root)
                                   if Path(s.root).is_dir()]
    if not targets:
        raise MslamError("no dataset folder exists under the data root; set MSLAM_DATA or --data-root")
    for n in targets:
        _check_and_print(n, sample, root, opts.registry)


@datasets_app.command()
def download(
    ctx: typer.Context,
    name: list[str] | None = typer.Argument(None, help="datasets.yaml names of entries with a `download:` block "
                                               "(none: the error lists them)."),
    base_url: str | None = typer.Option(None, "--base-url", help="A mirror; each URL becomes "
                                           "BASE_URL/<file name> (default $MSLAM_DOWNLOAD_BASE_URL)."),
    force: bool = typer.Option(False, "--force", help="Unpack again and replace a sequence folder that mslam "
                               "unpacked, once the new one passes the check (downloaded archives are reused; the "
                               "old folder stays if anything fails; a folder mslam did not unpack is never "
                               "replaced)."),
    max_unpack_gb: float | None = typer.Option(None, "--max-unpack-gb", min=0, help="Most GB an archive may "
                                                  "unpack to (default 10× its size; never more than the free "
                                                  "disk)."),
    sample: int = SampleOpt,
    registry: Path | None = RegistryOpt,
    data_root: str | None = DataRootOpt,
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
) -> None:
    """Fetch, verify and unpack the public archives of datasets.yaml entries, then check each sequence.

    Archives go to <data root>/_downloads (a cut download resumes), their size and checksum are verified,
    and each is unpacked into its entry's folder within limits and checked as `mslam datasets check` does."""
    opts = _shared(ctx, registry, data_root, config, sets)
    _download(list(name or []), sample, base_url, force, opts.registry, opts.data_root_of(), max_unpack_gb)


@datasets_app.command()
def splice(
    src: Path = typer.Argument(..., help="A TUM-layout folder (rgb.txt; depth.txt and groundtruth.txt if any)."),
    out: Path = typer.Argument(..., help="The new folder (an earlier splice there is replaced)."),
    keep: list[str] = typer.Option(..., "--keep", metavar="A:B", help="The colour frames A to B-1 (0-based, rgb.txt "
                                   "order); repeat for more ranges, written in the order given."),
    rate: float = typer.Option(30.0, "--rate", help="Frame rate of the new timestamps (Hz)."),
) -> None:
    """Cut and splice a sequence: the frames of each --keep range, one after the other, re-stamped at --rate.

    A join where the camera jumps is a gap tracking cannot bridge (a cut, or a kidnap): real images for
    relocalisation and map merging. Images are linked, not copied; depth and GT go with their frames;
    splice.json names each frame's source frame."""
    from mutualslam_cli.datasets.splice import splice_sequence

    ranges = []
    for text in keep:
        a, _, b = text.partition(":")
        try:
            ranges.append((int(a), int(b)))
        except ValueError:
            raise DatasetError(f"--keep {text!r}: expected A:B, two frame indices (e.g. 0:450)") from None
    info = splice_sequence(src, out, ranges, rate)
    common.console.print(shown(f"wrote {len(info.sources)} frames ({info.depth} with depth, {info.gt} with GT, "
                               f"joins at {info.joins or 'none'}) to {info.out}"), highlight=False)


def _check_and_print(target: SequenceSpec | str, sample: int, data_root: str | None, registry: Path | None) -> None:
    """``check_sequence`` of ``target`` (a name, folder or spec) with a decode bar, then its table."""
    from mutualslam_cli.datasets.check import check_sequence

    label = getattr(target, "name", None) or Path(str(target)).name
    with _decode_bar(label) as cb:
        r = check_sequence(target, sample=sample, data_root=data_root, registry_path=registry, progress=cb)
    _print_report(r)


@contextmanager
def _decode_bar(label: str) -> Iterator[Callable[[str, Info], None]]:
    """A progress bar for the images a sequence check decodes; yields its callback, removed at the end (the
    table replaces the bar; an error is one line, not a bar and a line)."""
    with progress_bar() as p:
        tasks: list[TaskID] = []  # added at the first image

        def cb(stage: str, info: Info) -> None:
            if not tasks:
                tasks.append(p.add_task(shown(f"decode {label}"), total=None, info=""))
            p.update(tasks[0], completed=progress_figure(info.get("done")), total=progress_figure(info.get("total")),
                     info=shown(Path(str(info["file"])).name))

        try:
            yield cb
        finally:
            for task in tasks:
                p.remove_task(task)


def _print_report(r: CheckReport) -> None:
    """The table of a :class:`~mutualslam_cli.datasets.check.CheckReport`."""
    t = Table("check", "value", title=shown(f"{r.name} ({r.format})"), title_justify="left")
    intr = " ".join(f"{v:g}" for v in r.intrinsics[:4])
    rows = [
        ("root", r.root), ("frames", str(r.frames)), ("time span", f"{r.time_span_s:.2f}"),
        ("frames with depth", str(r.frames_with_depth)),
        ("GT coverage", f"{r.frames_with_gt} frames ({r.gt_coverage_pct:.1f} %)"),
        ("intrinsics fx fy cx cy", intr + (" + distortion" if len(r.intrinsics) > 4 else "")),
        ("image size", "×".join(map(str, r.image_size))), ("depth scale", f"{r.depth_scale:g} = 1 m"),
        ("median depth", fmt_value(r.median_depth_m, 2) + " m"),
        ("images decoded", f"{r.images_decoded} ("
         + ("every frame)" if r.frames_decoded == r.frames else f"{r.frames_decoded} of {r.frames} frames)")),
    ]
    if r.fy_sign is not None:
        errs = ", ".join(f"{k}: {v:.3g}" for k, v in (r.fy_sign_errors or {}).items())
        rows.append(("fy sign", f"{r.fy_sign:+d}" + (f" (photometric error {errs})" if errs else "")))
    rows.append(("warnings", "; ".join(r.warnings) or "none"))
    for k, v in rows:
        t.add_row(k, shown(v))  # paths and warnings may quote names from a downloaded archive
    common.console.print(t)


def _download(names: list[str], sample: int, base_url: str | None, force: bool, registry: Path | None,
              data_root: str | None, max_unpack_gb: float | None) -> None:
    """``mslam datasets download NAME…``: each sequence fetched, verified, unpacked, then checked."""
    from mutualslam_cli.datasets.download.entry import DOWNLOAD_DIR, data_root_of, downloadable_specs
    from mutualslam_cli.datasets.download.limits import UnpackLimits

    specs = downloadable_specs(names, registry, data_root)
    folder = data_root_of(registry, data_root) / DOWNLOAD_DIR
    limits = UnpackLimits(max_bytes=None if max_unpack_gb is None else int(max_unpack_gb * 1e9))
    for spec in specs:
        report = _download_one(spec, folder, base_url, force, limits, sample)
        if report is None:  # skipped: the folder there is checked as it is
            _check_and_print(spec, sample, data_root, registry)
        else:  # checked before it took the folder's place
            _print_report(report)


def _download_one(spec: SequenceSpec, folder: Path, base_url: str | None, force: bool, limits: UnpackLimits,
                  sample: int) -> CheckReport | None:
    """One entry's download, unpacking and check, with a bar (size, speed) per file; the bars go when it is done.
    Returns the check's report (``None``: skipped)."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn, TransferSpeedColumn

    from mutualslam_cli.datasets.download.entry import download_sequence

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
                  TimeRemainingColumn(), console=common.console, transient=True) as p:
        tasks: dict[tuple[str, str], TaskID] = {}

        def cb(stage: str, info: Info) -> None:
            key = (stage, str(info["file"]))
            if key not in tasks:
                tasks[key] = p.add_task(shown(f"{stage} {info['file']}"), total=progress_figure(info.get("total")))
            p.update(tasks[key], completed=progress_figure(info.get("done")), total=progress_figure(info.get("total")))

        def say(msg: str) -> None:
            p.console.print(shown(msg), highlight=False, soft_wrap=True)

        def check_cb(stage: str, info: Info) -> None:  # the staged folder's check, in the same display
            cb("check", {"done": info["done"], "total": info["total"], "file": f"{spec.name} (images)"})

        return download_sequence(spec, folder, base_url=base_url, force=force, progress=cb, on_message=say,
                                 limits=limits, sample=sample, check_progress=check_cb).report


# --------------------------------------------------------------------------- synth


@app.command()
def synth(
    out: Path = typer.Argument(..., help="Output folder (TUM layout)."),
    scene: str = typer.Option("room", "--scene", help="room | planar | far"),
    frames: int = typer.Option(120, "--frames", "-n", min=2),
    size: str = typer.Option("640x480", "--size", help="WIDTHxHEIGHT"),
    seed: int | None = typer.Option(None, "--seed", help="Default: the config's seed."),
    domain: str = typer.Option("target", "--domain", help="target | source (pre-training domain)"),
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
) -> None:
    """Render a synthetic RGB-D sequence with exact depth and poses, in TUM layout."""
    from mutualslam_cli.datasets import synthetic

    seed = config_from(config, sets).seed if seed is None else seed
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size {size!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
    if scene not in synthetic.SCENES:
        raise ConfigError(f"--scene {scene!r}: unknown scene; valid scenes: {', '.join(synthetic.SCENES)}")
    if domain not in ("target", "source"):
        raise ConfigError(f"--domain {domain!r}: expected target or source")
    with progress_bar() as p:
        task = p.add_task(f"render {scene}", total=frames, info="")
        it = synthetic.iter_render(scene, frames, w, h, seed, cast(Literal["target", "source"], domain))  # checked

        def tracked() -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
            for item in it:
                yield item
                p.advance(task)

        path = synthetic.write_tum(tracked(), out, scene=scene, width=w, height=h, seed=seed, domain=domain)
    common.console.print(f"wrote {frames} frames ({w}×{h}, scene {scene}, seed {seed}) to {path}")


# --------------------------------------------------------------------------- pretrain


@app.command()
def pretrain(
    out: Path | None = typer.Option(None, "--out",
                                       help="Folder for encoder.pth/depth.pth (default: the default model)."),
    steps: int = typer.Option(1150, "--steps", min=1, help="Training steps (the shipped model: 1150)."),
    batch_size: int = typer.Option(4, "--batch-size", min=1),
    seed: int | None = typer.Option(None, "--seed", help="Default: the config's seed."),
    threads: int = typer.Option(1, "--threads", min=1, help="torch threads (results depend on it slightly)."),
    max_minutes: float | None = typer.Option(None, "--max-minutes", help="Stop early and save after this long."),
    quick: bool = typer.Option(False, "--quick", help="A few steps at small size (smoke test)."),
    pose: bool = typer.Option(False, "--pose", help="Train scheme comoda's pose network instead "
                              "(pose_encoder.pth/pose.pth, from the depth encoder in --out or the default)."),
    config: Path | None = ConfigOpt,
    sets: list[str] | None = SetOpt,
) -> None:
    """Train the default depth network on the synthetic source domain (stand-in for KITTI pre-training)."""
    from mutualslam_cli.adapt import pretrain as pt
    from mutualslam_cli.adapt.weights import default_weights_dir

    cfg = config_from(config, sets)
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
    with progress_bar() as p:
        task = p.add_task("pretrain", total=kwargs["steps"], info="")

        def cb(info: dict) -> None:
            p.update(task, completed=info.get("step", 0), info=f"loss {info.get('loss', float('nan')):.4f}")

        summary = pt.pretrain(out, progress=cb, **kwargs)
    common.console.print(f"saved the pre-trained model to {out} ({summary.get('time_s', 0):.0f} s, "
                  f"{summary.get('steps_done', summary.get('steps'))} steps)")


def _pretrain_pose(cfg: RunConfig, out: Path, steps: int, batch_size: int, seed: int, threads: int,
                   max_minutes: float | None, quick: bool) -> None:
    """``mslam pretrain --pose``: the pose network, initialised from the depth encoder found in ``out``."""
    from mutualslam_cli.adapt.pretrain_pose import pretrain_pose
    from mutualslam_cli.adapt.weights import default_weights_dir, load_monodepth2

    init = load_monodepth2(out if (out / "encoder.pth").is_file() else default_weights_dir())
    w, h, steps = (64, 32, min(steps, 3)) if quick else (cfg.net.width, cfg.net.height, steps)
    with progress_bar() as p:
        task = p.add_task("pretrain pose", total=steps, info="")

        def cb(info: dict) -> None:
            p.update(task, completed=info["step"], info=f"loss {info['loss']:.4f}")

        rec = pretrain_pose(out, steps, w, h, batch_size, seed=seed, init=init, max_minutes=max_minutes,
                            threads=threads, half=True, progress=cb)
    common.console.print(f"saved the pose network to {out} ({rec['time_s']:.0f} s, {rec['steps_done']} steps, "
                         f"final loss {rec['loss_curve'][-1]['loss']:.4f})")
