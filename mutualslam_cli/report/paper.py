"""The paper's Tables 1–6 in the paper's shape, with mean ± std over seeds (DESIGN §8).

Each builder takes the collected runs (:func:`mutualslam_cli.report.collect`) and returns a
:class:`PaperTable`: a display frame (cells ``"mean ± std"``; ``"—"`` where no run has the value,
never 0), a numeric frame for CSV (``<column> mean``, ``<column> std``, ``<column> n``) and the
cells to set in bold (the best of our columns per row, as the paper does). Rows are sequences
(the paper's name in brackets when the sequence is one of the paper's) and an ``Average`` row,
the mean of the sequence means. Where a sequence is the paper's, the paper's own number is in a
``paper:`` column beside ours (:mod:`mutualslam_cli.report.paper_numbers`); ours are on our windows of
those sequences with our VO on 2 CPU cores, so they are the same metric, not the same experiment.

"Ours" is the scheme ``experiment.ours`` names (default ``replay+ewc``, the paper's); the
pre-trained columns read ``depth.*.pretrained``, which every scheme's run reports identically.
Models scored by ``mslam eval-depth`` (``external.model`` in their summary) are extra columns of
Tables 1–2 and rows of Table 6, labelled "NAME (external, no adaptation)".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from mutualslam_cli.report import paper_numbers as paper
from mutualslam_cli.report.columns import numeric
from mutualslam_cli.types import Scalar

#: Scheme columns of Table 3: the paper's (a), (b), (c), then the other schemes of ours.
SCHEME_COLUMNS = (("(a) recent", "recent"), ("(b) replay", "replay"), ("(c) replay+ewc", "replay+ewc"),
                  ("ewc", "ewc"), ("replay+mas", "replay+mas"), ("replay+si", "replay+si"))


@dataclass
class PaperTable:
    """One of the paper's tables built from our runs."""

    name: str
    title: str
    display: pd.DataFrame
    numeric: pd.DataFrame
    bold: set[tuple[int, str]] = field(default_factory=set)


def _stat(v: pd.Series) -> tuple[float, float, int]:
    """Mean, sample std (NaN for one value) and count of the finite values."""
    v = v[np.isfinite(v.to_numpy(dtype=float))] if len(v) else v
    n = len(v)
    if n == 0:
        return float("nan"), float("nan"), 0
    return float(v.mean()), float(v.std(ddof=1)) if n > 1 else float("nan"), n


def cell(mean: float, std: float, n: int, digits: int) -> str:
    """``"53.76 ± 1.20"`` (``"53.76"`` for one seed, ``"—"`` for none)."""
    if n == 0 or not np.isfinite(mean):
        return "—"
    if n == 1 or not np.isfinite(std):
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def seq_label(name: str) -> str:
    """``icl_lr_kt2 (ICL/living2)`` for the paper's sequences, else the name."""
    p = paper.paper_name(name)
    return f"{name} ({p})" if p else name


def _ours(runs: pd.DataFrame) -> str:
    col = "config.experiment.ours"
    if col in runs and runs[col].notna().any():
        return str(runs[col].dropna().iloc[0])
    return "replay+ewc"


Column = tuple[str, Callable[[pd.DataFrame], pd.Series]]  # label, runs of one sequence -> values over seeds


