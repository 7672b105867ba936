"""`orderings.md`: each of the paper's orderings is judged right on groups whose answer is
known, only where the runs it needs exist, and 'n/a' where a metric is undefined."""

from __future__ import annotations

from ccfit.report.orderings import ORDERINGS, ordering_rows, write_orderings


def _group(bwt: float | None, fwt: float = 10.0, seeds: int = 3) -> dict:
    lo = None if bwt is None else bwt - 1
    hi = None if bwt is None else bwt + 1
    return {"bwt": bwt, "bwt_min": lo, "bwt_max": hi, "fwt": fwt, "fwt_min": fwt - 1,
            "fwt_max": fwt + 1, "seeds": list(range(seeds)), "fwt_seeds_defined": seeds,
            "bwt_seeds_defined": 0 if bwt is None else seeds}  # fmt: skip


def _rows(groups: dict, ordering: str) -> list[tuple]:
    return [row for name, row in ordering_rows(groups) if name == ordering]


PACKNET, ER = "PackNet forgets least, FT most", "ER transfers most"
DREAMER = "DreamerV3 forgets less than TD-MPC2 under every method"
PWM = "PWM with experts forgets far less than TD-MPC2 under the frozen encoder"


def test_within_a_backbone():
    groups = {
        ("tdmpc2", "Reach", "ft", ""): _group(3.0, fwt=15.0),
        ("tdmpc2", "Reach", "er", ""): _group(1.0, fwt=16.0),
        ("tdmpc2", "Reach", "packnet", ""): _group(0.5, fwt=14.0),
        ("tdmpc2", "Grasp", "ft", ""): _group(2.0, fwt=15.0),
        ("tdmpc2", "Grasp", "er", ""): _group(2.5, fwt=14.0),
        ("tdmpc2", "Grasp", "packnet", ""): _group(0.1, fwt=16.0),
    }
    grasp, reach = _rows(groups, PACKNET)  # scopes in sorted order
    assert reach[:3] == ("tdmpc2", "Reach", "yes")
    assert reach[3] == ("BWT packnet 0.50 [-0.50, 1.50] < er 1.00 [0.00, 2.00] "
                        "< ft 3.00 [2.00, 4.00]")  # fmt: skip
    assert grasp[2] == "no"  # ER forgets more than FT there
    assert [r[2] for r in _rows(groups, ER)] == ["no", "yes"]  # Grasp, then Reach
    # no FT run: the first ordering cannot be checked; one seed: no [min, max]
    groups = {("tdmpc2", "Reach", "er", ""): _group(1.0, seeds=1),
              ("tdmpc2", "Reach", "packnet", ""): _group(0.5, seeds=1)}  # fmt: skip
    assert _rows(groups, PACKNET) == []
    assert _rows(groups, ER) == [("tdmpc2", "Reach", "yes", "FWT er 10.00 > packnet 10.00")]


def test_across_backbones_within_a_track_and_suite():
    groups = {
        ("dreamerv3", "Reach", "ft", ""): _group(1.0),
        ("dreamerv3", "Reach", "ewc", ""): _group(0.2),
        ("tdmpc2", "Reach", "ft", ""): _group(2.0),
        ("tdmpc2", "Reach", "ewc", ""): _group(1.0),
        ("tdmpc2", "Reach", "er", ""): _group(0.1),  # DreamerV3 has no ER run: not compared
        ("dreamerv3", "Grasp", "ft", ""): _group(1.0),  # no TD-MPC2 Grasp run
        ("tdmpc2-offline", "Reach", "ft", ""): _group(0.1),  # the other track
    }
    (row,) = _rows(groups, DREAMER)
    assert row[:3] == ("dreamerv3 vs tdmpc2", "Reach", "yes")
    assert row[3].startswith("BWT ft 1.00 [0.00, 2.00] vs ft 2.00 [1.00, 3.00]; ewc")
    groups[("dreamerv3", "Reach", "ewc", "")] = _group(1.5)
    assert _rows(groups, DREAMER)[0][2] == "no"
    groups[("dreamerv3", "Reach", "ewc", "")] = _group(None)
    assert _rows(groups, DREAMER)[0][2] == "n/a"


def test_pwm_experts_against_tdmpc2_fine_tuned_under_the_frozen_encoder():
    """The paper's comparison: PWM with experts against TD-MPC2 under fine-tuning (another
    TD-MPC2 method, here PackNet forgetting less than PWM, does not enter the verdict)."""
    groups = {
        ("pwm+frozen-enc", "Reach", "experts", ""): _group(0.5),
        ("pwm+frozen-enc", "Reach", "ft", ""): _group(9.0),  # PWM's other methods: not used
        ("tdmpc2+frozen-enc", "Reach", "ft", ""): _group(5.0),
        ("tdmpc2+frozen-enc", "Reach", "packnet", ""): _group(0.2),
    }
    (row,) = _rows(groups, PWM)
    assert row == ("pwm+frozen-enc vs tdmpc2+frozen-enc", "Reach", "yes",
                   "BWT experts 0.50 [-0.50, 1.50] vs ft 5.00 [4.00, 6.00]")  # fmt: skip
    groups[("tdmpc2+frozen-enc", "Reach", "ft", "")] = _group(0.5)  # a tie is not less
    assert _rows(groups, PWM)[0][2] == "no"
    del groups[("tdmpc2+frozen-enc", "Reach", "ft", "")]
    assert _rows(groups, PWM) == []  # no TD-MPC2 ft: not checkable


def test_the_file_names_what_it_could_not_check(tmp_path):
    groups = {("tdmpc2", "Reach", "ft", ""): _group(3.0),
              ("tdmpc2", "Reach", "packnet", ""): _group(0.5)}  # fmt: skip
    text = write_orderings(groups, tmp_path).read_text()
    assert "| PackNet forgets least, FT most | tdmpc2 | Reach | yes |" in text
    unchecked = [name for name in ORDERINGS if name != PACKNET]
    assert text.rstrip().endswith("Not checkable on these runs: " + "; ".join(unchecked) + ".")
