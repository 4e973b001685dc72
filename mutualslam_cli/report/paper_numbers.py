"""The paper's own numbers, to print beside ours where a sequence is one of the paper's.

Transcribed from the paper's Tables 1–6 (``../shared/paper/online-mutual-adaptation.tex``).
Sequence keys are the paper's names; :func:`paper_name` maps a dataset name of ours to them.
The paper ran whole sequences (1–2.5k frames) with its own SVO and a GPU; a row of ours on a
window of a sequence is not the same experiment, which the reports say next to the column.
"""

from __future__ import annotations

import re

#: Table 1 (PCD %, δ < 0.1): the paper's pre-trained model and its adapted one ("Ours", scaled to GT), and
#: Luo et al.'s pre-trained model and adaptation as the paper quotes them ("Luo pre-trained", "Luo").
TABLE1 = {
    "ICL/office0": {"Pre-trained": 8.766, "Ours": 12.541, "Luo pre-trained": 19.117, "Luo": 22.206},
    "ICL/office1": {"Pre-trained": 19.739, "Ours": 21.87, "Luo pre-trained": 28.086, "Luo": 31.289},
    "ICL/office2": {"Pre-trained": 4.591, "Ours": 42.244, "Luo pre-trained": 21.695, "Luo": 21.695},
    "ICL/living0": {"Pre-trained": 7.726, "Ours": 41.375, "Luo pre-trained": 18.68, "Luo": 23.278},
    "ICL/living1": {"Pre-trained": 8.518, "Ours": 49.075, "Luo pre-trained": 21.071, "Luo": 22.774},
    "ICL/living2": {"Pre-trained": 13.509, "Ours": 25.159, "Luo pre-trained": 16.15, "Luo": 20.995},
    "TUM/seq1": {"Pre-trained": 10.999, "Ours": 23.861, "Luo pre-trained": 18.208, "Luo": 20.259},
    "TUM/seq2": {"Pre-trained": 12.678, "Ours": 52.162, "Luo pre-trained": 25.796, "Luo": 29.014},
    "TUM/seq3": {"Pre-trained": 10.295, "Ours": 37.848, "Luo pre-trained": 20.668, "Luo": 30.156},
}
#: Table 2 (PCD %, median scaling), pre-trained mono+stereo_640x192, ours and CoMoDa.
TABLE2 = {
    "ICL/office0": {"Pre-trained": 13.660, "Ours": 32.98, "CoMoDa": 21.054},
    "ICL/office1": {"Pre-trained": 22.453, "Ours": 38.383, "CoMoDa": 41.623},
    "ICL/office2": {"Pre-trained": 22.514, "Ours": 44.790, "CoMoDa": 37.374},
    "ICL/living0": {"Pre-trained": 17.659, "Ours": 48.158, "CoMoDa": 35.164},
    "ICL/living1": {"Pre-trained": 22.585, "Ours": 51.531, "CoMoDa": 46.148},
    "ICL/living2": {"Pre-trained": 21.606, "Ours": 35.757, "CoMoDa": 35.571},
    "TUM/seq1": {"Pre-trained": 16.931, "Ours": 27.915, "CoMoDa": 33.120},
    "TUM/seq2": {"Pre-trained": 17.722, "Ours": 41.782, "CoMoDa": 33.708},
    "TUM/seq3": {"Pre-trained": 23.026, "Ours": 50.339, "CoMoDa": 39.769},
}
#: Table 3 (PCD %): pre-trained, (a) recent, (b) replay, (c) replay + regularisation.
TABLE3 = {
    "ICL/office0": {"none": 8.766, "recent": 7.249, "replay": 12.734, "replay+ewc": 12.541},
    "ICL/office1": {"none": 19.739, "recent": 4.034, "replay": 22.613, "replay+ewc": 21.870},
    "ICL/office2": {"none": 4.591, "recent": 21.449, "replay": 34.609, "replay+ewc": 42.244},
    "ICL/living0": {"none": 7.726, "recent": 13.179, "replay": 22.883, "replay+ewc": 41.375},
    "ICL/living1": {"none": 8.518, "recent": 38.246, "replay": 41.149, "replay+ewc": 49.075},
    "ICL/living2": {"none": 13.509, "recent": 9.110, "replay": 13.117, "replay+ewc": 25.159},
    "TUM/seq1": {"none": 10.999, "recent": 16.012, "replay": 19.782, "replay+ewc": 23.861},
    "TUM/seq2": {"none": 12.678, "recent": 14.457, "replay": 37.539, "replay+ewc": 52.162},
    "TUM/seq3": {"none": 10.295, "recent": 49.515, "replay": 51.545, "replay+ewc": 37.848},
}
#: Table 4 (keyframe ATE, m, aligned to GT): without and with global photometric BA.
TABLE4 = {
    "ICL/office0": {"Without BA": 0.363, "With BA": 0.323}, "ICL/office1": {"Without BA": 0.196, "With BA": 0.204},
    "ICL/office2": {"Without BA": 0.170, "With BA": 0.171}, "ICL/living0": {"Without BA": 0.220, "With BA": 0.227},
    "ICL/living1": {"Without BA": 0.032, "With BA": 0.026}, "ICL/living2": {"Without BA": 0.161, "With BA": 0.158},
    "TUM/seq1": {"Without BA": 0.088, "With BA": 0.073}, "TUM/seq2": {"Without BA": 0.029, "With BA": 0.011},
    "TUM/seq3": {"Without BA": 0.011, "With BA": 0.012},
}
#: Table 5: (BA, culling, max_fts) → sequence → (map points, e_si).
TABLE5 = {
    (False, False, 120): {"Lab1": (13992, 0.533), "Lab2": (19856, 0.607)},
    (True, False, 120): {"Lab1": (14469, 0.545), "Lab2": (20464, 0.625)},
    (True, True, 120): {"Lab1": (7435, 0.473), "Lab2": (9226, 0.495)},
    (False, False, 500): {"Lab1": (19179, 0.527), "Lab2": (25743, 0.540)},
    (True, False, 500): {"Lab1": (19208, 0.515), "Lab2": (23998, 0.528)},
    (True, True, 500): {"Lab1": (9916, 0.493), "Lab2": (12686, 0.472)},
}
#: Table 6 (e_si of depth maps) for the paper's Monodepth2 rows (MiDaS and DiverseDepth rows: ``mslam eval-depth``).
TABLE6 = {"Pre-trained": {"Lab1": 0.401, "Lab2": 0.399}, "Ours": {"Lab1": 0.235, "Lab2": 0.219}}

_PATTERNS = (
    (re.compile(r"(?:^|[^a-z])(?:of|office)_?kt([0-3])"), "ICL/office{}"),
    (re.compile(r"(?:^|[^a-z])(?:lr|living(?:_?room)?)_?kt([0-3])"), "ICL/living{}"),
    (re.compile(r"long_office_household"), "TUM/seq1"),
    (re.compile(r"nostructure_texture_near"), "TUM/seq2"),
    (re.compile(r"(?<!no)structure_texture_far"), "TUM/seq3"),
    (re.compile(r"(?:^|[^a-z])lab_?([12])(?:[^0-9]|$)"), "Lab{}"),
)


def paper_name(sequence: str) -> str | None:
    """The paper's name of one of our sequences (``icl_lr_kt2`` → ``ICL/living2``), or None.

    ICL-NUIM kt0–kt2 map to office/living 0–2 as in the paper; kt3 has no paper row.
    """
    s = sequence.lower()
    for pat, fmt in _PATTERNS:
        m = pat.search(s)
        if m:
            name = fmt.format(*m.groups())
            known = set(TABLE1) | {"Lab1", "Lab2"}
            return name if name in known else None
    return None
