"""The values the tool cannot work with, declared beside the fields they bound, and the one check of them.

Every field of a section record is declared with :func:`setting`, which puts its :class:`Range` (or
:class:`Pattern`) into the field's metadata; a record's relations between its own fields (``max_fts`` ≥
``min_tracked``, ``min_depth`` < ``max_depth``) are its class attribute ``RELATIONS``, a tuple of
:class:`Relation`. :func:`check_config` walks a record and its nested records and raises
:class:`~mutualslam_cli.errors.ConfigError` naming the first offending key, its value and what was expected
(``vo.grid_size = 2: expected an integer ≥ 4 (pixels)``). Types, finiteness and the size of integers are
:mod:`~mutualslam_cli.config.parse`'s, which runs first.

:func:`check_run` (a whole run configuration), :func:`check_vo` (the front end's section, which the front
end checks on its own too) and :func:`check_device_spec` (a device name) are the entry points.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar, overload

from mutualslam_cli.errors import ConfigError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance  # the section records import this module: they are typed as dataclasses

T = TypeVar("T")
#: The record a :class:`Relation` reads (a section record, :class:`~mutualslam_cli.config.run.RunConfig`).
R = TypeVar("R")

#: Metadata key of a field's rule.
RULE = "rule"
#: The largest integer a count, size or index may be: a C ``int``, what OpenCV and torch take.
INT_MAX = 2**31 - 1
#: Seeds: what numpy's and torch's generators accept, an unsigned 32-bit integer.
SEED_MAX = 2**32 - 1


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(x)


@dataclass(frozen=True)
class Range:
    """An interval for a number (for a list: for each element), with an optional step.

    Attributes:
        lo, hi: bounds (``None``: unbounded on that side; an integer field is bounded by :data:`INT_MAX`).
        lo_open, hi_open: the bound itself is excluded.
        multiple_of: integers only: the value is a multiple of this.
        or_zero: 0 is allowed besides the interval (``0 = all``).
        unit: shown after the expectation (``pixels``, ``0 = all``).
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    multiple_of: int | None = None
    or_zero: bool = False
    unit: str = ""

    def holds(self, v: object) -> bool:
        """Whether the number ``v`` is inside (a non-number: not this rule's business, True)."""
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return True
        if self.or_zero and v == 0:
            return True
        hi = INT_MAX if self.hi is None and isinstance(v, int) else self.hi
        return not ((isinstance(v, float) and not math.isfinite(v))
                    or (self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo))
                    or (hi is not None and (v >= hi if self.hi_open else v > hi))
                    or bool(self.multiple_of and v % self.multiple_of))

    def expected(self, v: float) -> str:
        """What the rule asks of ``v``, in words: ``an integer ≥ 4 (pixels)``, ``a number in (0, 1]``."""
        integer = isinstance(v, int) and not isinstance(v, bool)
        if integer and self.hi is None and v > INT_MAX:
            return f"an integer ≤ {INT_MAX} (a 32-bit count)"
        what = (f"a multiple of {self.multiple_of}" if self.multiple_of else "an integer" if integer
                else "a number" if math.isfinite(v) else "a finite number")
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            text = f"{what} in {'(' if self.lo_open else '['}{_num(lo)}, {_num(hi)}{')' if self.hi_open else ']'}"
        elif lo is not None:
            text = f"{what} {'>' if self.lo_open else '≥'} {_num(lo)}"
        elif hi is not None:
            text = f"{what} {'<' if self.hi_open else '≤'} {_num(hi)}"
        else:
            text = what
        if self.or_zero:
            text = f"0 or {text}"
        return text + (f" ({self.unit})" if self.unit else "")


@dataclass(frozen=True)
class Pattern:
    """A string that matches ``regex`` (the whole string), ``expected`` in words."""

    regex: str
    expected_text: str

    def holds(self, v: object) -> bool:
        return not isinstance(v, str) or re.fullmatch(self.regex, v) is not None

    def expected(self, v: object) -> str:
        return self.expected_text


@dataclass(frozen=True)
class Relation(Generic[R]):
    """A rule between fields of one record of type ``R``: ``holds(record)``; the message names ``key`` (dotted,
    from the record) and ``expected(record)``."""

    key: str
    holds: Callable[[R], bool]
    expected: Callable[[R], str]