def _by_sequence(name: str, title: str, runs: pd.DataFrame, columns: list[Column],
                 paper_table: dict[str, dict[str, float]] | None, paper_columns: list[tuple[str, str]], digits: int,
                 lower_is_better: bool) -> PaperTable:
    """Rows = sequences + Average; our columns, then ``paper: <label>`` columns where known."""
    disp_rows, num_rows, bold = [], [], set()
    means: dict[str, dict[str, float]] = {label: {} for label, _ in columns}
    seqs = sorted(runs["sequence.name"].astype(str).unique())
    for i, seq in enumerate(seqs):
        sub = runs[runs["sequence.name"].astype(str) == seq]
        d: dict[str, str] = {"Sequence": seq_label(seq)}
        n_row: dict[str, Scalar] = {"sequence": seq, "paper_sequence": paper.paper_name(seq)}
        best, best_col = None, None
        for label, get in columns:
            m, s, n = _stat(get(sub))
            d[label] = cell(m, s, n, digits)
            n_row.update({f"{label} mean": m, f"{label} std": s, f"{label} n": n})
            if n:
                means[label][seq] = m
                if best is None or (m < best if lower_is_better else m > best):
                    best, best_col = m, label
        if best_col is not None and len(columns) > 1:
            bold.add((i, best_col))
        p = paper.paper_name(seq)
        for label, key in paper_columns:
            v = (paper_table or {}).get(p, {}).get(key) if p else None
            d[f"paper: {label}"] = "—" if v is None else f"{v:.{digits}f}"
            n_row[f"paper: {label}"] = v
        disp_rows.append(d)
        num_rows.append(n_row)
    # the paper's Average: the mean of the sequence means; over the sequences that have a value,
    # with their count in the row label when that is not all of them
    common = [q for q in seqs if all(q in v for v in means.values())]
    k = len(common)
    name_avg = "Average" if k == len(seqs) else f"Average ({k} of {len(seqs)} sequences)"
    avg = {"Sequence": name_avg}
    avg_num: dict[str, Scalar] = {"sequence": name_avg, "paper_sequence": None}
    best, best_col = None, None
    for label, _ in columns:
        m = float(np.mean([means[label][q] for q in common])) if common else float("nan")
        avg[label] = "—" if not np.isfinite(m) else f"{m:.{digits}f}"
        avg_num.update({f"{label} mean": m, f"{label} std": float("nan"), f"{label} n": k})
        if np.isfinite(m) and (best is None or (m < best if lower_is_better else m > best)):
            best, best_col = m, label
    if best_col is not None and len(columns) > 1:
        bold.add((len(seqs), best_col))
    for label, _ in paper_columns:
        avg[f"paper: {label}"] = "—"
        avg_num[f"paper: {label}"] = None
    disp_rows.append(avg)
    num_rows.append(avg_num)
    return PaperTable(name, title, pd.DataFrame(disp_rows), pd.DataFrame(num_rows), bold)


def _key(key: str, scheme: str | None = None) -> Callable[[pd.DataFrame], pd.Series]:
    """Values of ``key`` over the runs (of ``scheme`` when given)."""
    def get(sub: pd.DataFrame) -> pd.Series:
        if scheme is not None:
            sub = sub[sub["scheme"].astype(str) == scheme]
        return numeric(sub, key)
    return get


def _pretrained(key: str) -> Callable[[pd.DataFrame], pd.Series]:
    """The pre-trained model's value: the same in every scheme's run of a seed, so one per seed."""
    def get(sub: pd.DataFrame) -> pd.Series:
        v = sub.assign(_v=numeric(sub, key)).dropna(subset=["_v"])
        return v.groupby("seed")["_v"].first() if "seed" in v else v["_v"]
    return get


# ----------------------------------------------------------------------------- external models (mslam eval-depth)


def external_names(runs: pd.DataFrame) -> list[str]:
    """Models scored by ``mslam eval-depth`` among ``runs`` (their ``external.model``), sorted."""
    return sorted(runs["external.model"].dropna().astype(str).unique()) if "external.model" in runs else []


def external_label(name: str) -> str:
    """An external model's row/column label: ``"midas (external, no adaptation)"``."""
    return f"{name} (external, no adaptation)"


def _externals(runs: pd.DataFrame, key: str) -> list[Column]:
    """One column per external model: ``key`` (its scores are ``depth.*.adapted``) over its runs."""
    def getter(name: str) -> Callable[[pd.DataFrame], pd.Series]:
        return lambda sub: numeric(sub[sub["external.model"].astype(str) == name], key)
    return [(external_label(n), getter(n)) for n in external_names(runs)]


#: The baselines that run as schemes: column label per scheme name.
BASELINES = (("Luo-style (luo)", "luo"), ("CoMoDa-style (comoda)", "comoda"))


def _baselines(runs: pd.DataFrame, key: str) -> list[Column]:
    """One column per baseline scheme that ran: ``key`` over its runs."""
    present = set(runs["scheme"].astype(str))
    return [(label, _key(key, s)) for label, s in BASELINES if s in present]


