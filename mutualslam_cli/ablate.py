"""The experiment grid (DESIGN §9): sequences × schemes × seeds as independent, resumable jobs.

The front end does not depend on the scheme, so it runs once per (sequence, seed) before the
scheme jobs and lands in the VO cache that every job then reads. Jobs run in a local process
pool (one torch thread per worker). Each job writes only its own result folder; a complete
folder (``summary.json`` present) is skipped, so a killed grid is resumed by running it again.
"""

from __future__ import annotations

import itertools
import logging
import os
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from mutualslam_cli import results as res
from mutualslam_cli.config import RunConfig, with_overrides
from mutualslam_cli.errors import MslamError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Job:
    """One cell of the grid."""

    sequence: str
    scheme: str
    seed: int


@dataclass
class JobOutcome:
    """What happened to a job: ``done``, ``skipped`` (already complete) or ``failed`` (with the error)."""

    job: Job
    status: str
    folder: Path | None = None
    error: str | None = None


def expand(sequences: list[str], schemes: list[str], seeds: list[int]) -> list[Job]:
    """The grid in a stable order (sequence, then seed, then scheme)."""
    return [Job(q, s, k) for q, k, s in itertools.product(sequences, seeds, schemes)]


def _job_config(cfg: RunConfig, job: Job, threads: int) -> RunConfig:
    return with_overrides(cfg, adapt={"scheme": job.scheme}, seed=job.seed, threads=threads)  # type: ignore[arg-type]


def _run_job(cfg: RunConfig, job: Job, out: str, command: list[str] | None, registry: str | None,
             threads: int) -> JobOutcome:
    """Worker body: run one job; library errors become a ``failed`` outcome, not a crash of the grid."""
    from mutualslam_cli.pipeline import run_sequence

    try:
        r = run_sequence(job.sequence, _job_config(cfg, job, threads), out=out, command=command,
                         registry=Path(registry) if registry else None)
        return JobOutcome(job, "skipped" if r.skipped else "done", r.folder)
    except MslamError as e:
        return JobOutcome(job, "failed", None, str(e))
    except Exception as e:  # noqa: BLE001 - a bug in one job must not lose the others' results
        return JobOutcome(job, "failed", None, f"{type(e).__name__}: {e}\n{traceback.format_exc()}")


def prepare_frontends(cfg: RunConfig, sequences: list[str], seeds: list[int], out: str,
                      registry: str | None = None) -> None:
    """Run every (sequence, seed) front end once so scheme jobs find it in the VO cache."""
    from mutualslam_cli.datasets.registry import load_sequence
    from mutualslam_cli.vo_cache import run_frontend

    for q, k in itertools.product(sequences, seeds):
        c = with_overrides(cfg, seed=k)  # type: ignore[arg-type]
        try:
            seq = load_sequence(q, data_root=c.data.data_root, registry_path=registry,
                                max_frames=c.data.max_frames, stride=c.data.stride)
            run_frontend(seq, c, cache_dir=Path(out) / "_cache" / "vo")
        except MslamError as e:  # the sequence's jobs will fail with this message; the others go on
            log.warning("front end for %s (seed %d) failed: %s", q, k, e)


def run_grid(cfg: RunConfig, jobs: list[Job], out: str | Path, workers: int = 1,
             command: list[str] | None = None, registry: str | Path | None = None,
             on_done: Callable[[JobOutcome], None] | None = None) -> list[JobOutcome]:
    """Run ``jobs`` (complete ones are skipped) and return one outcome per job.

    Args:
        workers: processes; each uses ``max(1, cpu_count // workers)`` torch threads.
        on_done: called as each job finishes (progress display).
    """
    out = str(out)
    reg = str(registry) if registry else None
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    outcomes: list[JobOutcome] = []
    todo = []
    for j in jobs:
        name = Path(j.sequence).name if Path(j.sequence).is_dir() else j.sequence
        folder = res.run_dir(out, name, j.scheme, j.seed)
        if res.is_complete(folder):
            o = JobOutcome(j, "skipped", folder)
            outcomes.append(o)
            if on_done:
                on_done(o)
        else:
            todo.append(j)
    if not todo:
        return outcomes
    prepare_frontends(cfg, sorted({j.sequence for j in todo}), sorted({j.seed for j in todo}), out, reg)
    if workers <= 1:
        for j in todo:
            o = _run_job(cfg, j, out, command, reg, threads)
            outcomes.append(o)
            if on_done:
                on_done(o)
        return outcomes
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futs = {pool.submit(_run_job, cfg, j, out, command, reg, threads): j for j in todo}
        for f in as_completed(futs):
            o = f.result()
            outcomes.append(o)
            if on_done:
                on_done(o)
    return outcomes
