"""The experiment grid (DESIGN §9): sequences × schemes × seeds as independent, resumable jobs.

The front end does not depend on the scheme, so it runs once per (sequence, seed) before the
scheme jobs and lands in the VO cache that every job then reads. Jobs run in a local process
pool by default (one torch thread per worker when there are as many workers as cores), or on a
Dask cluster (``executor="dask"``: a ``LocalCluster`` without a scheduler address). Each job
writes only its own result folder, through a staging folder beside it that takes its place once
``summary.json`` is written (:mod:`~mutualslam_cli.results.staging`), so a folder is either a complete
run or untouched; a killed grid is resumed by running it again (complete runs are skipped, a killed
job's staging folder is removed and the job redone).

Nothing is left behind: local pool workers are spawned (not forked from a process that already
runs OpenMP threads), ask the kernel to kill them when the grid's process dies (Linux
``PR_SET_PDEATHSIG``, so ``kill -9`` of ``mslam ablate`` leaves no orphan), and ignore Ctrl-C,
which the grid's process handles: it stops the workers and re-raises ``KeyboardInterrupt``.
While a grid runs it holds the lock of its results folder (:mod:`mutualslam_cli.results.lock`), so a
second grid on the same folder stops at once with a clear message.

GPUs (DESIGN §9): with the network on CUDA (``device`` ``auto`` or ``cuda``) and several local workers,
each worker sees one GPU of its own (``CUDA_VISIBLE_DEVICES``, :func:`~mutualslam_cli.device.gpu_slots`),
so ``-j N`` on N GPUs runs one job per GPU. On Dask a job asks for one ``GPU`` resource when ``device`` is
``cuda``/``cuda:N`` (workers declare theirs: ``dask worker --resources GPU=1``, one worker per GPU, as
dask-jobqueue's GPU clusters do); a ``LocalCluster`` gets one worker per GPU, each with its own.
"""

from __future__ import annotations

import ctypes
import itertools
import logging
import multiprocessing
import os
import signal
import threading
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from threadpoolctl import threadpool_limits

from mutualslam_cli.config import RunConfig, with_overrides
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.device import Slots, claim_gpu, gpu_slots
from mutualslam_cli.errors import ConfigError, MslamError
from mutualslam_cli.pipeline import run_sequence
from mutualslam_cli.results.lock import hold_lock
from mutualslam_cli.results.run_folder import is_complete, run_dir
from mutualslam_cli.results.writable import check_output_folder, write_errors
from mutualslam_cli.stages.context import resolve_threads, use_threads
from mutualslam_cli.stages.frontend import run_frontend

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
    return with_overrides(cfg, adapt={"scheme": job.scheme}, seed=job.seed, threads=threads)


def _run_job(cfg: RunConfig, job: Job, out: str, command: list[str] | None, registry: str | None,
             threads: int, *after: object) -> JobOutcome:
    """Worker body: run one job; library errors become a ``failed`` outcome, not a crash of the grid.

    ``after``: ignored; Dask passes the job's front-end task result here so the job waits for it.
    """
    try:  # run_sequence gives torch, OpenCV and BLAS the same threads, whatever the executor set up
        r = run_sequence(job.sequence, _job_config(cfg, job, threads), out=out, command=command,
                         registry=Path(registry) if registry else None)
        return JobOutcome(job, "skipped" if r.skipped else "done", r.folder)
    except MslamError as e:
        return JobOutcome(job, "failed", None, str(e))
    except Exception as e:  # a bug in one job must not lose the others' results
        return JobOutcome(job, "failed", None, f"{type(e).__name__}: {e}\n{traceback.format_exc()}")


def _prepare_one(cfg: RunConfig, sequence: str, seed: int, out: str, registry: str | None, threads: int) -> str | None:
    """Run one (sequence, seed) front end into ``<out>/_cache/vo``; the error message if it failed
    (the sequence's jobs then fail with it themselves, and the other sequences go on)."""
    # the jobs' thread count, set for OpenCV, torch and BLAS as a job sets it: the front end's output follows it
    c = use_threads(with_overrides(cfg, seed=seed, threads=threads))
    try:
        seq = load_sequence(sequence, data_root=c.data.data_root, registry_path=registry,
                            max_frames=c.data.max_frames, stride=c.data.stride)
        with threadpool_limits(limits=c.threads, user_api="blas"), write_errors(out):  # a full disk: OutputError
            run_frontend(seq, c, cache_dir=Path(out) / "_cache" / "vo")
    except MslamError as e:
        log.warning("front end for %s (seed %d) failed: %s", sequence, seed, e)
        return str(e)
    return None


