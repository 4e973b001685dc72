"""Run configuration: frozen dataclasses, loaded by a strict YAML reader and validated. ``configs/paper.yaml``
holds the paper's values (DESIGN §4–7), which are the defaults: a missing key means "the paper's value".
``--set section.key=value`` overrides one field; the value is parsed as YAML (``--set adapt.lr=1e-4``).

The package owns every setting of a run, one module per thing configured: :mod:`.run` (the top level,
:class:`RunConfig`, ``data:``), :mod:`.frontend` (``vo:``), :mod:`.adaptation` (``net:``, ``adapt:``),
:mod:`.backend` (``ba:``, ``loop:``), :mod:`.evaluation` (``eval:``, ``dense:``), :mod:`.experiment`
(``experiment:``); :mod:`.yaml_file` reads the YAML a user wrote (no key twice, no alias bomb, UTF-8),
:mod:`.parse` turns plain values into the records, :mod:`.checks` holds the range of every value (declared
beside its field) and refuses values the tool cannot work with, once, before any work. It sits on the ground
floor: it imports :mod:`mutualslam_cli.errors` and nothing else of the package.

Entry points: :func:`load_config`, :func:`with_settings`, :func:`with_overrides`, :func:`to_dict`,
:func:`tuned_on` (:mod:`.presets`: the data a preset was tuned on, from its header) and :data:`CONFIG_DIR`; the
section records below.
"""

from mutualslam_cli.config.adaptation import AdaptConfig, NetConfig
from mutualslam_cli.config.backend import BAConfig, LoopConfig
from mutualslam_cli.config.evaluation import DenseConfig, EvalConfig
from mutualslam_cli.config.experiment import ExperimentConfig
from mutualslam_cli.config.frontend import VOConfig
from mutualslam_cli.config.presets import tuned_on
from mutualslam_cli.config.run import (
    CONFIG_DIR,
    DEFAULT_CONFIG,
    DataConfig,
    RunConfig,
    load_config,
    to_dict,
    with_overrides,
    with_settings,
)

__all__ = [
    "CONFIG_DIR",
    "DEFAULT_CONFIG",
    "AdaptConfig",
    "BAConfig",
    "DataConfig",
    "DenseConfig",
    "EvalConfig",
    "ExperimentConfig",
    "LoopConfig",
    "NetConfig",
    "RunConfig",
    "VOConfig",
    "load_config",
    "to_dict",
    "tuned_on",
    "with_overrides",
    "with_settings",
]
