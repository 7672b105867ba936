"""`orderings.md`: each of the paper's orderings is judged right on groups whose answer is
known, only where the runs it needs exist, and 'n/a' where a metric is undefined."""

from __future__ import annotations

from ccfit.report.orderings import ORDERINGS, ordering_rows, write_orderings
from ccfit.report.stats import mean_interval, metric_fields


def _group(bwt: float | None, fwt: float = 10.0, seeds: int = 3,
           spread: float = 1.0) -> dict:  # fmt: skip
    """A group whose seeds score value - spread, value, value + spread (three seeds); its
    seed-averaged curves' metric is `value`, with the per-seed mean's CI standing in for that
    metric's own."""
    group = {"seeds": list(range(seeds))}
    for name, value in (("bwt", bwt), ("fwt", fwt)):
        by_seed = {s: None if value is None else value + spread * (s - (seeds - 1) / 2)
                   for s in range(seeds)}  # fmt: skip
        defined = [v for v in by_seed.values() if v is not None]
        group |= metric_fields(name, value, mean_interval(defined), by_seed)
    return group


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
    # both conventions, every seed (seed s of each method is value - 1 + s: the order holds on
    # each), the weakest pair's probability of improvement (packnet 0.5 against er 1.0, seeds
    # a spread of 1 apart: 6 of 9 seed pairs), the values with their CIs
    assert reach[:5] == ("tdmpc2", "Reach", "yes", "yes", "yes (3 of 3)")
    assert reach[5].startswith("0.67 [") and reach[5].endswith("] (packnet < er)")
    assert reach[6] == ("BWT packnet 0.50 [-0.50, 1.50] < er 1.00 [0.00, 2.00] "
                        "< ft 3.00 [2.00, 4.00]")  # fmt: skip
    assert grasp[2:5] == ("no", "no", "no (0 of 3)")  # ER forgets more than FT there
    assert [r[2] for r in _rows(groups, ER)] == ["no", "yes"]  # Grasp, then Reach
    # no FT run: the first ordering cannot be checked; one seed: no CI; a tie is not 'most'
    groups = {("tdmpc2", "Reach", "er", ""): _group(1.0, fwt=11.0, seeds=1),
              ("tdmpc2", "Reach", "packnet", ""): _group(0.5, seeds=1)}  # fmt: skip
    assert _rows(groups, PACKNET) == []
    ((*verdicts, p, values, _),) = _rows(groups, ER)
    assert verdicts == ["tdmpc2", "Reach", "yes", "yes", "yes (1 of 1)"]
    assert values == "FWT er 11.00 > packnet 10.00"
    groups[("tdmpc2", "Reach", "er", "")] = _group(1.0, fwt=10.0, seeds=1)
    assert _rows(groups, ER)[0][2:5] == ("no", "no", "no (0 of 1)")


def test_the_two_conventions_and_the_seeds_can_disagree():
    """The seed-averaged curves' metric is not the mean of the seeds' metrics (BWT clips each
    drop): a verdict is given under both, and on every seed."""
    ft, packnet = _group(3.0, spread=4.0), _group(2.0, spread=0.5)
    packnet["bwt"] = 3.5  # the curves' metric says PackNet forgets more; the seeds' mean less
    groups = {("tdmpc2", "Reach", "ft", ""): ft, ("tdmpc2", "Reach", "packnet", ""): packnet}
    (row,) = _rows(groups, PACKNET)
    assert row[2:5] == ("no", "yes", "no (2 of 3)")  # ft's seed 0 (-1.0) beats packnet's


def test_an_undefined_metric_carries_its_reason():
    groups = {("tdmpc2", "Reach", "ft", ""): _group(1.0),
              ("tdmpc2", "Reach", "packnet", ""): _group(None)}  # fmt: skip
    groups[("tdmpc2", "Reach", "packnet", "")]["bwt_reason"] = "no task learnt above 0"
    (row,) = _rows(groups, PACKNET)
    assert row[2:6] == ("n/a",) * 4
    assert row[6] == "BWT undefined for packnet: no task learnt above 0"


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
    assert row[6].startswith("BWT ft 1.00 [0.00, 2.00] vs ft 2.00 [1.00, 3.00]; ewc")
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
    assert row[:5] == ("pwm+frozen-enc vs tdmpc2+frozen-enc", "Reach", "yes", "yes",
                       "yes (3 of 3)")  # fmt: skip
    assert row[5] == "1.00 [1.00, 1.00] (pwm+frozen-enc experts < tdmpc2+frozen-enc ft)"
    assert row[6] == "BWT experts 0.50 [-0.50, 1.50] vs ft 5.00 [4.00, 6.00]"
    groups[("tdmpc2+frozen-enc", "Reach", "ft", "")] = _group(0.5)  # a tie is not less
    assert _rows(groups, PWM)[0][2] == "no"
    del groups[("tdmpc2+frozen-enc", "Reach", "ft", "")]
    assert _rows(groups, PWM) == []  # no TD-MPC2 ft: not checkable


def test_offline_rows_stand_apart_as_prediction_fidelity(tmp_path):
    groups = {("tdmpc2", "Reach", "ft", ""): _group(3.0),
              ("tdmpc2", "Reach", "packnet", ""): _group(0.5),
              ("tdmpc2-offline", "Reach", "ft", ""): _group(3.0),
              ("tdmpc2-offline", "Reach", "packnet", ""): _group(0.5)}  # fmt: skip
    text = write_orderings(groups, tmp_path).read_text()
    online, offline = text.split("## Online", 1)[1].split("## Offline: prediction fidelity")
    assert "| tdmpc2 | Reach |" in online and "tdmpc2-offline" not in online
    assert "| tdmpc2-offline | Reach |" in offline and "never counted as support" in offline


def test_the_file_names_what_it_could_not_check(tmp_path):
    groups = {("tdmpc2", "Reach", "ft", ""): _group(3.0),
              ("tdmpc2", "Reach", "packnet", ""): _group(0.5)}  # fmt: skip
    text = write_orderings(groups, tmp_path).read_text()
    assert "| PackNet forgets least, FT most | tdmpc2 | Reach | yes | yes | yes (3 of 3) |" in text
    unchecked = [name for name in ORDERINGS if name != PACKNET]
    assert text.rstrip().endswith("Not checkable on these runs: " + "; ".join(unchecked) + ".")
