"""Strict access to one mapping of a book file (:class:`Reader`): a key of the wrong type, a missing one or one
not read is one :class:`~mutualslam_cli.errors.ConfigError` naming the file and the place. :mod:`.spec` reads
``configs/book.yaml`` through it."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeGuard, TypeVar, overload

from mutualslam_cli.errors import ConfigError
from mutualslam_cli.types import JSON, JSONObject

_T = TypeVar("_T")
_D = TypeVar("_D")


def texts(v: JSON, ok: Callable[[str], bool] = bool) -> TypeGuard[list[str]]:
    """Whether ``v`` is a list of texts each ``ok`` (by default: not empty)."""
    return isinstance(v, list) and all(isinstance(x, str) and ok(x) for x in v)


class Reader:
    """One mapping of the book file (``where``: its place, e.g. ``grids.tum``), as parsed from YAML; the keys read
    are remembered, so that :meth:`done` refuses the others."""

    def __init__(self, path: Path, where: str, data: JSON) -> None:
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: {where}: expected a mapping, got {data!r}")
        self.path, self.where = path, where
        self.data: JSONObject = data
        self.used: set[str] = set()

    def fail(self, msg: str) -> ConfigError:
        return ConfigError(f"{self.path}: {self.where}: {msg}")

    @overload
    def get(self, key: str, kind: type[list[JSON]]) -> list[JSON]: ...
    @overload
    def get(self, key: str, kind: type[list[JSON]], default: list[JSON]) -> list[JSON]: ...
    @overload
    def get(self, key: str, kind: type[JSONObject]) -> JSONObject: ...
    @overload
    def get(self, key: str, kind: type[JSONObject], default: JSONObject) -> JSONObject: ...
    @overload
    def get(self, key: str, kind: tuple[type[int], type[float]], default: float) -> float: ...
    @overload
    def get(self, key: str, kind: type[_T]) -> _T: ...
    @overload
    def get(self, key: str, kind: type[_T], default: _D) -> _T | _D: ...

    def get(self, key: str, kind: type | tuple[type, ...], default: object = ...) -> object:
        """The value of ``key`` if it is a ``kind`` (a bool only where ``kind`` names ``bool``), else ``default``
        when the key is absent and a default is given.

        Raises:
            ConfigError: the key is absent without a default, or its value is not a ``kind``.
        """
        self.used.add(key)
        if key not in self.data:
            if default is ...:
                raise self.fail(f"'{key}' is missing")
            return default
        v = self.data[key]
        if not isinstance(v, kind) or (isinstance(v, bool) and bool not in (kind if isinstance(kind, tuple)
                                                                                else (kind,))):
            raise self.fail(f"'{key}' = {v!r}: expected {getattr(kind, '__name__', kind)}")
        return v

    def done(self) -> None:
        """Refuse the keys not read (:meth:`get`, or marked in :attr:`used`)."""
        extra = sorted(set(self.data) - self.used)
        if extra:
            raise self.fail(f"unknown key(s) {', '.join(map(str, extra))}")


def names(r: Reader, key: str, default: Sequence[JSON] | None = None) -> tuple[str, ...]:
    """A list of names (non-empty texts) under ``key`` (``default`` when absent; ``None``: required).

    Raises:
        ConfigError: absent without a default, or not a list of names.
    """
    v = r.get(key, list) if default is None else r.get(key, list, list(default))
    if not texts(v):
        raise r.fail(f"'{key}': expected a list of names, got {v!r}")
    return tuple(v)
