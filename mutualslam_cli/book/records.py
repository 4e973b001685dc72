"""The book's records: one small JSON file per finished job, committed with the repository, so a book survives
its run folders (:class:`Record`, :func:`job_state`).

A record holds what the book publishes of one run and where it came from: the run's flattened ``summary.json``
(every figure a table, finding or bound reads), its running-accuracy curves (the figure), the grid's config hash,
the fingerprint of the code that made it (:mod:`~mutualslam_cli.results.fingerprint`), the commit, CPU kind and
model, torch version, thread count, seed and the seconds the run took. It lives at
``<records>/<book>/<grid>/<variant>/<sequence>/<scheme>/seed<k>.json`` (``results/records/`` by default; a few
kB each), and a book run on any checkout and any machine counts the job complete when its record is **fresh**:
made under the grid's config hash, on the same sequence files, by code of the checkout's fingerprint. A record of
another fingerprint is **stale** — the code may have changed its results — and the job runs again (so is one of
another config or other data); the files that changed are named when
``<records>/code/<fingerprint>.json`` (each fingerprint's file hashes, written with its first record) is there.

A record carries the SHA-256 of its content (``digest``). One whose digest, format, fields or place do not match
is refused with one line naming the file (:class:`~mutualslam_cli.errors.DamagedRecord`): damaged, or written by
hand. Records of different CPU kinds can complete one book; a cell whose seeds span kinds says so (``‡``).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import pandas as pd
import yaml

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.errors import DamagedRecord
from mutualslam_cli.results.fingerprint import changed_files, code_fingerprint, code_manifest
from mutualslam_cli.results.run_folder import read_manifest
from mutualslam_cli.results.summary import read_summary
from mutualslam_cli.types import JSON, JSONObject, Scalar

#: The records' format; a reader refuses another.
FORMAT = 1
KIND = "mslam-book-record"
#: The running-accuracy curves a record keeps (``per_frame.csv``'s ``<model>_pcd_lsq_running``, %).
CURVES = ("pretrained", "adapted", "online")


@dataclass(frozen=True)
class Record:
    """One finished job of a book (module docstring). ``seconds``: the run's wall time; ``summary``: the flattened
    ``summary.json`` (non-finite numbers as ``None``); ``curves``: ``frame`` and each of :data:`CURVES` the run
    has, one value per frame (PCD %, 3 decimals)."""

    book: str
    grid: str
    variant: str
    sequence: str
    scheme: str
    seed: int
    config_hash: str
    data: str | None
    code: str
    commit: str | None
    cpu_kind: str
    cpu_model: str | None
    torch: str | None
    threads: int | None
    seconds: float | None
    created_utc: str
    summary: dict[str, Scalar]
    curves: dict[str, list[float | None]]

    def job(self) -> tuple[str, str, str, str, int]:
        """(grid, variant, sequence, scheme, seed)."""
        return self.grid, self.variant, self.sequence, self.scheme, self.seed


def _canonical(body: JSONObject) -> bytes:
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()


def record_path(root: Path, book: str, grid: str, variant: str, sequence: str, scheme: str, seed: int) -> Path:
    """Where the record of one job lives (module docstring)."""
    return Path(root) / book / grid / variant / sequence / scheme / f"seed{seed}.json"


def path_of(root: Path, rec: Record) -> Path:
    return record_path(root, rec.book, *rec.job())


def write_record(root: Path, rec: Record) -> Path:
    """Write ``rec`` (atomic) with its digest, and this checkout's file hashes under ``code/`` when ``rec`` is of
    this checkout's fingerprint and they are not there yet; the record's path."""
    body = {"format": FORMAT, "kind": KIND, **asdict(rec)}
    doc = {**body, "digest": hashlib.sha256(_canonical(body)).hexdigest()}
    path = path_of(root, rec)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(doc, indent=1, ensure_ascii=False, allow_nan=False) + "\n")
    code = Path(root) / "code" / f"{rec.code}.json"
    if rec.code == code_fingerprint() and not code.is_file():
        code.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(code, json.dumps(code_manifest(), indent=1, sort_keys=True) + "\n")
    return path


_TYPES: dict[str, tuple[type, ...]] = {
    "book": (str,), "grid": (str,), "variant": (str,), "sequence": (str,), "scheme": (str,), "seed": (int,),
    "config_hash": (str,), "data": (str, type(None)), "code": (str,), "commit": (str, type(None)), "cpu_kind": (str,),
    "cpu_model": (str, type(None)), "torch": (str, type(None)), "threads": (int, type(None)),
    "seconds": (float, int, type(None)), "created_utc": (str,), "summary": (dict,), "curves": (dict,)}


def read_record(path: Path) -> Record:
    """The record at ``path``, checked (module docstring).

    Raises:
        DamagedRecord: not JSON, another format, a field missing or of the wrong type, a digest that does not
            match its content (damaged or edited by hand), or a file whose place is not its job's.
    """
    path = Path(path)

    def refuse(why: str) -> DamagedRecord:
        return DamagedRecord(f"{path}: {why}; a book record is written only by mslam book — delete the file to run "
                             "that job again")

    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise refuse(f"not a readable JSON record ({e})") from None
    if not isinstance(doc, dict) or doc.get("kind") != KIND or doc.get("format") != FORMAT:
        raise refuse(f"not a book record of format {FORMAT} (expected \"kind\": \"{KIND}\")")
    names = [f.name for f in fields(Record)]
    extra = sorted(set(doc) - set(names) - {"format", "kind", "digest"})
    missing = [n for n in names if n not in doc]
    if missing or extra:
        raise refuse(f"fields {', '.join(missing) or '—'} missing, {', '.join(extra) or '—'} unexpected")
    for name, types in _TYPES.items():
        v = doc[name]
        if not isinstance(v, types) or (isinstance(v, bool) and bool not in types):
            raise refuse(f"field {name} is {type(v).__name__}, expected {' or '.join(t.__name__ for t in types)}")
    body = {k: v for k, v in doc.items() if k != "digest"}
    if doc.get("digest") != hashlib.sha256(_canonical(body)).hexdigest():
        raise refuse("its digest does not match its content (damaged, or edited by hand)")
    if any(not isinstance(v, (str, int, float, bool, type(None))) for v in doc["summary"].values()):
        raise refuse("summary holds a value that is not a number, text, true/false or null")
    rec = Record(**{n: doc[n] for n in names})
    root = path.parents[5] if len(path.parents) > 5 else None
    if root is None or path_of(root, rec).resolve() != path.resolve():
        raise refuse(f"it is the record of {'/'.join(map(str, rec.job()))} of book {rec.book}, not of this place")
    return rec


def _finite(v: JSON) -> Scalar:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v if isinstance(v, (str, int, float, bool, type(None))) else str(v)


def _curves(folder: Path) -> dict[str, list[float | None]]:
    f = folder / "per_frame.csv"
    if not f.is_file():
        return {}
    pf = pd.read_csv(f)
    have = [m for m in CURVES if f"{m}_pcd_lsq_running" in pf]
    if "frame" not in pf or not have:
        return {}
    out: dict[str, list[float | None]] = {"frame": [float(x) for x in pf["frame"]]}
    for m in have:
        vals = pd.to_numeric(pf[f"{m}_pcd_lsq_running"], errors="coerce")
        out[m] = [round(float(x), 3) if math.isfinite(x) else None for x in vals]
    return out


def record_from_run(folder: Path, book: str, grid: str, variant: str, scheme: str, seed: int,
                    config_hash: str, data: str | None) -> Record | None:
    """The record of a complete run folder (``data``: the digest of its sequence's files); ``None`` when its
    manifest has no code fingerprint (a run older than records: what code made it is not known, so it cannot be
    certified).

    Raises:
        DatasetError: the run's ``summary.json`` or ``manifest.json`` cannot be read.
        SchemaError: its ``summary.json`` is not of a schema version this mslam reads.
    """
    folder = Path(folder)
    man = read_manifest(folder)
    code = man.get("code_fingerprint")
    if not isinstance(code, str):
        return None
    flat = {k: _finite(v) for k, v in read_summary(folder).flat().items()}
    timings: JSONObject = man["timings_s"] if isinstance(man.get("timings_s"), dict) else {}
    seconds = timings.get("total_s", flat.get("timing.total_s"))
    threads = _config_threads(folder)
    return Record(book=book, grid=grid, variant=variant, sequence=folder.parent.parent.name, scheme=scheme,
                  seed=int(seed), config_hash=config_hash, data=data, code=code, commit=man.get("git_revision"),
                  cpu_kind=str(man.get("cpu_kind") or "unknown"), cpu_model=man.get("cpu_model"),
                  torch=(man.get("versions") or {}).get("torch"),
                  threads=int(threads) if isinstance(threads, (int, float)) and not isinstance(threads, bool)
                  else None,
                  seconds=float(seconds) if isinstance(seconds, (int, float)) else None,
                  created_utc=str(man.get("created_utc") or dt.datetime.now(dt.timezone.utc).isoformat()),
                  summary=flat, curves=_curves(folder))


def _config_threads(folder: Path) -> object:
    """``threads`` of the run's ``config.yaml`` (``None`` where it cannot be read)."""
    try:
        cfg = yaml.safe_load((folder / "config.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return None
    return cfg.get("threads") if isinstance(cfg, dict) else None


@dataclass(frozen=True)
class JobState:
    """A job's standing in the records: ``fresh`` (complete), ``stale`` (run again; ``why``) or ``missing``."""

    status: str
    why: str = ""
    record: Record | None = None


def job_state(root: Path, book: str, grid: str, variant: str, sequence: str, scheme: str, seed: int,
              config_hash: str, data: str | None = None) -> JobState:
    """The job's state (module docstring); ``data``: the digest of the sequence's files on this machine (``None``:
    not known here, not compared).

    Raises:
        DamagedRecord: its record is damaged or was written by hand.
    """
    path = record_path(root, book, grid, variant, sequence, scheme, seed)
    if not path.is_file():
        return JobState("missing")
    rec = read_record(path)
    if rec.config_hash != config_hash:
        return JobState("stale", f"made under config {rec.config_hash}, the grid's is now {config_hash}", rec)
    if data is not None and rec.data is not None and rec.data != data:
        return JobState("stale", f"made on other data: the files of {sequence} differ ({rec.data} → {data})", rec)
    if rec.code != code_fingerprint():
        return JobState("stale", f"made by code {rec.code}, this checkout is {code_fingerprint()}"
                        + _changed(root, rec.code), rec)
    return JobState("fresh", "", rec)


def _changed(root: Path, old: str) -> str:
    """``" (changed: a.py, b.py, …)"`` from the stored file hashes of fingerprint ``old``, when they are there."""
    try:
        was = json.loads((Path(root) / "code" / f"{old}.json").read_text())
    except (OSError, ValueError):
        return ""
    diff = changed_files(was, code_manifest()) if isinstance(was, dict) else []
    return f" (changed: {', '.join(diff[:4])}{' …' if len(diff) > 4 else ''})" if diff else ""