def prepare_frontends(cfg: RunConfig, sequences: list[str], seeds: list[int], out: str,
                      registry: str | None = None, threads: int | None = None) -> None:
    """Run every (sequence, seed) front end once, in this process, with the jobs' ``threads`` (default
    ``cfg.threads``), so scheme jobs find it in the VO cache."""
    for q, k in itertools.product(sequences, seeds):
        _prepare_one(cfg, q, k, out, registry, cfg.threads if threads is None else threads)


def _warm_up() -> None:
    """Pool task that does nothing: a worker unpickling it imports this module, and with it the
    pipeline (torch, seconds), so the worker is ready when the front ends are."""


def _die_with_parent() -> None:
    """Pool worker initialiser: killed with the grid's process, deaf to Ctrl-C (the grid handles it)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1 (Linux)
    except (OSError, AttributeError):  # not Linux: the pool's own shutdown is all there is
        return
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)


def _init_worker(slots: Slots | None = None) -> None:
    """Pool worker initialiser: :func:`_die_with_parent`, then a GPU of its own when the grid places them."""
    _die_with_parent()
    if slots is not None:
        claim_gpu(slots)


def make_pool(workers: int, slots: list[str]) -> ProcessPoolExecutor:
    """A spawned pool of ``workers`` processes; worker k takes ``CUDA_VISIBLE_DEVICES = slots[k]`` (none: as is)."""
    ctx = multiprocessing.get_context("spawn")
    queue = None
    if slots:
        queue = ctx.Queue()
        for s in slots:
            queue.put(s)
    return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker, initargs=(queue,))


def _local_outcomes(cfg: RunConfig, todo: list[Job], out: str, command: list[str] | None, reg: str | None,
                    workers: int, threads: int) -> Iterator[JobOutcome]:
    """Outcomes of ``todo`` run in this process (1 worker) or a spawned process pool, as they finish."""
    seqs, seeds = sorted({j.sequence for j in todo}), sorted({j.seed for j in todo})
    if workers <= 1:
        prepare_frontends(cfg, seqs, seeds, out, reg, threads)
        for j in todo:
            yield _run_job(cfg, j, out, command, reg, threads)
        return
    slots = gpu_slots(cfg.device, workers)
    if slots:
        log.info("one GPU per worker: CUDA_VISIBLE_DEVICES %s", ", ".join(slots))
    pool = make_pool(workers, slots)
    try:
        # the workers start (and import torch, seconds each) while this process runs the front ends
        warm = [pool.submit(_warm_up) for _ in range(workers)]
        prepare_frontends(cfg, seqs, seeds, out, reg, threads)
        with _ctrl_c_as_flag() as stop:
            _wait_all(warm, stop)
            futs = [pool.submit(_run_job, cfg, j, out, command, reg, threads) for j in todo]
            pending = set(futs)
            while pending:
                done, pending = wait(pending, timeout=_POLL_S, return_when=FIRST_COMPLETED)
                if stop.is_set():
                    raise KeyboardInterrupt
                for f in sorted(done, key=futs.index):
                    yield f.result()
    except BaseException:  # Ctrl-C (or the consumer stopping): stop the workers now, not after their jobs
        for p in list(getattr(pool, "_processes", {}).values()):
            p.kill()
        manager = getattr(pool, "_executor_manager_thread", None)
        pool.shutdown(wait=False, cancel_futures=True)
        # let the pool's manager thread see its workers gone and close its wake-up pipe now: still running at
        # interpreter exit, it races concurrent.futures' exit hook, which then writes to the closed pipe and
        # prints an OSError traceback after our message (Python 3.11; seen on a loaded machine)
        if manager is not None:
            manager.join(timeout=_JOIN_S)
        raise
    pool.shutdown()


#: Seconds between checks for Ctrl-C while the pool works.
_POLL_S = 0.2
#: Seconds an interrupted grid waits for the pool's manager thread to finish after killing the workers.
_JOIN_S = 10.0


@contextmanager
def _ctrl_c_as_flag() -> Iterator[threading.Event]:
    """Within the block, Ctrl-C sets the yielded event instead of raising ``KeyboardInterrupt``.

    While the pool works the main thread sits in ``concurrent.futures``' locking; an exception raised
    there at an arbitrary instruction can leave a future's lock held, and the pool's manager thread
    then waits for it forever when the interpreter exits (a grid that never stopped after Ctrl-C,
    seen once on a loaded machine). The caller checks the event and raises from a known point."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = signal.signal(signal.SIGINT, lambda signum, frame: stop.set())
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


def _wait_all(futures: list[Future[None]], stop: threading.Event) -> None:
    """Wait for every future; ``KeyboardInterrupt`` as soon as ``stop`` is set."""
    pending = set(futures)
    while pending:
        _, pending = wait(pending, timeout=_POLL_S)
        if stop.is_set():
            raise KeyboardInterrupt


