"""The forgetting table of ``mslam report``: the final model on the sequence's first and last quarters beside the
pre-trained model and the online score, and the backward transfer (summary keys of
:mod:`mutualslam_cli.stages.forgetting`)."""

from __future__ import annotations

#: table name → (title, [(column label, summary key)]), merged into :data:`~mutualslam_cli.report.tables.TABLES`.
FORGETTING_TABLE: dict[str, tuple[str, list[tuple[str, str]]]] = {
    "forgetting": ("Forgetting: PCD lsq (%) of the final model on the sequence's first and last quarters beside the "
                   "pre-trained model and the model of each frame's time (online); BWT = final − online, and final − "
                   "pre-trained, on the first quarter (negative: forgotten)", [
        ("Q1 pre", "depth.quarter_pcd_lsq.pretrained.q1"), ("Q1 online", "depth.quarter_pcd_lsq.online.q1"),
        ("Q1 final", "depth.quarter_pcd_lsq.adapted.q1"), ("Q4 pre", "depth.quarter_pcd_lsq.pretrained.q4"),
        ("Q4 online", "depth.quarter_pcd_lsq.online.q4"), ("Q4 final", "depth.quarter_pcd_lsq.adapted.q4"),
        ("BWT vs online", "depth.bwt.vs_online"), ("final − pre Q1", "depth.bwt.vs_pretrained"),
    ]),
}
