"""The paper's findings judged on the book's runs (:func:`judge`): each comparison of a finding paired by sequence
and seed and judged by :mod:`mutualslam_cli.report.paired`'s rule; a finding **holds** when every comparison
holds, **does not hold** when any does not, else it is **undecided**."""

from __future__ import annotations

import pandas as pd

from mutualslam_cli.book.build import arm_runs
from mutualslam_cli.book.entries import ArmEntry, ComparisonEntry, FindingEntry
from mutualslam_cli.book.spec import ArmSpec, BookSpec, FindingSpec
from mutualslam_cli.report.columns import numeric
from mutualslam_cli.report.paired import DOES_NOT_HOLD, HOLDS, RULE, UNDECIDED, pair_values, paired_stats


def _side(runs: pd.DataFrame, arm: ArmSpec, name: str) -> pd.DataFrame:
    r = arm_runs(runs, arm.grid, arm.variant, arm.scheme)
    if r.empty:
        return pd.DataFrame(columns=["sequence", "seed", "rest", name, f"folder_{name}"])
    return pd.DataFrame({"sequence": r["sequence.name"].astype(str), "seed": r["seed"], "rest": "",
                         name: numeric(r, arm.key), f"folder_{name}": r["book.run"]})


def overall(verdicts: list[str]) -> str:
    """A finding's verdict from its comparisons' (module docstring)."""
    if verdicts and all(v == HOLDS for v in verdicts):
        return HOLDS
    if DOES_NOT_HOLD in verdicts:
        return DOES_NOT_HOLD
    return UNDECIDED


def _arm(a: ArmSpec) -> ArmEntry:
    return {"grid": a.grid, "variant": a.variant, "scheme": a.scheme, "key": a.key}


def judge_one(f: FindingSpec, runs: pd.DataFrame) -> FindingEntry:
    """One finding: its comparisons' statistics (every pair with its two runs) and the overall verdict."""
    comps: list[ComparisonEntry] = []
    for c in f.comparisons:
        pairs = pair_values(_side(runs, c.a, "a"), _side(runs, c.b, "b"), c.broadcast)
        res = paired_stats(pairs, c.better, c.a.label, c.b.label)
        used = pd.concat([arm_runs(runs, x.grid, x.variant, x.scheme) for x in (c.a, c.b)])
        comps.append({**res.as_dict(), "arms": {"a": _arm(c.a), "b": _arm(c.b)},
                      "commits": sorted({str(v) for v in used.get("book.commit", []) if v}),
                      "devices": sorted({str(v) for v in used.get("run.device_label", []) if v == v and v})})
    return {"claim": f.claim, "paper": f.paper, "verdict": overall([c["verdict"] for c in comps]),
            "comparisons": comps, "rule": RULE}


def judge(spec: BookSpec, runs: pd.DataFrame, only_grids: set[str]) -> dict[str, FindingEntry]:
    """Every finding whose arms' grids ran in this book."""
    return {name: judge_one(f, runs) for name, f in spec.findings.items()
            if {a.grid for c in f.comparisons for a in (c.a, c.b)} <= only_grids}


def verdict_rows(findings: dict[str, FindingEntry]) -> pd.DataFrame:
    """The verdict table: one row per comparison (the finding's name and overall verdict on its first)."""
    rows = []
    for name, f in findings.items():
        for i, c in enumerate(f["comparisons"]):
            lo, hi = c["ci95"]
            mean, std = c["mean_diff"], c["std_diff"]
            rows.append({"finding": f"{name}: {f['claim']}" if i == 0 else "",
                         "verdict": f["verdict"] if i == 0 else "",
                         "comparison": f"{c['a']} vs {c['b']} ({c['better']} is better)",
                         "wins / N": f"{c['wins']} / {c['n']}" + (f" ({c['ties']} tied)" if c["ties"] else ""),
                         "mean ± std a − b": "—" if mean is None else
                         f"{mean:.3g}" + ("" if std is None else f" ± {std:.3g}"),
                         "sign p": "—" if c["sign_p"] is None else f"{c['sign_p']:.3g}",
                         "95 % CI": "—" if lo is None else f"[{lo:.3g}, {hi:.3g}]",
                         "this comparison": c["verdict"]})
    return pd.DataFrame(rows, columns=["finding", "verdict", "comparison", "wins / N", "mean ± std a − b", "sign p",
                                       "95 % CI", "this comparison"])
