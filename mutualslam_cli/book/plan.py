"""The book's grids as runs (:func:`plan_book`): each (grid, variant) a config, a hash of it, its jobs and its
results folder ``<out>/runs/<grid>/<variant>/`` — the layout ``mslam ablate`` writes, so the grid machinery runs
it and skips what is complete.

Before any work it refuses what would publish a dishonest figure: a grid whose preset was tuned on one of its
sequences (the preset's ``# tuned-on:`` line, :func:`~mutualslam_cli.config.tuned_on`; a preset without that line
counts as tuned on everything), and a variant whose folder holds runs made under another config (its stamp
``book-config.json``: a resumed book would reuse them). Rendered rooms are rendered once into ``<out>/data/``;
a ``when_present`` sequence whose folder is absent is left out, named in the book.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from mutualslam_cli.ablate import Job, expand
from mutualslam_cli.adapt.schemes import get_scheme
from mutualslam_cli.book.entries import GridEntry
from mutualslam_cli.book.spec import BookSpec, GridSpec, SequenceRef
from mutualslam_cli.config import CONFIG_DIR, RunConfig, load_config, to_dict, tuned_on, with_settings
from mutualslam_cli.datasets.registry import get_spec
from mutualslam_cli.errors import ConfigError, DatasetError, MslamError
from mutualslam_cli.results.summary import flatten

#: The file in each variant's folder that records the config its runs were made under.
STAMP = "book-config.json"
#: Config keys that do not change a run's numbers (where its files go, where the data is found).
UNHASHED = ("out", "data.data_root", "experiment")


@dataclass
class Part:
    """One (grid, variant): its config, hash, jobs and folder."""

    grid: str
    variant: str
    cfg: RunConfig
    config_hash: str
    jobs: list[Job]
    out: Path
    sets: tuple[str, ...]
    preset: str


@dataclass
class Plan:
    """Every part of the book's grids, and the sequences left out (``when_present`` ones not on this machine)."""

    parts: list[Part] = field(default_factory=list)
    skipped: dict[str, list[str]] = field(default_factory=dict)  # grid → sequence labels
    sequences: dict[str, dict[str, SequenceRef]] = field(default_factory=dict)  # grid → label → ref
    data: dict[str, str] = field(default_factory=dict)  # sequence label → digest of its files (:func:`data_digest`)


def config_hash(cfg: RunConfig) -> str:
    """SHA-256 (16 hex digits) of the config's values that change a run's numbers (not :data:`UNHASHED`)."""
    d = {k: v for k, v in flatten(to_dict(cfg)).items() if not k.startswith(UNHASHED)}
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


def preset_path(preset: str, book: Path) -> Path:
    """A preset named in a book: relative to the repository (``configs/...``), else to the book file."""
    p = Path(preset)
    if p.is_absolute():
        return p
    repo = CONFIG_DIR.parent
    return repo / p if (repo / p).is_file() else book.parent / p


def _check_tuning(grid: GridSpec, preset: Path) -> None:
    """Refuse a grid that reports a tuned preset on data it was tuned on (module docstring)."""
    tuned = tuned_on(preset)
    labels = [s.label for s in grid.sequences + grid.when_present if s.synth is None]
    if tuned is None and labels:
        raise ConfigError(f"grid {grid.name}: preset {preset} has no '# tuned-on:' header line, so the data it was "
                          f"tuned on is unknown; name it (or '# tuned-on: none') before the book reports it on "
                          f"{', '.join(labels)}")
    clash = sorted(set(labels) & set(tuned or []))
    if clash:
        raise ConfigError(f"grid {grid.name}: preset {preset} was tuned on {', '.join(clash)} (its '# tuned-on:' "
                          "line), so the book does not report it there; report it on other data")


def render_synth(ref: SequenceRef, data_dir: Path) -> Path:
    """The rendered room of ``ref`` under ``data_dir`` (rendered now unless a complete copy is there: the folder
    is renamed into place only once whole)."""
    from mutualslam_cli.datasets.synthetic import render_sequence, write_tum

    assert ref.synth is not None
    out = data_dir / ref.name
    if (out / "groundtruth.txt").is_file():
        return out
    s = ref.synth
    w, h = (int(x) for x in s["size"].split("x"))
    tmp = data_dir / f".{ref.name}.rendering-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        write_tum(render_sequence(s["scene"], int(s["frames"]), w, h, int(s["seed"])), tmp)
        tmp.rename(out)
    except MslamError:
        raise
    except Exception as e:  # a renderer refusal (bad scene, size) as one line
        raise ConfigError(f"sequence {ref.name}: cannot render {s}: {e}") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


#: The files whose content names a sequence's data: its indexes, trajectories and intrinsics.
DATA_FILES = (".txt", ".freiburg")


def data_digest(folder: Path) -> str:
    """SHA-256 (16 hex digits) of the sequence folder's top-level index, trajectory and intrinsics files
    (:data:`DATA_FILES`): which frames, times, poses and camera a run read. A record made on other data is stale."""
    h = hashlib.sha256()
    for f in sorted(p for p in Path(folder).iterdir() if p.suffix in DATA_FILES and p.is_file()):
        h.update(f.name.encode() + b"\0" + f.read_bytes().replace(b"\r\n", b"\n") + b"\0")
    return h.hexdigest()[:16]


