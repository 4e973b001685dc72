"""Are two runs the same run? ``python -m mutualslam_cli.results.compare A B`` compares two run folders (or two
results roots, run by run) file by file: ``summary.json`` key by key, and the trajectories, ``per_frame.csv`` and
``keyframes.csv`` byte for byte — apart from what a rerun may change (wall times, versions, paths), listed in
:data:`VOLATILE`. It prints each difference and exits 1 when there is one: a restructuring of the code must
leave every run's output bit-identical.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pandas as pd

#: Summary keys (prefixes) that differ between two runs of the same code: times, machine, versions, paths; and the
#: file's schema version (a result of the previous format compares by its values: it has none).
VOLATILE = ("timing.", "notes.timing", "run.", "versions.", "git.", "vo.from_cache", "vo.frames_from_cache",
            "machine.", "config_path", "schema_version")
#: Files compared byte for byte (when either run has them).
FILES = ("traj_kf.txt", "traj_all.txt", "traj_kf_bridged.txt", "traj_all_bridged.txt", "traj_kf_ba.txt",
         "traj_all_ba.txt", "per_frame.csv")
#: ``keyframes.csv`` columns that hold wall times.
TIME_COLUMNS = ("ms",)


def _flat(d: dict, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def compare_runs(a: Path, b: Path) -> list[str]:
    """The differences between run folders ``a`` and ``b`` (empty: the same run), one line each."""
    out = []
    sa, sb = (_flat(json.loads((p / "summary.json").read_text())) for p in (a, b))
    for k in sorted(set(sa) | set(sb)):
        if k.startswith(VOLATILE):
            continue
        if k not in sa or k not in sb:
            out.append(f"summary {k}: only in {'A' if k in sa else 'B'}")
        elif not _same(sa[k], sb[k]):
            out.append(f"summary {k}: {sa[k]!r} vs {sb[k]!r}")
    for name in FILES:
        fa, fb = a / name, b / name
        if fa.exists() != fb.exists():
            out.append(f"{name}: only in {'A' if fa.exists() else 'B'}")
        elif fa.exists() and fa.read_bytes() != fb.read_bytes():
            out.append(f"{name}: differs")
    ka, kb = a / "keyframes.csv", b / "keyframes.csv"
    if ka.exists() != kb.exists():
        out.append(f"keyframes.csv: only in {'A' if ka.exists() else 'B'}")
    elif ka.exists():
        da, db = pd.read_csv(ka), pd.read_csv(kb)
        drop = [c for c in set(da.columns) | set(db.columns) if c in TIME_COLUMNS or c.endswith("_s")
                or c.startswith("rt_")]
        da, db = da.drop(columns=[c for c in drop if c in da]), db.drop(columns=[c for c in drop if c in db])
        if list(da.columns) != list(db.columns) or not da.equals(db):
            out.append("keyframes.csv: differs (wall times aside)")
    return out


def run_folders(root: Path) -> dict[str, Path]:
    """``{relative path: folder}`` of the complete runs (with ``summary.json``) under ``root`` (or ``root``)."""
    if (root / "summary.json").exists():
        return {".": root}
    return {str(p.parent.relative_to(root)): p.parent for p in sorted(root.rglob("summary.json"))
            if "_cache" not in p.parts}


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: python -m mutualslam_cli.results.compare RUN_OR_ROOT_A RUN_OR_ROOT_B", file=sys.stderr)
        return 2
    ra, rb = (run_folders(Path(p)) for p in argv)
    bad = 0
    for name in sorted(set(ra) | set(rb)):
        if name not in ra or name not in rb:
            print(f"{name}: only in {'A' if name in ra else 'B'}")
            bad += 1
            continue
        diffs = compare_runs(ra[name], rb[name])
        print(f"{name}: {'identical' if not diffs else f'{len(diffs)} difference(s)'}")
        for d in diffs:
            print(f"  {d}")
        bad += bool(diffs)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
