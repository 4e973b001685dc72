"""Paired comparisons of two variants run on the same sequences and seeds, and the verdict rule the book uses.

A comparison has two *arms* (:class:`Arm`): which runs (a selector over the collected runs: the scheme, config
keys) and which ``summary.json`` key. Runs of the two arms are paired by sequence and seed — and by every other
setting in which they agree, so that ``replay+ewc vs replay`` over a results root holding two configs pairs within
each config; two keys of the same runs (``@depth.pcd.lsq.adapted vs @depth.pcd.lsq.pretrained``) pair run with
itself (:func:`pair_runs`). :func:`paired_stats` then gives the paired differences ``a − b``: wins (``a`` better,
by the key's direction) / ties / losses out of N, mean ± std of the difference, the exact two-sided sign test and
a seeded paired bootstrap CI of the mean difference, and a verdict on the claim "``a`` is better than ``b``":

- **holds**: N ≥ :data:`MIN_PAIRS`, the sign test's p < :data:`ALPHA` with more wins than losses, and the 95 % CI
  of the mean difference excludes 0 on ``a``'s better side;
- **does not hold**: N ≥ :data:`MIN_PAIRS` and the CI excludes 0 on the other side (the effect is reliably the
  other way);
- **undecided**: anything else — among it every comparison of fewer than :data:`MIN_PAIRS` pairs, where the sign
  test cannot reach p < 0.05 even with every pair a win.

Pairs are samples only when they are different runs: per sequence, pairs whose two values are both identical to
another pair's (a scheme without replay gives the same numbers for every seed: ``b`` and ``a`` alike) count once
(``collapsed``). With ``broadcast``, a sequence where one arm ran a single seed pairs it with every seed of the
other (for a scheme that gives the same figures for every seed, declared by the caller; said in the result).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np
import pandas as pd

from mutualslam_cli.errors import ConfigError
from mutualslam_cli.report.columns import numeric
from mutualslam_cli.report.runs import config_labels
from mutualslam_cli.types import Scalar

#: The verdict rule (module docstring): the sign test's level, the fewest pairs for any verdict, the CI.
ALPHA = 0.05
MIN_PAIRS = 6
CONFIDENCE = 0.95
#: Paired bootstrap resamples, and the seed of their draws (one seed, one CI).
RESAMPLES = 10_000
BOOTSTRAP_SEED = 0

HOLDS, DOES_NOT_HOLD, UNDECIDED = "holds", "does not hold", "undecided"
#: Parts of a summary key whose values are better when lower (errors, times); any other key: higher.
LOWER_IS_BETTER = ("trajectory.", "ate", "esi", "rmse", "error", "_ms", "_s.", "timing.", "accuracy_m",
                   "completeness_m")


def better_of(key: str) -> str:
    """``"lower"`` for errors and times (:data:`LOWER_IS_BETTER`), else ``"higher"``."""
    k = key.lower() + "."
    return "lower" if any(p in k for p in LOWER_IS_BETTER) else "higher"


@dataclass(frozen=True)
class Arm:
    """One side of a comparison: the runs ``select`` picks (``{"scheme": "replay", "ba.final": "always"}``;
    ``scheme`` is the run's scheme, anything else a config key compared as text) and the summary ``key``."""

    select: tuple[tuple[str, str], ...]
    key: str

    @property
    def label(self) -> str:
        sel = ", ".join(v if k == "scheme" else f"{k}={v}" for k, v in self.select)
        return f"{sel or 'all runs'} @ {self.key}"


def parse_arm(text: str, default_key: str) -> Arm:
    """``"replay+ewc"``, ``"scheme=replay,ba.final=always"``, ``"replay@trajectory.credit.ba"`` or ``"@KEY"``.

    Raises:
        ConfigError: an empty key or a selector part that is neither a scheme name nor ``key=value``.
    """
    sel_text, _, key = text.strip().partition("@")
    key = key.strip() or default_key
    if not key:
        raise ConfigError(f"--pair side {text!r}: names no summary key (e.g. replay@depth.pcd.lsq.adapted)")
    select = []
    for part in (p.strip() for p in sel_text.split(",") if p.strip()):
        k, eq, v = part.partition("=")
        if not eq:
            k, v = "scheme", part
        if not k.strip() or not v.strip():
            raise ConfigError(f"--pair side {text!r}: {part!r} is neither a scheme name nor key=value")
        select.append((k.strip(), v.strip()))
    return Arm(tuple(select), key)


def parse_pair(text: str, default_key: str) -> tuple[Arm, Arm]:
    """``"A vs B"`` → two arms (:func:`parse_arm`).

    Raises:
        ConfigError: not of the form ``A vs B``, or a side :func:`parse_arm` refuses.
    """
    a, sep, b = text.partition(" vs ")
    if not sep:
        raise ConfigError(f"--pair {text!r}: expected 'A vs B', e.g. 'replay+ewc vs replay' or "
                          "'@depth.pcd.lsq.adapted vs @depth.pcd.lsq.pretrained'")
    return parse_arm(a, default_key), parse_arm(b, default_key)


def _column(runs: pd.DataFrame, key: str) -> pd.Series:
    col = "scheme" if key == "scheme" else f"config.{key}"
    if col not in runs:
        return pd.Series("", index=runs.index)
    return runs[col].map(lambda v: "" if v is None or (isinstance(v, float) and v != v) else str(v))


def select_runs(runs: pd.DataFrame, arm: Arm) -> pd.DataFrame:
    """The runs of ``arm``: every selector part matches (a boolean config value matches ``true``/``True``)."""
    mask = pd.Series(True, index=runs.index)
    for k, v in arm.select:
        col = _column(runs, k)
        mask &= (col == v) | (col.str.lower() == v.lower())
    return runs[mask]


def _seed(runs: pd.DataFrame) -> pd.Series:
    return runs["seed"].fillna(runs["folder"]) if "seed" in runs else runs["folder"]


def pair_runs(runs: pd.DataFrame, a: Arm, b: Arm, broadcast: bool = False) -> pd.DataFrame:
    """The pairs of ``a`` and ``b`` over ``runs`` (module docstring): one row per (sequence, seed, rest) with
    ``a``, ``b``, ``diff = a − b``, the two folders and ``broadcast`` (b's or a's single seed stood for this one);
    pairs where either value is missing are left out."""
    keys = tuple(sorted({k for k, _ in a.select + b.select} - {"scheme"}))
    rest = config_labels(runs, exclude=keys) if any(c.startswith("config.") for c in runs) else \
        pd.Series("", index=runs.index)
    runs = runs.assign(_rest=rest.values, _seed=_seed(runs).values)

    def side(arm: Arm, name: str) -> pd.DataFrame:
        r = select_runs(runs, arm)
        return pd.DataFrame({"sequence": r["sequence.name"].astype(str), "seed": r["_seed"], "rest": r["_rest"],
                             name: numeric(r, arm.key), f"folder_{name}": r["folder"]})

    return pair_values(side(a, "a"), side(b, "b"), broadcast)


def pair_values(left: pd.DataFrame, right: pd.DataFrame, broadcast: bool = False) -> pd.DataFrame:
    """Pairs of two arms' values: ``left`` (columns ``sequence``, ``seed``, ``rest``, ``a``, ``folder_a``) and
    ``right`` (… ``b``, ``folder_b``) matched on sequence, seed and rest; with ``broadcast``, an arm's only seed on a
    sequence stands for each seed of the other there. Pairs with a missing value are left out; ``diff = a − b``."""
    on = ["sequence", "seed", "rest"]
    pairs = left.merge(right, on=on, how="inner")
    pairs["broadcast"] = False
    if broadcast:
        extra = []
        for (seq, rest_), ls in left.groupby(["sequence", "rest"]):
            rs = right[(right["sequence"] == seq) & (right["rest"] == rest_)]
            if len(rs) == 1 and len(ls) > 1:  # b ran one seed: it stands for every seed of a
                extra.append(ls.assign(b=rs["b"].iloc[0], folder_b=rs["folder_b"].iloc[0]))
            elif len(ls) == 1 and len(rs) > 1:
                extra.append(rs.assign(a=ls["a"].iloc[0], folder_a=ls["folder_a"].iloc[0]))
        if extra:
            more = pd.concat(extra, ignore_index=True).assign(broadcast=True)
            pairs = pd.concat([pairs, more], ignore_index=True).drop_duplicates(subset=on, keep="first")
    pairs = pairs.dropna(subset=["a", "b"])
    pairs["diff"] = pairs["a"] - pairs["b"]
    return pairs.sort_values(on).reset_index(drop=True)


def sign_test(wins: int, losses: int) -> float:
    """Exact two-sided sign test (binomial, p = ½) of ``wins`` against ``losses`` (ties left out); 1.0 for none."""
    n = wins + losses
    if n == 0:
        return 1.0
    k = min(wins, losses)
    return min(1.0, 2.0 * sum(math.comb(n, i) for i in range(k + 1)) / 2.0 ** n)


def bootstrap_ci(d: np.ndarray, seed: int = BOOTSTRAP_SEED, resamples: int = RESAMPLES,
                 confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Percentile CI of the mean of ``d`` by the paired bootstrap (pairs resampled with replacement, seeded);
    NaNs for fewer than 2 pairs."""
    d = np.asarray(d, dtype=float)
    if len(d) < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, len(d), size=(resamples, len(d)))].mean(axis=1)
    tail = 100.0 * (1.0 - confidence) / 2.0
    lo, hi = np.percentile(means, [tail, 100.0 - tail])
    return float(lo), float(hi)


class PairedDict(TypedDict):
    """:meth:`PairedResult.as_dict`: the statistics as plain values (``None`` for a number that is not finite;
    ``ci95``: ``[low, high]``), the rule, and every pair as a record (``sequence``, ``seed``, ``a``, ``b``,
    ``diff``, the folders, ``broadcast``)."""

    a: str
    b: str
    better: str
    n: int
    wins: int
    ties: int
    losses: int
    mean_diff: float | None
    std_diff: float | None
    sign_p: float | None
    ci95: list[float | None]
    verdict: str
    collapsed: int
    broadcast: int
    rule: str
    pairs: list[dict[str, Scalar]]


@dataclass
class PairedResult:
    """The statistics of one comparison (module docstring); ``diff`` = a − b in the key's unit."""

    a: str
    b: str
    better: str
    n: int
    wins: int
    ties: int
    losses: int
    mean: float
    std: float
    sign_p: float
    ci: tuple[float, float]
    verdict: str
    collapsed: int = 0
    broadcast: int = 0
    pairs: pd.DataFrame = field(default_factory=pd.DataFrame, repr=False)

    def as_dict(self) -> PairedDict:
        """Plain values for JSON (the pairs as records)."""
        return {"a": self.a, "b": self.b, "better": self.better, "n": self.n, "wins": self.wins, "ties": self.ties,
                "losses": self.losses, "mean_diff": _f(self.mean), "std_diff": _f(self.std),
                "sign_p": _f(self.sign_p), "ci95": [_f(self.ci[0]), _f(self.ci[1])], "verdict": self.verdict,
                "collapsed": self.collapsed, "broadcast": self.broadcast,
                "rule": RULE, "pairs": [{k: _plain(v) for k, v in r.items()} for r in self.pairs.to_dict("records")]}


#: The verdict rule in one line (written beside every verdict).
RULE = (f"holds: N ≥ {MIN_PAIRS}, sign test p < {ALPHA} (more wins) and the {int(CONFIDENCE * 100)} % paired-bootstrap "
        f"CI of the mean difference excludes 0 on the claimed side; does not hold: N ≥ {MIN_PAIRS} and the CI "
        "excludes 0 on the other side; else undecided")


def _f(v: float) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


def _plain(v: Scalar | np.floating | np.integer | np.bool_) -> Scalar:
    """A cell of a pair's record as a JSON value (numpy scalars as Python's; NaN as ``None``)."""
    if isinstance(v, (np.floating, float)):
        return _f(float(v))
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def _collapse(pairs: pd.DataFrame) -> tuple[pd.DataFrame, int]:
    """Per sequence, pairs whose (a, b) repeat another pair's exactly count once; the number left out."""
    if pairs.empty:
        return pairs, 0
    keep = ~pairs.duplicated(subset=["sequence", "a", "b"], keep="first")
    return pairs[keep], int((~keep).sum())


def verdict(n: int, wins: int, losses: int, p: float, ci: tuple[float, float], better: str) -> str:
    """The verdict rule (module docstring) on the claim "a is better than b"."""
    if n < MIN_PAIRS or not all(np.isfinite(ci)):
        return UNDECIDED
    lo, hi = ci if better == "higher" else (-ci[1], -ci[0])  # oriented: > 0 is a's better side
    if p < ALPHA and wins > losses and lo > 0:
        return HOLDS
    if hi < 0:
        return DOES_NOT_HOLD
    return UNDECIDED


def paired_stats(pairs: pd.DataFrame, better: str, a: str = "a", b: str = "b",
                 seed: int = BOOTSTRAP_SEED) -> PairedResult:
    """Statistics and verdict of ``pairs`` (:func:`pair_runs`; columns ``sequence``, ``a``, ``b``, ``diff``).

    Raises:
        ConfigError: ``better`` is neither ``higher`` nor ``lower``.
    """
    if better not in ("higher", "lower"):
        raise ConfigError(f"better {better!r}: expected higher or lower")
    used, collapsed = _collapse(pairs)
    d = used["diff"].to_numpy(dtype=float) if len(used) else np.zeros(0)
    sign = 1.0 if better == "higher" else -1.0
    wins, losses = int((sign * d > 0).sum()), int((sign * d < 0).sum())
    ties = int(len(d) - wins - losses)
    p = sign_test(wins, losses)
    ci = bootstrap_ci(d, seed)
    mean = float(d.mean()) if len(d) else float("nan")
    std = float(d.std(ddof=1)) if len(d) > 1 else float("nan")
    n_broadcast = int(used["broadcast"].sum()) if "broadcast" in used else 0
    return PairedResult(a, b, better, len(d), wins, ties, losses, mean, std, p, ci,
                        verdict(len(d), wins, losses, p, ci, better), collapsed, n_broadcast, used)


def per_sequence(result: PairedResult) -> pd.DataFrame:
    """One row per sequence (N, wins / ties / losses, mean ± std of a − b) and an ``all`` row with the test."""
    rows = []
    sign = 1.0 if result.better == "higher" else -1.0
    for seq, g in result.pairs.groupby("sequence", sort=True):
        d = g["diff"].to_numpy(dtype=float)
        rows.append({"sequence": seq, "N": len(d), "wins / ties / losses":
                     f"{int((sign * d > 0).sum())} / {int((d == 0).sum())} / {int((sign * d < 0).sum())}",
                     "mean a − b": float(d.mean()), "std a − b": float(d.std(ddof=1)) if len(d) > 1 else float("nan"),
                     "sign p": float("nan"), "95 % CI": "", "verdict": ""})
    lo, hi = result.ci
    rows.append({"sequence": "all", "N": result.n,
                 "wins / ties / losses": f"{result.wins} / {result.ties} / {result.losses}",
                 "mean a − b": result.mean, "std a − b": result.std, "sign p": result.sign_p,
                 "95 % CI": "—" if not np.isfinite(lo) else f"[{lo:.4g}, {hi:.4g}]", "verdict": result.verdict})
    return pd.DataFrame(rows)


def paired_table(runs: pd.DataFrame, comparisons: list[tuple[Arm, Arm]], better: str | None = None,
                 broadcast: bool = False) -> tuple[pd.DataFrame, pd.DataFrame, list[PairedResult]]:
    """``mslam report --pair``: per comparison its :func:`per_sequence` rows (a ``comparison`` column first),
    every pair (CSV), and the results.

    Raises:
        ConfigError: a comparison with no pair (no run of an arm, or none on a common sequence and seed).
    """
    shown, every, results = [], [], []
    for a, b in comparisons:
        pairs = pair_runs(runs, a, b, broadcast)
        if pairs.empty:
            raise ConfigError(f"--pair '{a.label} vs {b.label}': no pair of runs (same sequence and seed, both values "
                              f"present); runs of a: {len(select_runs(runs, a))}, of b: {len(select_runs(runs, b))}")
        res = paired_stats(pairs, better or better_of(a.key), a.label, b.label)
        results.append(res)
        name = f"{a.label} vs {b.label} ({res.better} is better)"
        shown.append(per_sequence(res).assign(comparison=name))
        every.append(res.pairs.assign(comparison=name))
    table = pd.concat(shown, ignore_index=True)
    table = table[["comparison", *[c for c in table.columns if c != "comparison"]]]
    return table, pd.concat(every, ignore_index=True), results
