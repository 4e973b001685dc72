"""The ``summary.json`` of a run: its required keys, the builder that records a value or ``null`` with its
reason (:class:`Summary`, checked against :mod:`~mutualslam_cli.results.schema` as it is written), the typed
record it is read back as (:class:`RunSummary`, :func:`read_summary`) and the flat ``a.b.c`` view.

A value that cannot be computed is ``null`` and its reason is under ``notes`` (same dotted key),
never 0. Every stage writes its own keys (:mod:`mutualslam_cli.stages`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np

from mutualslam_cli.errors import DatasetError, SchemaError
from mutualslam_cli.results.schema import READABLE, SCHEMA_VERSION, check, field_of
from mutualslam_cli.types import JSON, JSONObject

#: Keys other tools read from ``summary.json`` (dotted paths), DESIGN §8.
SUMMARY_KEYS: tuple[str, ...] = (
    "depth.pcd.lsq.pretrained", "depth.pcd.lsq.adapted",
    "depth.pcd.median.pretrained", "depth.pcd.median.adapted",
    "depth.esi.pretrained", "depth.esi.adapted",
    "depth.pcd_nonkf.lsq.pretrained", "depth.pcd_nonkf.lsq.adapted",
    "depth.pcd_nonkf.median.pretrained", "depth.pcd_nonkf.median.adapted",
    "depth.esi_nonkf.pretrained", "depth.esi_nonkf.adapted",
    "depth.pcd.seq_lsq.pretrained", "depth.pcd.seq_lsq.adapted",
    "depth.pcd_online.lsq", "depth.pcd_online.median", "depth.pcd_online.seq_lsq",
    "adaptation.reg.shrink.mean",
    "trajectory.ate_rmse_m.vo", "trajectory.ate_rmse_m.ba", "trajectory.ate_rmse_m.all_frames",
    "trajectory.local_scale.vo.max_over_min", "trajectory.local_scale.ba.max_over_min",
    "trajectory.local_ate_m.vo", "trajectory.local_ate_m.ba",
    "vo.keyframes", "vo.tracked_fraction",
    "map.points.vo", "map.points.culled", "map.points.ba",
    "map.esi.vo", "map.esi.culled", "map.esi.ba",
    "timing.vo_fps", "timing.depth_ms", "timing.finetune_ms", "timing.ba_s", "timing.total_s",
)


def plain(x: object) -> JSON:
    """numpy scalars/arrays and Paths → JSON-safe Python values; NaN/inf → None.

    Raises:
        TypeError: a value JSON cannot hold (what ``json.dumps`` would refuse), named with its type.
    """
    if isinstance(x, dict):
        return {str(k): plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return plain(x.tolist())
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, Path):
        return str(x)
    if x is None or isinstance(x, (str, int, bool)):
        return x
    raise TypeError(f"{type(x).__name__} is not JSON serializable: {x!r}")


class Summary:
    """Builds the nested ``summary.json`` with explicit nulls and reasons.

    >>> s = Summary()
    >>> s.set("vo.keyframes", 12)
    >>> s.absent("trajectory.ate_rmse_m.ba", "global BA not run")
    >>> s.to_dict()["trajectory"]["ate_rmse_m"]["ba"] is None
    True
    """

    def __init__(self) -> None:
        self.values: dict[str, JSON] = {}  # JSON-safe (plain) as set
        self.notes: dict[str, str] = {}

    @classmethod
    def from_record(cls, record: RunSummary, drop_prefix: str | None = None) -> Summary:
        """The builder of a written ``summary.json`` (``record``), without the keys (and notes) that
        start with ``drop_prefix`` — a stage run again on a finished run rewrites its own keys."""
        s = cls()
        keep = (lambda k: not k.startswith(drop_prefix)) if drop_prefix else (lambda k: True)
        s.values = {k: v for k, v in record.values.items() if keep(k)}
        s.notes = {k: v for k, v in record.notes.items() if keep(k)}
        return s

    def set(self, key: str, value: object, reason_if_missing: str = "not computed") -> None:
        """Set a dotted key; ``None``/NaN values are recorded as absent with the reason.

        Raises:
            SchemaError: ``key`` is not in the schema, or ``value`` (made JSON-safe) is not of its kind.
        """
        if value is None or (isinstance(value, float) and not math.isfinite(value)):
            self.absent(key, reason_if_missing)
        else:
            v = plain(value)
            check(key, v, "the run's summary")
            self.values[key] = v
            self.notes.pop(key, None)

    def absent(self, key: str, reason: str) -> None:
        """Record ``key`` as ``null`` with ``reason`` under ``notes``.

        Raises:
            SchemaError: ``key`` is not in the schema.
        """
        check(key, None, "the run's summary")
        self.values[key] = None
        self.notes[key] = reason

    def number(self, key: str) -> float | None:
        """A value set so far, as a number (``None``: unset, null or not a number)."""
        v = self.values.get(key)
        return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None

    def to_dict(self, required: Iterable[str] = SUMMARY_KEYS) -> JSONObject:
        """Nested dict with ``schema_version``; required keys never set are ``null`` with reason "not computed"."""
        vals = dict(self.values)
        notes = dict(self.notes)
        for k in required:
            if k not in vals:
                vals[k] = None
                notes.setdefault(k, "not computed by this run")
        nested: JSONObject = {}
        for k, v in vals.items():
            node = nested
            parts = k.split(".")
            for p in parts[:-1]:
                child = node.setdefault(p, {})
                if not isinstance(child, dict):
                    raise SchemaError(f"the run's summary: {p!r} of {k!r} holds a value, not a group of keys")
                node = child
            node[parts[-1]] = v
        nested["notes"] = dict(sorted(notes.items()))
        nested["schema_version"] = SCHEMA_VERSION
        return nested


def flatten(d: Mapping[str, JSON], prefix: str = "") -> dict[str, JSON]:
    """Nested dict → ``{"a.b.c": value}`` (``notes`` kept as one entry)."""
    out: dict[str, JSON] = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else k
        if isinstance(v, dict) and k != "notes":
            out.update(flatten(v, key))
        else:
            out[key] = v
    return out


@dataclass(frozen=True)
class RunSummary:
    """A ``summary.json`` read back through :mod:`~mutualslam_cli.results.schema`.

    Attributes:
        version: its schema version (1: written before ``schema_version`` existed).
        values: flat dotted key → JSON value (``None``: absent, its reason in ``notes``).
        notes: dotted key → why the value is ``null``.
        source: the file it was read from (or the writer), for messages.

    The accessors :meth:`number`, :meth:`integer`, :meth:`flag` and :meth:`text` refuse a key the schema does not
    hold (:class:`SchemaError`): a reader that asks for a renamed key fails, it does not read ``None``.
    """

    version: int
    values: Mapping[str, JSON]
    notes: Mapping[str, str]
    source: str = field(default="summary.json", compare=False)

    @classmethod
    def parse(cls, data: JSON, where: str) -> RunSummary:
        """A parsed ``summary.json``; version 2 is checked key by key, version 1 (the previous schema) is read as it
        was written.

        Raises:
            SchemaError: not an object, a version this mslam does not read, or (version 2) a key or value the
                schema does not hold; the message names ``where`` and the version.
        """
        if not isinstance(data, dict):
            raise SchemaError(f"{where}: a JSON {type(data).__name__}, not an object of metrics "
                              "(the summary of mslam run)")
        version = data.get("schema_version", 1)
        if version not in READABLE or isinstance(version, bool):
            raise SchemaError(f"{where}: summary schema version {version!r}; this mslam reads versions "
                              f"{READABLE[0]}–{READABLE[-1]} (written by a newer mslam?)")
        assert isinstance(version, int)
        flat = flatten({k: v for k, v in data.items() if k != "schema_version"})
        notes = flat.pop("notes", None) or {}
        texts = {k: v for k, v in notes.items() if isinstance(v, str)} if isinstance(notes, dict) else {}
        if not isinstance(notes, dict) or len(texts) != len(notes):
            raise SchemaError(f"{where}: 'notes' is not an object of texts (summary schema version {version})")
        if version >= 2:
            for k, v in flat.items():
                check(k, v, f"{where} (version {version})")
        return cls(version, MappingProxyType(flat), MappingProxyType(texts), where)

    def get(self, key: str) -> JSON:
        """The value of a schema key, ``None`` when absent or null."""
        if field_of(key) is None:
            raise SchemaError(f"{self.source}: a reader asked for {key!r}, which is not in summary schema version "
                              f"{SCHEMA_VERSION}")
        return self.values.get(key)

    def number(self, key: str) -> float | None:
        """A finite number, or ``None`` (absent, null, not a number)."""
        v = self.get(key)
        return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None

    def integer(self, key: str) -> int | None:
        """An integer, or ``None``."""
        v = self.get(key)
        return v if isinstance(v, int) and not isinstance(v, bool) else None

    def flag(self, key: str) -> bool | None:
        """A flag, or ``None``."""
        v = self.get(key)
        return v if isinstance(v, bool) else None

    def text(self, key: str) -> str | None:
        """A text, or ``None``."""
        v = self.get(key)
        return v if isinstance(v, str) else None

    def flat(self) -> dict[str, JSON]:
        """Every value by dotted key (``notes`` left out): a table row."""
        return dict(self.values)

    def nested(self) -> JSONObject:
        """The ``summary.json`` content, as :meth:`Summary.to_dict` writes it."""
        s = Summary()
        s.values, s.notes = dict(self.values), dict(self.notes)
        out = s.to_dict(required=())
        if self.version < SCHEMA_VERSION:
            del out["schema_version"]
        return out


def read_summary(folder: Path) -> RunSummary:
    """Load ``summary.json`` of a result folder as a :class:`RunSummary`.

    Raises:
        DatasetError: missing, unreadable, not UTF-8 or not valid JSON (one line naming the file).
        SchemaError: of a schema version this mslam does not read, or not of its version's schema.
    """
    path = Path(folder) / "summary.json"
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise DatasetError(f"{path}: no summary.json (run incomplete or not a result folder)") from None
    except OSError as e:  # a folder of that name, unreadable
        raise DatasetError(f"{path}: cannot be read ({e.strerror})") from None
    except UnicodeDecodeError as e:
        raise DatasetError(f"{path}: not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start})") from None
    except ValueError as e:  # json.JSONDecodeError, and numbers too long for int()
        raise DatasetError(f"{path}: not valid JSON ({e})") from None
    return RunSummary.parse(data, str(path))
