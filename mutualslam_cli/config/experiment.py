"""The experiment section of the run configuration (``experiment:``): what ``mslam ablate`` runs for a
paper experiment and how the tables name it."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class ExperimentConfig:
    """What a paper experiment runs (``mslam ablate --config configs/<experiment>.yaml``) and reports."""

    name: str = ""
    """The experiment (e.g. ``table3_schemes``); empty for an ordinary run."""
    schemes: list[str] = field(default_factory=list)
    """Schemes ``mslam ablate`` runs when ``--schemes`` is not given (empty: its default list)."""
    seeds: list[int] = field(default_factory=list)
    """Seeds ``mslam ablate`` runs when ``--seeds`` is not given (empty: seed 0)."""
    ours: str = "replay+ewc"
    """The scheme the paper tables report as "Ours"."""
    variants: dict[str, list[str]] = field(default_factory=dict)
    """Named config variants, label → ``key=value`` overrides: ``mslam ablate`` runs the whole grid once
    per variant into ``<out>/<label>/`` (e.g. Table 5's culling off and ``vo.max_fts`` 120)."""
