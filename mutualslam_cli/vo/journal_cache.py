"""The per-sequence front-end cache: the event journal (DESIGN §9).

Every scheme of a grid starts from the same front end, which does not depend on the network up to
the first event that asks it (a bridge, a BA's feedback). The cache keeps that front end's
:class:`~mutualslam_cli.map.journal.Journal` from frame 0 — the whole sequence when it ran alone,
else up to the frame of its run's first such event — with resumption points
(:mod:`~mutualslam_cli.vo.checkpoint`) every :data:`CHECKPOINT_EVERY` keyframes, in
``<results>/_cache/vo/<sequence>-<mode>-<key>.journal.npz`` (key: :func:`vo_cache_key`).

The entry is data only, read back with ``allow_pickle=False``, so a results folder shared on a
cluster cannot run code in whoever reads it. An entry that cannot be read (truncated, garbage,
another layout version) is logged as a warning naming the file and recomputed; a longer journal
replaces a shorter one.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.config import RunConfig, to_dict
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.journal import JOURNAL_VERSION, Event, journal_from_arrays, journal_to_arrays
from mutualslam_cli.types import JSON
from mutualslam_cli.vo.frontend import FRONTEND_VERSION

log = logging.getLogger(__name__)

#: Version of the oracle front ends in their cache key (2: ``gt`` = pose oracle, ``gt-depth`` = depth oracle).
ORACLE_VERSION = 3
#: Keyframes between two resumption points of the front end.
CHECKPOINT_EVERY = 8
_FORMAT = "mslam-vo-cache"


def vo_cache_key(seq: Sequence, cfg: RunConfig) -> str:
    """Cache key of a front-end journal: sequence identity + front-end and data config + seed + thread count
    (OpenCV's output follows it: a journal of 2 threads is not the front end of 1)."""
    ident = {
        "root": str(Path(seq.root).resolve()), "n": len(seq),
        "first": seq.frames[0].timestamp if len(seq) else None,
        "last": seq.frames[-1].timestamp if len(seq) else None,
        "vo": {k: v for k, v in to_dict(cfg.vo).items()
               if k not in ("inject_outliers", "bridge_segments", "merge_segments")},
        "data": {"max_frames": cfg.data.max_frames, "stride": cfg.data.stride},
        "seed": cfg.seed, "threads": cfg.threads, "intr": seq.intrinsics.as_list(), "version": FRONTEND_VERSION,
        "journal": JOURNAL_VERSION,
    }
    if cfg.vo.mode != "svo":  # an oracle's result also depends on the oracles' version
        ident["oracle_version"] = ORACLE_VERSION
    return hashlib.sha1(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest()[:16]


def cache_path(cache_dir: Path, seq: Sequence, cfg: RunConfig) -> Path:
    """Where the front-end journal of ``seq`` under ``cfg`` is kept."""
    return Path(cache_dir) / f"{seq.name}-{cfg.vo.mode}-{vo_cache_key(seq, cfg)}.journal.npz"


@dataclass
class JournalEntry:
    """A cached front end.

    Attributes:
        events: the journal from frame 0.
        until: the last frame whose events are all here (``n_frames - 1`` when complete).
        n_frames: frames of the sequence.
        checkpoints: resumption points, frame → :func:`~mutualslam_cli.vo.checkpoint.capture` arrays.
        meta: the finished front end's ``VOResult.meta`` (complete entries; ``{}`` otherwise).
    """

    events: list[Event]
    until: int
    n_frames: int
    checkpoints: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return self.until >= self.n_frames - 1


def save_entry(path: Path, entry: JournalEntry) -> None:
    """Write ``entry`` to ``path`` atomically (one ``.npz``, no object arrays)."""
    header = {"format": _FORMAT, "version": JOURNAL_VERSION, "until": entry.until, "n_frames": entry.n_frames,
              "checkpoints": sorted(entry.checkpoints), "meta": entry.meta}
    arrays = journal_to_arrays(entry.events)
    arrays["header"] = np.frombuffer(json.dumps(header, default=_plain).encode("utf-8"), np.uint8)
    for frame, ck in entry.checkpoints.items():
        arrays.update({f"ck{frame}.{k}": v for k, v in ck.items()})
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:  # a file object: np.savez would append ".npz" to a name
        np.savez(f, **arrays)  # type: ignore[arg-type]  # mypy: a key of the dict could be savez's allow_pickle
        f.flush()
        os.fsync(f.fileno())


def load_entry(path: Path) -> JournalEntry | None:
    """The entry in ``path``; ``None`` when there is none or it is invalid (logged as a warning)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(bytes(np.asarray(z["header"], np.uint8)).decode("utf-8"))
            if header.get("format") != _FORMAT or header.get("version") != JOURNAL_VERSION:
                raise ValueError(f"format {header.get('format')!r} version {header.get('version')!r}")
            events = journal_from_arrays(z)
            cks = {int(f): {k.split(".", 1)[1]: np.asarray(z[k]) for k in z.files if k.startswith(f"ck{f}.")}
                   for f in header["checkpoints"]}
    except Exception as e:  # whatever is wrong with the file, the entry is recomputed
        log.warning("VO cache %s is unreadable (%s: %s); recomputing it", path, type(e).__name__, e)
        return None
    log.info("front-end journal loaded from %s (frames 0-%d of %d)", path, header["until"], header["n_frames"])
    return JournalEntry(events, int(header["until"]), int(header["n_frames"]), cks, header.get("meta") or {})


def _plain(x: object) -> JSON:
    """``json.dumps``'s ``default``: a numpy scalar or array as plain values (anything else is refused)."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"{type(x).__name__} is not JSON-like")