# ----------------------------------------------------------------------------- the tables


def table1(runs: pd.DataFrame) -> PaperTable:
    """Table 1: PCD (%, δ < 0.1, per-frame least-squares scale), pre-trained vs ours."""
    ours = _ours(runs)
    return _by_sequence("table1_pcd", "Table 1: percentage of correct depth (%, δ<0.1, per-frame least-squares "
                        f"scaling), pre-trained vs ours ({ours}); mean ± std over seeds", runs,
                        [("Pre-trained", _pretrained("depth.pcd.lsq.pretrained"))]
                        + _baselines(runs, "depth.pcd.lsq.adapted")
                        + [("Ours", _key("depth.pcd.lsq.adapted", ours))] + _externals(runs, "depth.pcd.lsq.adapted"),
                        paper.TABLE1, [("Luo pre-trained", "Luo pre-trained"), ("Luo", "Luo"),
                                       ("Pre-trained", "Pre-trained"), ("Ours", "Ours")], 2, False)


def table2(runs: pd.DataFrame) -> PaperTable:
    """Table 2: PCD with median scaling, pre-trained vs ours (paper: and CoMoDa)."""
    ours = _ours(runs)
    return _by_sequence("table2_pcd_median", "Table 2: percentage of correct depth (%, δ<0.1, per-frame median "
                        f"scaling), pre-trained vs ours ({ours}); mean ± std over seeds", runs,
                        [("Pre-trained", _pretrained("depth.pcd.median.pretrained"))]
                        + _baselines(runs, "depth.pcd.median.adapted")
                        + [("Ours", _key("depth.pcd.median.adapted", ours))]
                        + _externals(runs, "depth.pcd.median.adapted"),
                        paper.TABLE2, [("Pre-trained", "Pre-trained"), ("Ours", "Ours"), ("CoMoDa", "CoMoDa")],
                        2, False)


#: The scalings of :func:`table1_scalings`: column suffix → (summary key of the pre-trained / adapted model).
SCALING_COLUMNS = (("lsq/frame", "depth.pcd.lsq"), ("lsq/sequence", "depth.pcd.seq_lsq"),
                   ("median/frame", "depth.pcd.median"), ("lsq/frame pooled", "depth.pcd_pooled.lsq"))


def table1_scalings(runs: pd.DataFrame) -> PaperTable:
    """Tables 1 and 2 under every scaling, pre-trained and ours, beside the paper's Table 1 (lsq) and
    Table 2 (median) numbers: which scaling reproduces the paper's pre-trained gap between them."""
    ours = _ours(runs)
    cols: list[Column] = [(f"Pre-trained {lab}", _pretrained(f"{key}.pretrained")) for lab, key in SCALING_COLUMNS]
    cols += [(f"Ours {lab}", _key(f"{key}.adapted", ours)) for lab, key in SCALING_COLUMNS]
    cols += [("Ours online lsq/frame", _key("depth.pcd_online.lsq", ours))]
    both = {q: {f"T1 {k}": v for k, v in paper.TABLE1.get(q, {}).items()}
            | {f"T2 {k}": v for k, v in paper.TABLE2.get(q, {}).items()} for q in set(paper.TABLE1) | set(paper.TABLE2)}
    return _by_sequence("table1_scalings", f"Tables 1–2 under each scaling: PCD (%, δ<0.1) of the pre-trained model "
                        f"and ours ({ours}) with a least-squares scale per frame (Table 1 as we read it), one "
                        "least-squares scale per sequence, a median scale per frame (Table 2), per-frame lsq pooled "
                        "over pixels, and ours scored online (each frame by the model of its time); paper: Table 1 "
                        "('scaled to GT') and Table 2 (median); mean ± std over seeds", runs, cols, both,
                        [("T1 pre-trained", "T1 Pre-trained"), ("T1 ours", "T1 Ours"),
                         ("T2 pre-trained", "T2 Pre-trained"), ("T2 ours", "T2 Ours")], 2, False)