def _dask_outcomes(cfg: RunConfig, todo: list[Job], out: str, command: list[str] | None, reg: str | None,
                   workers: int, scheduler: str | None) -> Iterator[JobOutcome]:
    """Outcomes of ``todo`` run on a Dask cluster (``scheduler`` address, or a ``LocalCluster`` of
    ``workers`` single-threaded processes). Front ends are tasks too, one per (sequence, seed), and
    each job depends on its own; results go to the shared ``out`` folder."""
    try:
        from dask.distributed import Client, LocalCluster
        from dask.distributed import as_completed as dask_completed
    except ImportError:
        raise ConfigError("--executor dask needs dask.distributed: pip install 'dask[distributed]'") from None
    cluster = None
    gpu = cfg.device.startswith("cuda")  # each job asks for one GPU (only where the config says so: a cluster
    # without GPU resources would hold the jobs forever; ``auto`` runs where it lands)
    resources = {"GPU": 1} if gpu else None
    slots = gpu_slots(cfg.device, workers) if scheduler is None else []  # ``cuda``, several workers
    if scheduler is None:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                               resources=resources)
        threads = resolve_threads(cfg.threads, workers)
    else:
        threads = cfg.threads  # 0: every core of the worker's machine
    client = Client(cluster if cluster is not None else scheduler)
    if slots:  # a LocalCluster on a multi-GPU machine: worker k sees GPU k (before any job initialises CUDA)
        for addr, slot in zip(sorted(client.scheduler_info()["workers"]), slots):
            client.run(_set_visible, slot, workers=[addr])
    try:
        fronts = {(q, k): client.submit(_prepare_one, cfg, q, k, out, reg, threads, pure=False,
                                        key=f"vo-{Path(q).name}-seed{k}-{os.getpid()}")
                  for q, k in sorted({(j.sequence, j.seed) for j in todo})}
        futs = {client.submit(_run_job, cfg, j, out, command, reg, threads, fronts[(j.sequence, j.seed)],
                              pure=False, resources=resources): j for j in todo}
        for f in dask_completed(list(futs)):
            try:
                yield f.result()
            except Exception as e:  # a lost worker fails its job, not the grid
                yield JobOutcome(futs[f], "failed", None, f"{type(e).__name__}: {e}")
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _set_visible(slot: str) -> None:
    """On a Dask worker: the GPU it may use (:func:`_dask_outcomes`)."""
    os.environ["CUDA_VISIBLE_DEVICES"] = slot


def run_grid(cfg: RunConfig, jobs: list[Job], out: str | Path, workers: int = 1,
             command: list[str] | None = None, registry: str | Path | None = None,
             on_done: Callable[[JobOutcome], None] | None = None, executor: str = "local",
             scheduler: str | None = None) -> list[JobOutcome]:
    """Run ``jobs`` (complete ones are skipped) and return one outcome per job.

    Args:
        workers: local processes (or ``LocalCluster`` workers); each uses ``cfg.threads`` torch threads,
            or ``max(1, cpu_count // workers)`` when that is 0 (the default).
        on_done: called as each job finishes (progress display).
        executor: ``"local"`` (process pool, the default) or ``"dask"``.
        scheduler: Dask scheduler address (``tcp://host:8786``); ``None`` starts a ``LocalCluster``.

    Each job's run writes a staging folder that replaces its run folder when it completes
    (:mod:`~mutualslam_cli.results.staging`), so a failed or killed job leaves no half-written run folder.

    Raises:
        ResultsLocked: another grid or run holds ``out``.
        OutputError: ``out`` is a file or cannot be written.
        KeyboardInterrupt: Ctrl-C; the workers are stopped first, finished jobs stay complete.
    """
    if executor not in ("local", "dask"):
        raise ConfigError(f"--executor {executor!r}: expected local or dask")
    out = str(check_output_folder(out))  # a file, read-only: one line before any work
    reg = str(registry) if registry else None
    threads = resolve_threads(cfg.threads, workers)
    outcomes: list[JobOutcome] = []

    def record(o: JobOutcome) -> None:
        outcomes.append(o)
        if on_done:
            on_done(o)

    with hold_lock(Path(out), "mslam ablate"):
        todo = []
        for j in jobs:
            name = Path(j.sequence).name if Path(j.sequence).is_dir() else j.sequence
            folder = run_dir(out, name, j.scheme, j.seed)
            if is_complete(folder):
                record(JobOutcome(j, "skipped", folder))
            else:
                todo.append(j)
        if todo:
            stream = (_dask_outcomes(cfg, todo, out, command, reg, workers, scheduler) if executor == "dask"
                      else _local_outcomes(cfg, todo, out, command, reg, workers, threads))
            for o in stream:
                record(o)
    return outcomes
