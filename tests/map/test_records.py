"""Named records of the map and the back end: a relocalisation, a global BA's statistics (their JSON rows keep the
keys and the order the manifest has always had)."""

from __future__ import annotations

from mutualslam_cli.backend.ba.global_ba import BAStats
from mutualslam_cli.backend.records import BARun
from mutualslam_cli.map.records import Relocalised

#: The keys of a manifest's ``ba_runs`` row, in order (before the stats were named).
BA_RUN_ROW = ["kf_id", "n_points", "n_culled", "n_judged", "n_judged_elsewhere", "n_targets", "n_nearby_targets",
              "n_diverged", "n_blocks", "n_outlier_blocks", "iterations", "accepted", "cost0", "cost", "n_parts",
              "n_refined", "n_unrefined", "n_dropped", "keyframes", "seconds"]


def test_a_ba_run_row_keeps_the_manifests_keys_and_leaves_the_costs_out():
    row = BARun(7, BAStats(n_points=10, n_culled=2, costs=[[1.0, 0.5]], seconds=0.25)).to_json()
    assert list(row) == BA_RUN_ROW
    assert row["kf_id"] == 7
    assert row["n_culled"] == 2
    assert row["seconds"] == 0.25
    assert row["cost0"] == 0


def test_a_relocalisation_row_is_the_dict_the_result_always_held():
    r = Relocalised(12, 0.4, 3, 80, 5, 2)
    assert r.to_json() == {"frame": 12, "timestamp": 0.4, "keyframe": 3, "inliers": 80, "frames_lost": 5,
                           "candidates_tried": 2}
    assert list(r.to_json()) == ["frame", "timestamp", "keyframe", "inliers", "frames_lost", "candidates_tried"]