def table3(runs: pd.DataFrame) -> PaperTable:
    """Table 3: PCD of every adaptation scheme present (paper: (a) recent, (b) replay, (c) replay+ewc)."""
    present = set(runs["scheme"].astype(str))
    cols: list[Column] = [("Pre-trained", _pretrained("depth.pcd.lsq.pretrained"))]
    cols += [(label, _key("depth.pcd.lsq.adapted", s)) for label, s in SCHEME_COLUMNS if s in present]
    return _by_sequence("table3_schemes", "Table 3: percentage of correct depth (%, δ<0.1, per-frame least-squares "
                        "scaling) of the final model per adaptation scheme; mean ± std over seeds", runs, cols,
                        paper.TABLE3, [("Pre-trained", "none"), ("(a)", "recent"), ("(b)", "replay"),
                                       ("(c)", "replay+ewc")], 2, False)


def table4(runs: pd.DataFrame) -> PaperTable:
    """Table 4: ATE (m, one Sim(3)) of the same frames for the front end alone, bridged, and after culling + BA; and,
    when scheme comoda ran, the ATE of its PoseNet trajectory (every frame, chained)."""
    ours = _ours(runs)
    posenet = ([("PoseNet, all frames (comoda)", _key("trajectory.ate_rmse_m.posenet", "comoda"))]
               if (runs["scheme"].astype(str) == "comoda").any() else [])
    keys = [f"trajectory.credit.{k}" for k in ("vo", "bridged", "ba")]
    have = [runs[k].notna() if k in runs else pd.Series(False, index=runs.index) for k in keys]
    full = have[0] & have[1] & have[2]
    seq_full = full.groupby(runs["sequence.name"].astype(str)).transform("any")
    paired = runs[~((runs["scheme"].astype(str) == ours) & seq_full & ~full)]  # cells paired by seed
    return _by_sequence("table4_ate_ba", f"Table 4: ATE RMSE (m, one Sim(3) each) of the frames every column tracked: "
                        f"the front end alone, joined by its bridges, after culling + global photometric BA ({ours}); "
                        "mean ± std over the seeds that have every column (— : no BA requested)", paired,
                        [("VO", _key("trajectory.credit.vo", ours)),
                         ("Bridged", _key("trajectory.credit.bridged", ours)),
                         ("With BA", _key("trajectory.credit.ba", ours))] + posenet,
                        paper.TABLE4, [("Without BA", "Without BA"), ("With BA", "With BA")], 4, True)


def table6(runs: pd.DataFrame) -> PaperTable:
    """Table 6: e_si of the depth maps (lower is better), methods as rows and sequences as columns."""
    ours = _ours(runs)
    seqs = sorted(runs["sequence.name"].astype(str).unique())
    rows = [("Pre-trained", _pretrained("depth.esi.pretrained"))] + _baselines(runs, "depth.esi.adapted")
    rows += [("Ours", _key("depth.esi.adapted", ours))] + _externals(runs, "depth.esi.adapted")
    disp, num, bold = [], [], set()
    best: dict[str, tuple[float, int]] = {}
    for i, (label, get) in enumerate(rows):
        d: dict[str, str] = {"Method": label}
        n_row: dict[str, Scalar] = {"method": label}
        for seq in seqs:
            m, s, n = _stat(get(runs[runs["sequence.name"].astype(str) == seq]))
            d[seq_label(seq)] = cell(m, s, n, 3)
            n_row.update({f"{seq} mean": m, f"{seq} std": s, f"{seq} n": n})
            if n and (seq not in best or m < best[seq][0]):
                best[seq] = (m, i)
            p = paper.paper_name(seq)
            if p in ("Lab1", "Lab2"):
                v = paper.TABLE6.get(label, {}).get(p)  # none for an external model
                d[f"paper: {p}"] = "—" if v is None else f"{v:.3f}"
                n_row[f"paper: {p}"] = v
        disp.append(d)
        num.append(n_row)
    bold = {(i, seq_label(seq)) for seq, (_, i) in best.items()}
    return PaperTable("table6_esi", f"Table 6: scale-invariant error e_si of the depth maps (pre-trained vs ours, "
                      f"{ours}); mean ± std over seeds", pd.DataFrame(disp), pd.DataFrame(num), bold)


