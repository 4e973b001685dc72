"""``keyframes.csv`` rows (:mod:`mutualslam_cli.online.rows`): one fixed column order whatever the rows hold, the
adapter's record copied when taken, and only the back end's work columns accepted as seconds."""

from __future__ import annotations

import pytest

from mutualslam_cli.adapt.step_info import StepInfo
from mutualslam_cli.online.rows import COLUMNS, KeyframeRow, keyframes_table


def test_columns_follow_one_order_whatever_the_first_row_holds():
    untouched = KeyframeRow(0, seconds={"bridge_s": 0.5}, not_ticked="a segment no bridge joined")
    info = StepInfo(kf_id=1, t=1, state="IDLE", is_validation=False, trained=True, batch=[1, 0],
                    loss={"photo": 0.2, "total": 0.3}, steps=8, ms=4.0)
    trained = KeyframeRow(1, n_sparse=40, rt_start_ms=10.0)
    trained.took(info)
    trained.add_seconds("ba_s", 1.0)
    trained.add_seconds("ba_s", 0.5)
    info.loss["photo"] = 9.0  # the adapter going on with its own record does not change the row
    table = keyframes_table([untouched, trained])
    cols = list(table.columns)
    fixed = [c for c in cols if not c.startswith("loss_")]
    assert fixed == [c for c in COLUMNS if c in fixed]
    assert cols.index("loss_photo") == cols.index("ms") + 1
    assert cols.index("loss_total") == cols.index("ms") + 2
    assert cols.index("n_sparse") > cols.index("loss_total")
    row = table.set_index("kf_id").loc[1]
    assert row["loss_photo"] == 0.2
    assert row["ba_s"] == 1.5
    assert row["batch"] == "1 0"
    assert trained.run_global_ba is False
    assert trained.n_steps == 8
    assert untouched.n_steps == 0


def test_only_the_back_ends_work_is_booked_as_seconds():
    with pytest.raises(KeyError, match=r"not a keyframes\.csv work column"):
        KeyframeRow(0).add_seconds("steps", 1.0)
