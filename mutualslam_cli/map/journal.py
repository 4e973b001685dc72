"""The front end as a stream of events in frame order (DESIGN §5, the online rule).

Everything the front end does to its map and frame records is an :class:`Event` stamped with the
frame it was processing when it happened (the front end's clock): a keyframe created, points
promoted from converged seeds, a keyframe's observations, a windowed BA's new poses and depths,
rejected observations, a frame tracked, tracking lost, relocalised, a segment started — and the
changes the network's side makes: a segment joined to the map before it (a bridge, a similarity),
a global BA's refinement (poses, depths, host pixels, removed points).

:class:`~mutualslam_cli.map.state.MapState` applies events; the front end's own state and a
replica built from the same events are therefore identical at every frame, which is what lets the
adaptation loop see the map *as it stood* at any time, and what the per-sequence cache stores
(:func:`journal_to_arrays`, read back without pickle by :func:`journal_from_arrays`).

Each kind has a fixed schema (:data:`SCHEMA`): scalar fields (one number per event) and array
fields (any length along the first axis). Text fields (a segment's initialisation method, why
tracking was lost) go into the JSON header.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, TypeAlias

import numpy as np

FieldSpec: TypeAlias = Literal["i", "f", "s"] | tuple[int, ...]
"""How one field of an event is stored: ``"i"`` (int scalar), ``"f"`` (float scalar), ``"s"`` (text) or the
trailing shape of an array field (``()`` for a 1-D array, ``(2,)`` for ``(n, 2)``, ``(4, 4)`` for ``(n, 4, 4)``…)."""
EventValue: TypeAlias = int | float | str | np.ndarray
"""One field's value in :attr:`Event.data`, as its :data:`FieldSpec` says (int64/float64 arrays)."""

#: Kind → field → its :data:`FieldSpec`.
SCHEMA: dict[str, dict[str, FieldSpec]] = {
    # the map (map.store.Map)
    "keyframe": {"kf": "i", "frame": "i", "t": "f", "segment": "i", "T_wc": (4, 4)},
    "pose": {"kfs": (), "T_wc": (4, 4)},
    "points": {"first": "i", "host": (), "px_h": (2,), "xn_h": (2,), "rho": (), "sigma": (), "obs_n": (),
               "obs_kf": (), "obs_px": (2,)},
    "observe": {"kf": "i", "pids": (), "px": (2,)},
    "depth": {"pids": (), "rho": ()},
    "unobserve": {"pids": (), "kfs": ()},
    "refresh": {"pids": ()},
    "remove": {"pids": ()},
    "pixel": {"pids": (), "px_h": (2,), "xn_h": (2,)},
    # a similarity x ↦ s·R·x + t applied to one segment, joining it to segment ``onto`` (a bridge)
    "similarity": {"segment": "i", "onto": "i", "s": "f", "R": (3,), "t": ()},
    # the frames tracked from keyframes ``kfs``: their translation from it × ``scales`` (a Sim(3) correction)
    "rescale": {"kfs": (), "scales": ()},
    # the frame records
    "frame": {"index": "i", "segment": "i", "ref": "i", "T_rel": (4, 4)},
    "segment": {"segment": "i", "index": "i", "method": "s"},
    "lost": {"index": "i", "reason": "s", "why": "s"},
    "reloc": {"index": "i", "t": "f", "keyframe": "i", "inliers": "i", "frames_lost": "i", "candidates_tried": "i"},
}
KINDS = tuple(SCHEMA)
_INT = {"kfs", "pids", "host", "obs_n", "obs_kf"}


@dataclass
class Event:
    """One change, at the front end's frame ``frame`` (its clock; -1 before the first frame).

    Attributes:
        kind: a key of :data:`SCHEMA`.
        frame: the frame being processed when it happened.
        data: the fields of the kind's schema (numbers, strings, arrays).
    """

    kind: str
    frame: int
    data: dict[str, EventValue] = field(default_factory=dict)

    def __getitem__(self, key: str) -> Any:
        """The field ``key`` (:attr:`data`), typed ``Any``: which of :data:`EventValue` it is depends on the kind,
        which the caller has dispatched on (``e["kf"]`` of a ``keyframe`` is an int, ``e["pids"]`` an array)."""
        return self.data[key]

    def same(self, other: Event) -> bool:
        """Equal kind, frame and data, arrays compared exactly (NaN equal to NaN)."""
        if self.kind != other.kind or self.frame != other.frame or self.data.keys() != other.data.keys():
            return False
        for k, v in self.data.items():
            w = other.data[k]
            if isinstance(v, np.ndarray) or isinstance(w, np.ndarray):
                if not np.array_equal(np.asarray(v), np.asarray(w), equal_nan=np.asarray(v).dtype.kind == "f"):
                    return False
            elif v != w and not (isinstance(v, float) and np.isnan(v) and np.isnan(w)):
                return False
        return True