def _flag(runs: pd.DataFrame, key: str, default: Scalar) -> pd.Series:
    return runs[key].where(runs[key].notna(), default) if key in runs else pd.Series(default, index=runs.index)


def table5(runs: pd.DataFrame) -> PaperTable | None:
    """Table 5: map points and map e_si per (BA, culling, max_fts) row, sequences as column pairs.

    Rows come from our runs as the paper defines them: no BA/no culling = the VO map of the runs
    (``map.*.vo``); BA without culling = ``map.*.ba`` of runs with ``ba.culling=false``; BA + culling
    = ``map.*.ba`` of runs with culling on. ``max_fts`` is ``vo.max_fts`` of the run's config.
    """
    ours = _ours(runs)
    r = runs[runs["scheme"].astype(str) == ours]
    if not len(r) or "map.points.vo" not in r:
        return None
    enabled = _flag(r, "config.ba.enabled", True).astype(bool)
    culling = _flag(r, "config.ba.culling", True).astype(bool)
    fts = _flag(r, "config.vo.max_fts", "default").astype(str)
    seqs = sorted(r["sequence.name"].astype(str).unique())
    disp, num = [], []
    for f in sorted(fts.unique(), key=lambda x: (not x.isdigit(), int(x) if x.isdigit() else 0, x)):
        vo_sel = (fts == f) & culling if ((fts == f) & culling).any() else fts == f  # one VO map per seed
        rows = ((False, False, vo_sel, "vo"), (True, False, (fts == f) & enabled & ~culling, "ba"),
                (True, True, (fts == f) & enabled & culling, "ba"))
        for ba, cull, sel, part in rows:
            sub = r[sel]
            if not len(sub):
                continue
            d: dict[str, str] = {"BA": "✓" if ba else "", "MP culling": "✓" if cull else "", "max_fts": f}
            n_row: dict[str, Scalar] = {"ba": ba, "culling": cull, "max_fts": f}
            for seq in seqs:
                s = sub[sub["sequence.name"].astype(str) == seq]
                for what, key, digits in (("points", f"map.points.{part}", 0), ("e_si", f"map.esi.{part}", 3)):
                    m, sd, n = _stat(numeric(s, key))
                    d[f"{seq_label(seq)} {what}"] = cell(m, sd, n, digits)
                    n_row.update({f"{seq} {what} mean": m, f"{seq} {what} std": sd, f"{seq} {what} n": n})
                p = paper.paper_name(seq)
                key5 = (ba, cull, int(f)) if f.isdigit() else None
                if p in ("Lab1", "Lab2") and key5 in paper.TABLE5:
                    pts, esi = paper.TABLE5[key5][p]
                    d[f"paper: {p} points / e_si"] = f"{pts} / {esi:.3f}"
            disp.append(d)
            num.append(n_row)
    if not disp:
        return None
    return PaperTable("table5_map", f"Table 5: map points and map e_si with and without culling + global BA, per "
                      f"vo.max_fts ({ours}; BA without culling = runs with ba.culling=false); mean ± std over seeds",
                      pd.DataFrame(disp), pd.DataFrame(num))


def paper_tables(runs: pd.DataFrame) -> list[PaperTable]:
    """Tables 1–4 and 6 per config group (a suffix names the group when there are several), Table 5
    over all runs; a table is left out when no run has its values."""
    out: list[PaperTable] = []
    labels = runs["config"].fillna("").astype(str) if "config" in runs else pd.Series("", index=runs.index)
    groups = sorted(labels.unique())
    for g in groups:
        sub = runs[labels == g]
        for build in (table1, table2, table1_scalings, table3, table4, table6):
            t = build(sub)
            data = [c for c in t.display.columns if c not in ("Sequence", "Method") and not c.startswith("paper:")]
            if not (t.display[data] != "—").to_numpy().any():
                continue
            if len(groups) > 1:
                t.name += f"__{groups.index(g)}"
                t.title += f" [{g or 'default config'}]"
            out.append(t)
    t5 = table5(runs)
    if t5 is not None:
        out.append(t5)
    return out
