"""The experiment section of the run configuration (``experiment:``): what ``mslam ablate`` runs for a
paper experiment and how the tables name it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from mutualslam_cli.config.checks import NOT_EMPTY, SEED, Relation, setting


def _usable_labels(variants: dict[str, list[str]]) -> bool:
    """Every label names one folder of its own (``<out>/<label>/``): not empty, no ``/``, not hidden or ``_cache``."""
    return all(label and "/" not in label and not label.startswith((".", "_"))
               for label in variants)


@dataclass(frozen=True)
class ExperimentConfig:
    """What a paper experiment runs (``mslam ablate --config configs/<experiment>.yaml``) and reports; each
    field's range is beside it, ``RELATIONS`` holds those of whole lists."""

    RELATIONS: ClassVar[tuple[Relation[ExperimentConfig], ...]] = (
        Relation("schemes", lambda c: len(set(c.schemes)) == len(c.schemes), lambda c: "no scheme named twice"),
        Relation("seeds", lambda c: len(set(c.seeds)) == len(c.seeds), lambda c: "no seed named twice"),
        Relation("variants", lambda c: _usable_labels(c.variants),
                 lambda c: "labels that are folder names: not empty, no '/', not starting with '.' or '_'"),
    )

    name: str = ""
    """The experiment (e.g. ``table3_schemes``); empty for an ordinary run."""
    schemes: list[str] = setting(rule=NOT_EMPTY, factory=list)
    """Schemes ``mslam ablate`` runs when ``--schemes`` is not given (empty: its default list)."""
    seeds: list[int] = setting(rule=SEED, factory=list)
    """Seeds ``mslam ablate`` runs when ``--seeds`` is not given (empty: seed 0)."""
    ours: str = setting("replay+ewc", NOT_EMPTY)
    """The scheme the paper tables report as "Ours"."""
    variants: dict[str, list[str]] = setting(factory=dict)
    """Named config variants, label → ``key=value`` overrides: ``mslam ablate`` runs the whole grid once
    per variant into ``<out>/<label>/`` (e.g. Table 5's culling off and ``vo.max_fts`` 120)."""