class Journal:
    """Events in the order they happened; :attr:`frame` is the clock the front end sets per frame.

    Attributes:
        events: every event so far.
        frame: the frame being processed (stamped on each new event).
    """

    def __init__(self) -> None:
        self.events: list[Event] = []
        self.frame = -1

    def emit(self, kind: str, **data: Any) -> None:
        """Record one event of ``kind`` at the current frame (arrays are copied); ``data``: its fields as the
        caller has them (numbers, array-likes), converted here by the kind's schema."""
        schema = SCHEMA[kind]
        out: dict[str, EventValue] = {}
        for k, spec in schema.items():
            v = data[k]
            if spec == "i":
                out[k] = int(v)
            elif spec == "f":
                out[k] = float(v)
            elif spec == "s":
                out[k] = str(v)
            else:
                dtype = np.int64 if k in _INT else np.float64
                out[k] = np.array(v, dtype=dtype).reshape(-1, *spec)
        self.events.append(Event(kind, self.frame, out))

    def __len__(self) -> int:
        return len(self.events)

    @property
    def nbytes(self) -> int:
        """Bytes held by the events' arrays (the journal's payload)."""
        return sum(v.nbytes for e in self.events for v in e.data.values() if isinstance(v, np.ndarray))


# ----------------------------------------------------------------------------- plain arrays (the cache)

#: Version of the :func:`journal_to_arrays` layout.
JOURNAL_VERSION = 3
_FORMAT = "mslam-vo-journal"


def journal_to_arrays(events: list[Event], prefix: str = "ev") -> dict[str, np.ndarray]:
    """``events`` as flat numeric arrays (for ``np.savez``; no object arrays).

    Layout: ``{prefix}.kind`` ``(E,)`` int8 (index into :data:`KINDS`), ``{prefix}.frame`` ``(E,)`` int64;
    per kind ``k`` with ``n_k`` events: scalar field ``f`` as ``{prefix}.k.f`` ``(n_k,)``, array field as
    ``{prefix}.k.f`` (concatenated) with ``{prefix}.k.f.off`` ``(n_k + 1,)``; text fields as a uint8 JSON
    list ``{prefix}.text`` (one dict per event that has text, in event order).
    """
    out: dict[str, np.ndarray] = {
        f"{prefix}.kind": np.array([KINDS.index(e.kind) for e in events], np.int8),
        f"{prefix}.frame": np.array([e.frame for e in events], np.int64),
    }
    texts: list[dict[str, str]] = []
    for kind, schema in SCHEMA.items():
        evs = [e for e in events if e.kind == kind]
        for f, spec in schema.items():
            key = f"{prefix}.{kind}.{f}"
            if spec == "s":
                continue
            if spec in ("i", "f"):
                out[key] = np.array([e.data[f] for e in evs], np.int64 if spec == "i" else np.float64)
                continue
            parts: list[np.ndarray] = [e[f] for e in evs]
            dtype = np.int64 if f in _INT else np.float64
            out[key] = np.concatenate(parts).astype(dtype) if parts else np.zeros((0, *spec), dtype)
            off = np.zeros(len(parts) + 1, np.int64)
            off[1:] = np.cumsum([len(p) for p in parts])
            out[key + ".off"] = off
    for e in events:
        text: dict[str, str] = {f: e[f] for f, spec in SCHEMA[e.kind].items() if spec == "s"}
        if text:
            texts.append(text)
    out[f"{prefix}.text"] = np.frombuffer(json.dumps(texts).encode("utf-8"), np.uint8)
    return out


def journal_from_arrays(a: Mapping[str, np.ndarray], prefix: str = "ev") -> list[Event]:
    """Inverse of :func:`journal_to_arrays` (``a``: that dict or an open ``np.load`` archive).

    Raises:
        ValueError: arrays whose sizes disagree with the event list.
        KeyError: a missing array.
    """
    kinds = np.asarray(a[f"{prefix}.kind"])
    frames = np.asarray(a[f"{prefix}.frame"])
    if kinds.shape != frames.shape or (len(kinds) and (kinds.min() < 0 or kinds.max() >= len(KINDS))):
        raise ValueError("invalid journal: event kinds and frames disagree")
    texts = iter(json.loads(bytes(np.asarray(a[f"{prefix}.text"], np.uint8)).decode("utf-8")))
    columns: dict[str, dict[str, np.ndarray | tuple[np.ndarray, np.ndarray]]] = {}  # (values, offsets): arrays
    counters = {k: 0 for k in KINDS}
    for kind, schema in SCHEMA.items():
        n = int(np.sum(kinds == KINDS.index(kind)))
        cols: dict[str, np.ndarray | tuple[np.ndarray, np.ndarray]] = {}
        for f, spec in schema.items():
            if spec == "s":
                continue
            key = f"{prefix}.{kind}.{f}"
            col = np.asarray(a[key])
            if spec in ("i", "f"):
                if len(col) != n:
                    raise ValueError(f"invalid journal: {key} has {len(col)} values for {n} events")
                cols[f] = col
            else:
                off = np.asarray(a[key + ".off"])
                if off.shape != (n + 1,) or off[-1] != len(col) or col.shape[1:] != tuple(spec):
                    raise ValueError(f"invalid journal: {key} does not match its offsets")
                cols[f] = (col, off)
        columns[kind] = cols
    events = []
    for code, frame in zip(kinds.tolist(), frames.tolist()):
        kind = KINDS[code]
        j = counters[kind]
        counters[kind] += 1
        data: dict[str, EventValue] = {}
        for f, spec in SCHEMA[kind].items():
            if spec == "s":
                continue
            c = columns[kind][f]
            if isinstance(c, tuple):  # an array field
                col, off = c
                data[f] = col[off[j]:off[j + 1]]
            elif spec == "i":
                data[f] = int(c[j])
            else:  # "f"
                data[f] = float(c[j])
        if any(spec == "s" for spec in SCHEMA[kind].values()):
            data.update(next(texts))
        events.append(Event(kind, int(frame), data))
    return events
