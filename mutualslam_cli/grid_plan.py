"""The grid of an ``mslam ablate`` command line (:func:`plan_grid`): its schemes, seeds and variants, from the
arguments, else the config's ``experiment:`` section, else the defaults; refused in one line when it would run
nothing (no scheme, an empty seed range) or one run folder twice. :mod:`~mutualslam_cli.ablate` runs it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mutualslam_cli.ablate import Job, expand
from mutualslam_cli.adapt.schemes import get_scheme
from mutualslam_cli.config import RunConfig, with_settings
from mutualslam_cli.config.checks import SEED_MAX
from mutualslam_cli.errors import ConfigError

#: Schemes ``mslam ablate`` runs without ``--schemes`` or ``experiment.schemes``.
DEFAULT_SCHEMES = ("none", "recent", "replay", "replay+ewc", "replay+mas", "replay+si")


@dataclass
class GridPart:
    """One variant of a grid: its config, its jobs and its results folder."""

    label: str
    cfg: RunConfig
    jobs: list[Job]
    out: Path


#: The most seeds one grid runs (a range like ``0-99999999`` is a typo, not a grid).
MAX_SEEDS = 10_000


def parse_seeds(text: str) -> list[int]:
    """``"0,1,2"`` or ``"0-2"`` → ``[0, 1, 2]``.

    Raises:
        ConfigError: malformed, a seed outside 0..2³²−1 or given twice, an empty range (``3-1``), or more
            than :data:`MAX_SEEDS` seeds.
    """
    try:
        a, _, b = text.partition("-")
        lo, hi = (int(a), int(b)) if b else (None, None)
        seeds = [int(x) for x in text.split(",")] if lo is None else []
    except ValueError:
        raise ConfigError(f"--seeds {text!r}: expected e.g. 0,1,2 or 0-2") from None
    if lo is not None and hi is not None:
        if hi < lo:
            raise ConfigError(f"--seeds {text!r}: the range is empty ({hi} < {lo}), so the grid would run nothing; "
                              f"expected e.g. {hi}-{lo}")
        if hi - lo + 1 > MAX_SEEDS:
            raise ConfigError(f"--seeds {text!r}: {hi - lo + 1} seeds; a grid runs at most {MAX_SEEDS}")
        seeds = list(range(lo, hi + 1))
    for k in (seeds[0], seeds[-1]) if lo is not None else seeds:
        if not 0 <= k <= SEED_MAX:
            raise ConfigError(f"--seeds {text!r}: seed {k} is outside 0..{SEED_MAX}")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds {text!r}: a seed is given twice (each seed is one run folder)")
    return seeds


def _names(text: str, what: str, example: str) -> list[str]:
    """The comma-separated names of ``--<what>``; refused when none is left or one is given twice."""
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names:
        raise ConfigError(f"--{what} {text!r}: names no {what[:-1]}, so the grid would run nothing; expected e.g. "
                          f"{example}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError(f"--{what} {text!r}: {', '.join(twice)} given twice (each is one run folder)")
    return names


def plan_grid(cfg: RunConfig, sequences: list[str], schemes: str | None, seeds: str | None,
              out: Path) -> list[GridPart]:
    """The grid of a command line: schemes and seeds from the arguments, else from ``cfg.experiment``,
    else the defaults; one :class:`GridPart` per ``experiment.variants`` entry (into ``out/<label>``),
    or one for ``cfg`` itself into ``out``. The variants' labels are checked with the config
    (:class:`~mutualslam_cli.config.ExperimentConfig`).

    Raises:
        ConfigError: unknown scheme, malformed seeds or variant override, or a grid that would run nothing
            or one run twice (no scheme, an empty seed range, a name given twice).
    """
    names = (_names(schemes, "schemes", "none,replay+ewc") if schemes is not None
             else list(cfg.experiment.schemes) or list(DEFAULT_SCHEMES))
    for n in names:
        get_scheme(n, cfg.adapt)  # unknown name or a setting out of range: before any work
    seed_list = parse_seeds(seeds) if seeds is not None else list(cfg.experiment.seeds) or [0]
    twice = sorted({q for q in sequences if sequences.count(q) > 1})
    if twice:
        raise ConfigError(f"sequence {twice[0]!r} is given twice (each sequence is one run folder per scheme and seed)")
    jobs = expand(sequences, names, seed_list)
    if not cfg.experiment.variants:
        return [GridPart("", cfg, jobs, Path(out))]
    return [GridPart(label, with_settings(cfg, list(overrides)), jobs, Path(out) / label)
            for label, overrides in cfg.experiment.variants.items()]