def _folder(ref: SequenceRef, out: Path, registry: str | None, data_root: str | None) -> Path:
    """Where a sequence's files are on this machine."""
    if ref.synth is not None:
        return out / "data" / ref.name
    if Path(ref.name).is_dir():
        return Path(ref.name)
    return Path(get_spec(ref.name, registry, data_root).root)


def _present(ref: SequenceRef, registry: str | None, data_root: str | None) -> bool:
    """Whether a named sequence's folder is on this machine."""
    if Path(ref.name).is_dir():
        return True
    try:
        spec = get_spec(ref.name, registry, data_root)
    except DatasetError:
        return False
    return Path(spec.root).exists()


def _stamp(part: Part) -> None:
    """Refuse a variant folder whose runs were made under another config; else (re)write its stamp."""
    path = part.out / STAMP
    now = {k: v for k, v in flatten(to_dict(part.cfg)).items() if not k.startswith(UNHASHED)}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError):
            old = {}
        if old.get("config_hash") not in (None, part.config_hash):
            was = old.get("config", {})
            diff = sorted(k for k in set(was) | set(now) if was.get(k) != now.get(k))
            shown = "; ".join(f"{k}: {was.get(k)!r} → {now.get(k)!r}" for k in diff[:4]) + (" …" if len(diff) > 4
                                                                                          else "")
            raise ConfigError(f"{part.out}: its runs were made under another config ({shown}); a resumed book "
                              "would reuse them: move the folder away (or delete it) to run that variant anew")
    part.out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({"config_hash": part.config_hash, "grid": part.grid, "variant": part.variant,
                               "preset": part.preset, "sets": list(part.sets), "config": now}, indent=1,
                              default=str) + "\n")
    tmp.replace(path)


def plan_book(spec: BookSpec, out: Path, grids: list[str], registry: str | None = None,
              data_root: str | None = None, overrides: list[str] | None = None, render: bool = True) -> Plan:
    """The parts of ``grids`` (module docstring); ``overrides``: ``key=value`` on every config (the CLI's
    ``--set``, e.g. ``threads=1``); ``render``: render the rooms and write the stamps (``False``: plan only).

    Raises:
        ConfigError: a preset tuned on the grid's data, an unknown scheme or override, a variant folder of another
            config.
        DatasetError: a required sequence that is not on this machine.
    """
    plan = Plan()
    for name in grids:
        g = spec.grids[name]
        preset = preset_path(g.preset, spec.path)
        _check_tuning(g, preset)
        common = list(spec.sets) + list(g.sets) + list(overrides or [])
        base = load_config(preset, common)
        for s in g.schemes:
            get_scheme(s, base.adapt)
        refs: dict[str, SequenceRef] = {}
        missing = [r.name for r in g.sequences if r.synth is None and not _present(r, registry, data_root)]
        if missing:
            raise DatasetError(f"grid {name}: sequence(s) {', '.join(missing)} not found on this machine "
                               "(datasets.yaml and the data root); move them to 'when_present' to run the book "
                               "without them")
        for r in g.sequences + g.when_present:
            if r.synth is not None:
                if render:
                    render_synth(r, out / "data")
                refs[r.label] = r
            elif _present(r, registry, data_root):
                refs[r.label] = r
            else:
                plan.skipped.setdefault(name, []).append(r.label)
        plan.sequences[name] = refs
        for label, r in refs.items():
            folder = _folder(r, out, registry, data_root)
            if label not in plan.data and folder.is_dir():
                plan.data[label] = data_digest(folder)
        seq_args = [str(out / "data" / r.name) if r.synth is not None else r.name for r in refs.values()]
        for variant, sets in g.variants.items():
            cfg = with_settings(base, list(sets))
            many = [x for x in g.schemes if x not in g.one_seed]
            jobs = expand(seq_args, many, list(g.seeds)) + expand(seq_args, list(g.one_seed), list(g.seeds[:1]))
            part = Part(name, variant, cfg, config_hash(cfg), jobs,
                        out / "runs" / name / variant, tuple(common) + tuple(sets),
                        str(g.preset))
            if render:
                _stamp(part)
            plan.parts.append(part)
    return plan


def part_of(plan: Plan, grid: str, variant: str) -> Part:
    """The part of ``grid``'s ``variant``."""
    for p in plan.parts:
        if p.grid == grid and p.variant == variant:
            return p
    raise KeyError((grid, variant))


def describe(plan: Plan) -> dict[str, GridEntry]:
    """Per grid and variant, the config hash, overrides and job count (for ``book.json``)."""
    out: dict[str, GridEntry] = {}
    for p in plan.parts:
        g = out.setdefault(p.grid, {"preset": p.preset, "variants": {}, "skipped": plan.skipped.get(p.grid, []),
                                    "sequences": [r.as_dict() for r in plan.sequences[p.grid].values()]})
        g["variants"][p.variant] = {"config_hash": p.config_hash, "sets": list(p.sets), "jobs": len(p.jobs),
                                    "schedule": p.cfg.adapt.schedule}
    return out
