"""`axes.md`: the composition-axis table averages what is there, says what it averaged, and
stands the paper's figures beside it."""

from __future__ import annotations

import pytest

from ccfit.report.axes import PAPER_AXES, axis_cells, write_axes


def _group(bwt: float | None, fwt: float | None) -> dict:
    return {"bwt": bwt, "fwt": fwt, "seeds": [0, 1, 2]}


def test_a_cell_averages_the_paper_methods_of_its_axis_suites(tmp_path):
    groups = {
        ("tdmpc2", "Reach", "ft", ""): _group(2.0, 10.0),
        ("tdmpc2", "Reach", "packnet", ""): _group(0.0, 14.0),
        ("tdmpc2", "Grasp", "ft", ""): _group(50.0, 6.0),
        ("tdmpc2", "Grasp", "er", ""): _group(None, 2.0),  # BWT undefined: left out of BWT
        ("tdmpc2", "Reach", "experts", ""): _group(99.0, 99.0),  # not one of the paper's four
        ("tdmpc2", "BinPnP", "ft", ""): _group(30.0, -4.0),  # the perception axis
        ("tdmpc2-offline", "Reach", "ft", ""): _group(1.0, 1.0),  # offline: not the paper's
        ("tdmpc2", "Grasp", "ft", "obs=pixels"): _group(70.0, 0.0),  # another variant
    }
    cells = {(c["backbone"], c["variant"], c["axis"]): c for c in axis_cells(groups)}
    assert set(cells) == {("tdmpc2", "", "action"), ("tdmpc2", "", "perception"),
                          ("tdmpc2", "obs=pixels", "action")}  # fmt: skip
    action = cells[("tdmpc2", "", "action")]
    assert action["bwt"] == pytest.approx((2.0 + 0.0 + 50.0) / 3)
    assert action["fwt"] == pytest.approx((10.0 + 14.0 + 6.0 + 2.0) / 4)
    assert action["bwt_undefined"] == [("Grasp", "er")] and action["fwt_undefined"] == []
    assert action["paper"] == PAPER_AXES[("tdmpc2", "action")] == (32.15, 16.76)
    assert cells[("tdmpc2", "obs=pixels", "action")]["bwt"] == 70.0

    text = write_axes(groups, tmp_path).read_text()
    row = next(x for x in text.splitlines() if x.startswith("| tdmpc2 | action"))
    assert row == (
        "| tdmpc2 | action | 17.33 | 8.00 | 32.15 | 16.76 | Reach: ft, packnet; "
        "Grasp: ft, er (2 of 2 suites, 4 of 8 groups); BWT undefined for Grasp er |"
    )
    assert "| tdmpc2 | perception | 30.00 | -4.00 | 57.81 | -1.88 | BinPnP: ft (1 of 2" in text


def test_no_online_run_of_the_papers_methods_makes_an_empty_table(tmp_path):
    text = write_axes({("pwm", "Reach", "experts", ""): _group(1.0, 1.0)}, tmp_path).read_text()
    assert "(no online run of FT, ER, EWC or PackNet here)" in text


def test_a_suite_that_is_one_task_from_state_is_named_in_its_cell(tmp_path):
    state = {**_group(30.0, 60.0), "obs": "state"}
    pixels = {**_group(40.0, 1.0), "obs": "pixels"}
    groups = {
        ("tdmpc2", "BinPnP", "ft", "obs=state"): state,
        ("tdmpc2", "Grasp", "ft", "obs=state"): state,  # Grasp's tasks differ from state
        ("tdmpc2", "BinPnP", "ft", "obs=pixels"): pixels,
    }
    cells = {c["variant"]: c for c in axis_cells(groups) if c["axis"] == "perception"}
    assert cells["obs=state"]["same_from_state"] == ["BinPnP"]
    assert cells["obs=pixels"]["same_from_state"] == []
    rows = write_axes(groups, tmp_path).read_text().splitlines()
    state_row = next(x for x in rows if x.startswith("| tdmpc2 [obs=state] | perception"))
    assert state_row.endswith(
        "; BinPnP from state: bin-red-blue, bin-yellow-blue, bin-red-purple and "
        "bin-yellow-purple are one task |"
    )
    assert not any("one task" in x for x in rows if "obs=pixels" in x or "| action" in x)
