"""The top level of the run configuration: :class:`RunConfig` (seed, threads, device, results folder and
one section per part of the tool) with its input section :class:`DataConfig`, and the ways to make one:
:func:`load_config` (a YAML file + ``--set`` overrides), :func:`with_settings`, :func:`with_overrides`;
:func:`to_dict` writes one out (each run's ``config.yaml``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from mutualslam_cli.config.adaptation import AdaptConfig, NetConfig
from mutualslam_cli.config.backend import BAConfig, LoopConfig
from mutualslam_cli.config.checks import DEVICE, NOT_EMPTY, SEED, Relation, at_least, between, check_run, setting
from mutualslam_cli.config.evaluation import DenseConfig, EvalConfig
from mutualslam_cli.config.experiment import ExperimentConfig
from mutualslam_cli.config.frontend import VOConfig
from mutualslam_cli.config.parse import apply_overrides, build
from mutualslam_cli.config.yaml_file import read_yaml_mapping
from mutualslam_cli.errors import ConfigError
from mutualslam_cli.types import JSONObject, Scalar

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

CONFIG_DIR = Path(__file__).resolve().parent.parent.parent / "configs"
#: The preset a command reads without ``--config``: the paper's method made robust (its header says what chose it).
#: ``configs/paper.yaml`` holds the paper's values, which are the dataclass defaults.
DEFAULT_CONFIG = CONFIG_DIR / "default.yaml"


@dataclass(frozen=True)
class DataConfig:
    data_root: str | None = None
    """Root for relative ``datasets.yaml`` paths; ``None`` → ``$MSLAM_DATA`` or the yaml's folder."""
    max_frames: int = setting(0, at_least(0, "0 = all"))
    """Use only the first N associated frames (0 = all)."""
    stride: int = setting(1, at_least(1, "frames"))
    """Use every k-th frame."""


@dataclass(frozen=True)
class RunConfig:
    """A run's whole configuration: the top-level settings (each with its range beside it) and one record per
    section; ``RELATIONS`` holds the rules between sections."""

    RELATIONS: ClassVar[tuple[Relation[RunConfig], ...]] = (
        Relation("vo.inject_outliers", lambda c: c.vo.inject_outliers == 0 or c.adapt.labels == "hindsight",
                 lambda c: "0 (it corrupts the finished front end's map: it needs adapt.labels=hindsight)"),
        Relation("adapt.train_width", lambda c: c.adapt.train_width <= c.net.width,
                 lambda c: f"≤ net.width ({c.net.width}; 0 = net.width)"),
        Relation("adapt.train_height", lambda c: c.adapt.train_height <= c.net.height,
                 lambda c: f"≤ net.height ({c.net.height}; 0 = net.height)"),
    )

    seed: int = setting(0, SEED)
    """Seed of every random choice (replay sampling, RANSAC, init)."""
    threads: int = setting(0, between(0, 4096, "0 = all cores"))
    """torch/OpenCV threads (0 = all cores)."""
    device: str = setting("auto", DEVICE)
    """Where the depth network runs: ``auto`` (CUDA when ``torch.cuda.is_available()``, else the CPU), ``cpu``,
    ``cuda`` or ``cuda:N``; VO, BA and metrics always run on the CPU (:mod:`~mutualslam_cli.device`)."""
    deterministic: bool = True
    """CUDA: deterministic cuDNN algorithms, no autotuning (one seed, one result; slower convolution backward
    kernels); ``false``: ``cudnn.benchmark`` autotuning (:mod:`~mutualslam_cli.device`). No effect on the CPU."""
    out: str = setting("results", NOT_EMPTY)
    """Folder that receives ``<sequence>/<scheme>/seed<k>/``."""
    data: DataConfig = field(default_factory=DataConfig)
    vo: VOConfig = field(default_factory=VOConfig)
    net: NetConfig = field(default_factory=NetConfig)
    adapt: AdaptConfig = field(default_factory=AdaptConfig)
    ba: BAConfig = field(default_factory=BAConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    experiment: ExperimentConfig = field(default_factory=ExperimentConfig)


def to_dict(cfg: DataclassInstance) -> dict[str, Any]:
    """Plain nested dict of a config or one of its sections (safe for ``yaml.safe_dump`` and JSON): a
    :data:`~mutualslam_cli.types.JSONObject`, typed ``Any``-valued as callers write into its sections."""
    return dataclasses.asdict(cfg)


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> RunConfig:
    """Load a YAML config (default :data:`DEFAULT_CONFIG`, ``configs/default.yaml``), apply ``--set`` overrides,
    validate.

    Raises:
        ConfigError: one line naming the file or the key: a file that is missing, not a file, not UTF-8, not
            valid YAML, with a key given twice or too many aliases (:mod:`~mutualslam_cli.config.yaml_file`); an
            unknown key, a wrong type, a value out of its range (:mod:`~mutualslam_cli.config.checks`).
    """
    path = Path(path) if path is not None else DEFAULT_CONFIG
    data: JSONObject = {}
    if path != CONFIG_DIR / "paper.yaml" or path.exists():
        data = read_yaml_mapping(path, ConfigError, "YAML config file")
    cfg = build(RunConfig, apply_overrides(data, overrides or [], create=True), "")
    check_run(cfg)
    return cfg


def with_settings(cfg: RunConfig, overrides: list[str]) -> RunConfig:
    """Return ``cfg`` with ``--set``-style ``key=value`` overrides applied (validated like a file)."""
    out = build(RunConfig, apply_overrides(to_dict(cfg), overrides, create=False), "")
    check_run(out)
    return out


def with_overrides(cfg: RunConfig, **sections: Scalar | JSONObject) -> RunConfig:
    """Return ``cfg`` with some fields replaced: ``with_overrides(cfg, adapt={"scheme": "none"})`` updates a
    section's fields, ``seed=0`` sets a top-level value."""
    data: JSONObject = to_dict(cfg)
    for sec, vals in sections.items():
        if isinstance(vals, dict):
            section = data[sec]
            if not isinstance(section, dict):
                raise ConfigError(f"{sec} = {vals!r}: {sec} is not a config section")
            section.update(vals)
        else:
            data[sec] = vals
    out = build(RunConfig, data, "")
    check_run(out)
    return out