@overload
def setting(default: T, rule: Range | Pattern | None = None) -> T: ...
@overload
def setting(*, rule: Range | Pattern | None = None, factory: Callable[[], T]) -> T: ...
def setting(default: object = dataclasses.MISSING, rule: Range | Pattern | None = None, *,
            factory: Callable[[], object] | None = None) -> Any:
    """A dataclass field with its rule: ``grid_size: int = setting(20, at_least(4, "pixels"))``.

    Typed as the field's value (``T``), as :func:`dataclasses.field` is, so that the annotation of the field
    is checked against its default; what it returns is the :class:`dataclasses.Field` (hence ``Any``).
    """
    meta = {RULE: rule} if rule is not None else {}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def at_least(lo: float, unit: str = "") -> Range:
    """``≥ lo``."""
    return Range(lo=lo, unit=unit)


def above(lo: float, unit: str = "") -> Range:
    """``> lo`` (``above(0)``: positive, a rate, a threshold, a size)."""
    return Range(lo=lo, lo_open=True, unit=unit)


def between(lo: float, hi: float, unit: str = "", hi_open: bool = False, lo_open: bool = False) -> Range:
    """``[lo, hi]`` (either end open on request)."""
    return Range(lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open, unit=unit)


#: Every seed: 0 … 2³² − 1.
SEED = between(0, SEED_MAX)
#: A fraction, a weight balance: [0, 1].
FRACTION = between(0, 1)
#: Anything of a string field that must not be empty.
NOT_EMPTY = Pattern(r"(?s).+", "a non-empty string")

#: The values of ``device`` (:mod:`~mutualslam_cli.device`).
DEVICE_PATTERN = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")
DEVICE = Pattern(DEVICE_PATTERN.pattern[1:-1], "one of auto, cpu, cuda, cuda:N")


def _value_text(v: object) -> str:
    return _num(v) if isinstance(v, int) and not isinstance(v, bool) else repr(v)


def _dotted(record: object, key: str) -> object:
    for part in key.split("."):
        record = getattr(record, part)
    return record


@functools.cache
def _choices(cls: type) -> dict[str, tuple[object, ...]]:
    """Field name → the values its ``Literal`` annotation allows (alone or beside another type)."""
    out = {}
    for name, tp in typing.get_type_hints(cls).items():
        origin = typing.get_origin(tp)
        args = [tp] if origin is Literal else typing.get_args(tp) if origin in (typing.Union, types.UnionType) else []
        literal = [a for a in args if typing.get_origin(a) is Literal]
        if literal and len(literal) == len(args):
            out[name] = tuple(v for a in literal for v in typing.get_args(a))
    return out


def check_config(record: DataclassInstance, where: str = "") -> None:
    """Raise :class:`ConfigError` naming the first value of the dataclass ``record`` (nested records
    included) outside its field's rule, its ``Literal`` choices (a record built in code, not read by
    :mod:`~mutualslam_cli.config.parse`) or breaking one of the record's ``RELATIONS``.

    Args:
        where: the record's dotted key (``vo``), prefixed to every key named.
    """
    pre = f"{where}." if where else ""
    for f in dataclasses.fields(record):
        value = getattr(record, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):  # a nested record (never a class)
            check_config(value, pre + f.name)
            continue
        cls: type = type(record)
        choices = _choices(cls).get(f.name)
        if choices is not None and value not in choices:
            raise ConfigError(f"{pre}{f.name} = {value!r}: expected one of {list(choices)}")
        rule = f.metadata.get(RULE)
        if rule is None:
            continue
        for i, v in enumerate(value) if isinstance(value, list) else [(None, value)]:
            if not rule.holds(v):
                key = pre + f.name + (f"[{i}]" if i is not None else "")
                raise ConfigError(f"{key} = {_value_text(v)}: expected {rule.expected(v)}")
    for rel in getattr(type(record), "RELATIONS", ()):
        if not rel.holds(record):
            raise ConfigError(f"{pre}{rel.key} = {_value_text(_dotted(record, rel.key))}: "
                              f"expected {rel.expected(record)}")


def check_device_spec(spec: object) -> None:
    """Raise :class:`ConfigError` unless ``spec`` is ``auto``, ``cpu``, ``cuda`` or ``cuda:N``."""
    if not isinstance(spec, str) or not DEVICE_PATTERN.match(spec):
        raise ConfigError(f"device = {spec!r}: expected {DEVICE.expected_text}")


def check_vo(cfg: DataclassInstance) -> None:
    """Raise :class:`ConfigError` for options of a ``VOConfig`` the front end cannot work with."""
    check_config(cfg, "vo")


def check_run(cfg: DataclassInstance) -> None:
    """Raise :class:`ConfigError` naming the first value of a ``RunConfig`` the tool cannot work with."""
    check_config(cfg)
