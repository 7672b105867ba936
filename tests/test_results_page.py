"""The results page (`ccfit report results/`): rebuilt byte for byte from the published files,
its headline table on the first screen, every link resolving, and made from the records
themselves (a planted change to one run's record changes it)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

from ccfit.report.page import PAGE, write_page
from ccfit.run_files import SWEEP_JSON

try:
    from test_report import config, write_run
except ImportError:
    from tests.test_report import config, write_run

RESULTS = Path(__file__).resolve().parents[1] / "results"
FIRST_SCREEN, MOST_LINES = 60, 250


def test_the_published_page_is_what_the_files_beside_it_give(tmp_path):
    copy = tmp_path / "results"
    shutil.copytree(RESULTS, copy)
    write_page(copy)
    assert (copy / PAGE).read_text() == (RESULTS / PAGE).read_text(), (
        "results/README.md is stale: `ccfit report results/` rewrites it"
    )


def test_the_headline_table_is_on_the_first_screen_and_the_page_is_short():
    lines = (RESULTS / PAGE).read_text().splitlines()
    assert len(lines) <= MOST_LINES
    table = [i for i, line in enumerate(lines) if line.startswith("| suite | backbone |")]
    assert table, "no headline table"
    end = next(i for i in range(table[0], len(lines)) if not lines[i].startswith("|"))
    assert end <= FIRST_SCREEN, f"the headline table ends at line {end}"


def test_every_link_on_the_page_resolves():
    text = (RESULTS / PAGE).read_text()
    for target in re.findall(r"\]\(([^)#]+)\)", text):
        assert (RESULTS / target).exists(), target


def _results(root: Path) -> Path:
    """A published folder of three seeds of FT and ER whose sweep also named EWC."""
    folder = root / "online" / "reach-tiny"
    for method, scale in (("ft", 1.0), ("er", 0.8)):
        for seed in range(3):
            write_run(folder, f"{method}-s{seed}", config(seed=seed, method=method),
                      scale + 0.05 * seed)  # fmt: skip
    (folder / "report").mkdir()
    grid = {"suites": ["Reach"], "models": ["tdmpc2"], "methods": ["ft", "er", "ewc"],
            "seeds": [0, 1, 2], "preset": "smoke", "track": "online", "args": []}  # fmt: skip
    (folder / SWEEP_JSON).write_text(json.dumps({"grid": grid}))
    return root


def test_the_page_is_made_from_the_records_and_is_deterministic(tmp_path):
    root = _results(tmp_path / "results")
    write_page(root)
    first = (root / PAGE).read_text()
    row = next(line for line in first.splitlines() if line.startswith("| Reach | tdmpc2 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[6:8] == ["3", "partial: ewc not run"]
    assert cells[8].count("[") == 2 and cells[10] == "not run"  # ft: BWT and FWT with CIs
    assert "| Grasp | dreamerv3 | state | online | | | | not run |" in first
    assert "--methods ft,er,ewc --seeds 0,1,2 --preset smoke" in first
    write_page(root)
    assert (root / PAGE).read_text() == first  # the bootstrap is seeded

    records = root / "online" / "reach-tiny" / "ft-s1" / "metrics.jsonl"
    lines = [json.loads(line) for line in records.read_text().splitlines()]
    lines[-1]["normalized_return"] -= 30.0  # seed 1 forgets its first tasks more at the end
    records.write_text("".join(json.dumps(r) + "\n" for r in lines))
    write_page(root)
    changed = (root / PAGE).read_text()
    assert changed != first
    new_row = next(line for line in changed.splitlines() if line.startswith("| Reach | tdmpc2 |"))
    assert new_row != row


def test_the_aggregate_is_rliables_iqm_over_the_suites_on_the_seeds_they_share():
    from scipy.stats import trim_mean

    from ccfit.report.page import aggregate_table
    from ccfit.report.stats import mean_interval, metric_fields

    def group(bwt: list[float], fwt: list[float]) -> dict:
        out = {"seeds": list(range(len(bwt)))}
        for name, values in (("bwt", bwt), ("fwt", fwt)):
            out |= metric_fields(name, sum(values) / len(values), mean_interval(values),
                                 dict(enumerate(values)))  # fmt: skip
        return out

    groups = {("tdmpc2", "Reach", "ft", ""): group([1.0, 2.0, 30.0, 7.0, 8.0],  # 5 seeds
                                                   [10.0, 11.0, 12.0, 13.0, 14.0]),
              ("tdmpc2", "Grasp", "ft", ""): group([4.0, 5.0, 6.0], [20.0, 21.0, 22.0]),
              ("tdmpc2", "BinPnP", "ft", ""): group([90.0], [0.0]),  # one seed: left out
              ("tdmpc2", "Reach", "er", ""): group([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])}  # fmt: skip
    (row,) = [line for line in aggregate_table(groups) if line.startswith("| tdmpc2 |")]
    cells = [c.strip() for c in row.strip("|").split("|")]
    # on the 3 seeds the two suites share; ER ran one suite: no row
    assert cells[:4] == ["tdmpc2", "ft", "Reach, Grasp", "3"]
    iqm = trim_mean([1.0, 2.0, 30.0, 4.0, 5.0, 6.0], 0.25)  # the middle half: 2, 4, 5, 6
    assert cells[4].startswith(f"{iqm:.2f} [")


def test_a_folder_of_offline_runs_only_gets_its_page_without_a_figure(tmp_path):
    copy = tmp_path / "results"
    shutil.copytree(RESULTS / "offline" / "dreamerv3", copy / "offline" / "dreamerv3")
    written = write_page(copy)
    text = (copy / PAGE).read_text()
    assert not (copy / "intervals.png").exists() and "intervals.png" not in text
    assert "| Reach | dreamerv3 | state | offline |" in text and copy / PAGE in written


def test_the_page_pretrains_each_published_encoder_with_the_settings_it_was_made_with():
    """The `ccfit pretrain-encoder` command the page prints for a published encoder gives the
    settings its sidecar records (its identity), whatever the presets say today: the `cpu`
    preset's recipe changed after `encoder-cpu-s0` was made, so a command that left a setting
    to the preset would make another encoder."""
    import argparse
    import shlex

    from ccfit.pretrain import add_pretrain_parser, config_from_args
    from ccfit.report.commands import setup_commands

    parser = argparse.ArgumentParser()
    add_pretrain_parser(parser.add_subparsers(dest="command"))
    sidecars = sorted(RESULTS.glob("probe/*/encoder.json"))
    assert sidecars
    for sidecar in sidecars:
        record = json.loads(sidecar.read_text())
        name = record["weights"]
        run = type("Run", (), {"config": {"encoder": f"frozen:{name}", "suite": "Reach"}})
        lines = setup_commands({"group": [run]}, RESULTS)
        text = " ".join(line.rstrip("\\") for line in lines if not line.startswith("ccdata"))
        argv = shlex.split(text)[1:]  # after `ccfit`
        config = config_from_args(parser.parse_args(argv))
        made = {k: v for k, v in config.identity().items() if k != "dataset_roots"}
        recorded = {k: v for k, v in record["identity"].items() if k != "dataset_roots"}
        assert made == recorded, sidecar


def test_an_encoders_line_says_whether_its_latent_holds_the_task(tmp_path):
    # The probe of each frozen encoder the runs read: an arm-only latent's rows are said to
    # measure the arm; one that holds the goals and objects is summarised, not called arm-only.
    from types import SimpleNamespace

    from ccfit.report.page import encoder_notes

    def probe(name: str, task_r2: list[float]) -> None:
        (tmp_path / "probe" / name).mkdir(parents=True)
        rows = [{"position": "hand", "latent_r2": [0.97, 0.95]},
                {"position": "goal", "latent_r2": task_r2}]  # fmt: skip
        found = {"encoder": f"{name}.safetensors", "rows": rows}
        (tmp_path / "probe" / name / "probe.json").write_text(json.dumps(found))

    probe("arm", [0.04, 0.09])
    probe("task", [0.98, 0.3, 0.9])
    runs = {k: [SimpleNamespace(config={"encoder": f"frozen:{k}.safetensors"})]
            for k in ("arm", "task")}  # fmt: skip
    arm, _, task, _ = encoder_notes(runs, tmp_path)
    assert "R^2 <= 0.09" in arm and "the arm alone" in arm
    assert "0.90 at the median, 67% of their coordinates >= 0.5" in task
    assert "arm alone" not in task
    assert "do not give" not in task  # a probe from before `others_r2`: no such clause


def test_an_encoders_line_counts_apart_what_the_other_positions_give(tmp_path):
    # A cube under a goal that floats over it is given by the goal: a latent's R^2 on it says
    # nothing of its own, so the line summarises the coordinates the others do not give.
    from types import SimpleNamespace

    from ccfit.report.page import encoder_notes

    rows = [
        {"position": "hand", "latent_r2": [0.97], "others_r2": [0.0]},
        {"position": "object", "latent_r2": [0.91, 0.84], "others_r2": [0.94, 0.91]},
        {"position": "goal", "latent_r2": [0.9, 0.2, 0.6], "others_r2": [0.1, 0.0, None]},
    ]
    (tmp_path / "probe" / "e").mkdir(parents=True)
    found = {"encoder": "e.safetensors", "rows": rows}
    (tmp_path / "probe" / "e" / "probe.json").write_text(json.dumps(found))
    runs = {"e": [SimpleNamespace(config={"encoder": "frozen:e.safetensors"})]}
    line = encoder_notes(runs, tmp_path)[0]
    assert "0.84 at the median, 80% of their coordinates >= 0.5" in line
    assert "of the 2 coordinates that the task's other positions do not give" in line
    assert "0.55 at the median, 50% >= 0.5" in line
