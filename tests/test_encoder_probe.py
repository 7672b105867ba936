"""`ccfit probe-encoder`: the ridge scorer and the classifier on data of known content (planted
squares in synthetic images), the task selection, and the command end to end on real renders
through a (random) frozen encoder."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from ccdata.errors import InputError
from ccdata.suites import SUITES
from ccfit.analysis.encoder_probe import (
    classification_rows,
    markdown,
    others_r2,
    probe_rows,
    probed_sidecar,
    ridge_accuracy,
    ridge_r2,
    select_tasks,
    write_probe,
)
from ccfit.cli import main

SIZE = 32
PUBLISHED = Path(__file__).resolve().parents[1] / "results" / "probe"


def test_ridge_r2_scores_what_the_inputs_hold():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 6))
    y = np.stack([x @ rng.normal(size=6), rng.normal(size=400), np.full(400, 0.3)], axis=1)
    linear, noise, constant = ridge_r2(x, y)
    assert linear > 0.99 and noise < 0.05 and constant is None


def test_probe_rows_score_each_varying_position_and_drop_the_rest():
    """A 'latent' that holds the hand (plus noise) and nothing of the goal: the hand scores
    near 1, the goal near 0 or below, a coordinate that never varies and an absent object are
    left out, and the pixels column is scored from its own input."""
    rng = np.random.default_rng(1)
    state = np.zeros((300, 39))
    state[:, 0:3] = rng.uniform(-0.3, 0.3, (300, 3))  # hand
    state[:, 36:38] = rng.uniform(-0.2, 0.2, (300, 2))  # goal x, y; its z stays 0
    latent = np.concatenate([state[:, 0:3], rng.normal(size=(300, 5))], axis=1)
    latent[:, :3] += 0.01 * rng.normal(size=(300, 3))
    rows = probe_rows("t", {"latent": latent, "pixels": state[:, 36:38].copy(), "state": state})
    by = {r["position"]: r for r in rows}
    assert set(by) == {"hand", "goal"} and by["goal"]["axes"] == "xy"
    assert min(by["hand"]["latent_r2"]) > 0.99 and max(by["goal"]["latent_r2"]) < 0.1
    # The pixel probe's penalty (10x, for thousands of pooled inputs) shrinks two exact ones.
    assert min(by["goal"]["pixels_r2"]) > 0.85


def test_a_position_tied_to_another_scores_from_the_other_positions():
    """pick-cube's goal floats over its cube: a latent that held only the goal would give the
    cube too, which `others_r2` says; an independent position scores near 0 there. An older
    probe.json without the column renders without it."""
    rng = np.random.default_rng(2)
    state = np.zeros((400, 39))
    state[:, 0:3] = rng.uniform(-0.3, 0.3, (400, 3))  # hand, independent
    state[:, 4:6] = rng.uniform(-0.12, 0.12, (400, 2))  # cube x, y
    state[:, 36:38] = state[:, 4:6] + rng.uniform(-0.03, 0.03, (400, 2))  # goal over it
    latent = np.concatenate([state[:, 36:38], rng.normal(size=(400, 4))], axis=1)  # goal only
    rows = {r["position"]: r for r in probe_rows("t", {"latent": latent, "pixels": latent,
                                                        "state": state})}  # fmt: skip
    assert min(rows["object"]["latent_r2"]) > 0.8  # the latent "gives" the cube...
    assert min(rows["object"]["others_r2"]) > 0.8  # ...as the goal alone does
    assert max(rows["hand"]["others_r2"]) < 0.1
    # A coordinate of another position that hardly varies in the fitted frames and jumps in
    # the held-out ones (a drawer the walk nudged) is left out, not scaled up: the hand's
    # score stays near 0 instead of far below it.
    nudged = state.copy()
    nudged[:320, 38] = 1e-4 * rng.normal(size=320)
    nudged[320:, 38] = 0.05
    assert min(others_r2(nudged, "hand")) > -0.1
    table = markdown({"rows": list(rows.values())})
    assert "from the other positions |" in table.splitlines()[0]
    old = [{k: v for k, v in r.items() if k != "others_r2"} for r in rows.values()]
    assert "other positions" not in markdown({"rows": old})


def planted_squares(n: int, classes: int = 1, side: int = 16, square: int = 3, seed: int = 0):
    """`n` noisy RGB images (n, 3, side, side), each with a bright square at a random place in
    the colour channel of its class (frame i is of class i % classes): (images, class, the
    square's row and column)."""
    rng = np.random.default_rng(seed)
    label = np.arange(n) % classes
    where = rng.integers(0, side - square + 1, (n, 2))
    images = 0.05 * rng.normal(size=(n, 3, side, side))
    for i, (row, col) in enumerate(where):
        images[i, label[i], row : row + square, col : col + square] += 1.0
    return images, label, where.astype(np.float64)


def pooled(images: np.ndarray) -> np.ndarray:
    """Images average-pooled 2x and flattened, as the pixel probe sees its frames."""
    n, channels, side, _ = images.shape
    return images.reshape(n, channels, side // 2, 2, side // 2, 2).mean((3, 5)).reshape(n, -1)


def test_probe_recovers_a_planted_square_only_from_a_latent_that_keeps_the_image():
    """A latent that mixes the (pooled) image into every unit gives the square's place; one
    that ignores the image does not. The square's place is the 'object' of the state."""
    images, _, where = planted_squares(300)
    rng = np.random.default_rng(1)
    mixing = np.linalg.qr(rng.normal(size=(3 * 64, 3 * 64)))[0]  # invertible: loses nothing
    latents = {"keeps": pooled(images) @ mixing, "ignores": rng.normal(size=(300, 3 * 64))}
    state = np.zeros((300, 39))
    state[:, 4:6] = where  # its height never varies: z is left out
    for name, latent in latents.items():
        rows = probe_rows("t", {"latent": latent, "pixels": pooled(images), "state": state})
        (row,) = rows
        assert row["position"] == "object" and row["axes"] == "xy"
        assert min(row["pixels_r2"]) > 0.9
        if name == "keeps":
            assert min(row["latent_r2"]) > 0.9, row
        else:
            assert max(row["latent_r2"]) < 0.1, row


def test_classifier_tells_a_planted_colour_apart_only_from_a_latent_that_keeps_colour():
    """Three classes whose square differs only in colour: the pooled colour image tells them
    apart, its grey image (the channels summed) is at chance."""
    images, label, _ = planted_squares(450, classes=3)
    grey = images.sum(1, keepdims=True)
    in_colour = ridge_accuracy([pooled(images[label == c]) for c in range(3)])
    in_grey = ridge_accuracy([pooled(grey[label == c]) for c in range(3)])
    assert in_colour > 0.95 and abs(in_grey - 1 / 3) < 0.1, (in_colour, in_grey)


def test_classification_rows_cover_each_same_from_state_group_probed_twice_or_more():
    """BinPnP's group probed on three of its four tasks is one 3-way row; PnPBlock's blue block
    alone, and a task of no group, make none."""
    images, label, _ = planted_squares(300, classes=3)
    bins = ["bin-red-blue", "bin-yellow-blue", "bin-red-purple"]
    data = {t: {"latent": pooled(images[label == c]), "pixels": pooled(images[label == c])}
            for c, t in enumerate(bins)}  # fmt: skip
    (row,) = classification_rows([*bins, "pnp-blue-block", "reach-xy"], data)
    assert row["suite"] == "BinPnP" and row["tasks"] == bins and row["frames"] == 100
    assert row["chance"] == pytest.approx(1 / 3)
    assert row["latent_accuracy"] > 0.95 and row["pixels_accuracy"] > 0.95


def test_select_tasks_takes_every_task_of_the_suites_and_the_tasks_named_once_each():
    assert select_tasks("PnPBlock", "stack-blocks, reach-xy") == (
        ["PnPBlock"], ["pnp-red-block", "pnp-blue-block", "stack-blocks", "reach-xy"])  # fmt: skip
    suites, tasks = select_tasks("all", None)
    assert suites == list(SUITES) and tasks.count("pnp-cube") == 1
    assert set(tasks) == {t for s in SUITES.values() for t in s.task_ids}
    assert select_tasks(None, "reach-xy") == ([], ["reach-xy"])
    with pytest.raises(InputError, match="give --suites or --tasks"):
        select_tasks(" ", None)


def test_a_published_probe_reads_back_to_its_table():
    """probe.json files published before the classification still give their probe.md."""
    published = sorted(PUBLISHED.glob("*/probe.json"))
    assert published
    for path in published:
        assert markdown(json.loads(path.read_text())) == (path.parent / "probe.md").read_text()


@pytest.fixture
def encoder_path(tmp_path):
    from ccfit.models.encoders import build_encoder, save_encoder
    from ccfit.models.tdmpc2 import TDMPC2Config

    cfg = TDMPC2Config.preset("smoke", obs_mode="pixels", image_size=SIZE)
    torch.manual_seed(0)
    path = tmp_path / "enc.safetensors"
    save_encoder(build_encoder(cfg), cfg, path)
    return path


def test_a_probe_folder_holds_its_encoders_sidecar_as_published(tmp_path):
    """The probed weights' sidecar goes beside the probe as encoder.json, named as probed and
    with no path of this machine, so the folder goes into results/probe/ as is."""
    from ccfit.models.encoders import build_encoder, save_encoder, sidecar_path
    from ccfit.models.tdmpc2 import TDMPC2Config

    result = json.loads((PUBLISHED / "all-per-camera" / "probe.json").read_text())
    cfg = TDMPC2Config.preset("smoke", obs_mode="pixels", image_size=SIZE)
    first = tmp_path / "first-name.safetensors"
    save_encoder(build_encoder(cfg), cfg, first, metadata={"config": {"out": str(first)}})
    renamed = tmp_path / "renamed.safetensors"
    first.rename(renamed)
    sidecar_path(first).rename(sidecar_path(renamed))
    paths = write_probe(result, tmp_path / "probe", probed_sidecar(renamed))
    assert [p.name for p in paths] == ["probe.json", "probe.md", "encoder.json"]
    text = (tmp_path / "probe" / "encoder.json").read_text()
    published, own = json.loads(text), json.loads(sidecar_path(renamed).read_text())
    assert str(tmp_path) not in text and published["config"]["out"] == "first-name.safetensors"
    assert own["weights"] == "first-name.safetensors"
    assert published["weights"] == "renamed.safetensors"
    same = ("format", "spec", "weights_sha256")
    assert {k: published[k] for k in same} == {k: own[k] for k in same}
    older = tmp_path / "older.pt"  # the older single-file format has no sidecar
    save_encoder(build_encoder(cfg), cfg, older)
    assert probed_sidecar(older) is None


def test_a_damaged_sidecar_stops_the_probe_in_one_line(encoder_path, tmp_path, capsys):
    from ccfit.models.encoders import sidecar_path

    sidecar_path(encoder_path).write_text("{not json")
    code = main(["probe-encoder", str(encoder_path), "--tasks", "reach-xy", "--frames", "10",
                 "--out", str(tmp_path / "probe")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "cannot read encoder sidecar" in err
    assert not (tmp_path / "probe").exists()  # stopped before the probe ran


@pytest.mark.integration
def test_probe_reports_the_positions_each_task_varies(encoder_path, tmp_path, capsys):
    out = tmp_path / "probe"
    assert main(["probe-encoder", str(encoder_path), "--tasks", "reach-xy,reach-xyz",
                 "--frames", "30", "--out", str(out)]) == 0  # fmt: skip
    result = json.loads((out / "probe.json").read_text())
    # the encoder by name and content: no path of the machine that probed it
    assert result["encoder"] == "enc.safetensors" and str(tmp_path) not in json.dumps(result)
    assert result["encoder_sha256"] == hashlib.sha256(encoder_path.read_bytes()).hexdigest()
    rows = {(r["task"], r["position"]): r for r in result["rows"]}
    # Reach has no object; reach-xy's goal moves in x and y only, reach-xyz's in all three.
    assert set(rows) == {(t, p) for t in ("reach-xy", "reach-xyz") for p in ("hand", "goal")}
    assert rows["reach-xy", "goal"]["axes"] == "xy" and rows["reach-xyz", "goal"]["axes"] == "xyz"
    assert rows["reach-xy", "hand"]["axes"] == "xyz"
    for r in rows.values():
        assert len(r["latent_r2"]) == len(r["pixels_r2"]) == len(r["others_r2"]) == len(r["axes"])
    table = (out / "probe.md").read_text()
    assert table in capsys.readouterr().out and table.count("\n") == 2 + len(rows)
    assert (
        json.loads((out / "encoder.json").read_text())["weights_sha256"] == result["encoder_sha256"]
    )


@pytest.mark.integration
def test_workers_collect_the_same_probe_as_one_process(encoder_path, tmp_path, monkeypatch):
    """`--workers 2` collects each task in a spawned process: the same frames and latents, so
    the same probe.json, as one process collecting them in turn."""
    import ccfit.analysis.encoder_probe as probe

    results = []
    for workers in ("1", "2"):
        if workers == "2":  # the spawned workers import the module afresh: this is not theirs
            monkeypatch.setattr(probe, "collect", None)
        out = tmp_path / f"w{workers}"
        assert main(["probe-encoder", str(encoder_path), "--tasks", "reach-xy,pick-cube",
                     "--frames", "10", "--workers", workers, "--out", str(out)]) == 0  # fmt: skip
        results.append((out / "probe.json").read_text())
    assert results[0] == results[1]
    assert {r["task"] for r in json.loads(results[1])["rows"]} == {"reach-xy", "pick-cube"}


def test_the_states_alone_are_those_of_the_rendered_frames(encoder_path):
    """`collect_states` reads the frames `collect` renders (same layouts and walks), so a
    published probe's `others_r2` can be computed again without its encoder."""
    from ccfit.analysis.encoder_probe import collect, collect_states
    from ccfit.models.encoders import load_frozen_encoder

    encoder, _ = load_frozen_encoder(encoder_path)
    rendered = collect(encoder, "pick-cube", frames=4, image_size=SIZE, walk=30, seed=3)
    assert np.array_equal(collect_states("pick-cube", frames=4, walk=30, seed=3),
                          rendered["state"])  # fmt: skip


def test_probe_tells_which_block_of_pnpblock_a_frame_shows(encoder_path, tmp_path, capsys):
    """`--suites PnPBlock`: its three tasks' positions, and one classification of its two
    blocks (one MDP from state) from the frames the positions were probed on."""
    out = tmp_path / "probe"
    assert main(["probe-encoder", str(encoder_path), "--suites", "PnPBlock", "--frames", "10",
                 "--out", str(out)]) == 0  # fmt: skip
    result = json.loads((out / "probe.json").read_text())
    assert result["suites"] == ["PnPBlock"]
    assert result["tasks"] == ["pnp-red-block", "pnp-blue-block", "stack-blocks"]
    probed = {(r["task"], r["position"]) for r in result["rows"]}
    assert {("pnp-red-block", "object"), ("stack-blocks", "object 2")} <= probed
    (row,) = result["classification"]
    assert row["suite"] == "PnPBlock" and row["tasks"] == ["pnp-red-block", "pnp-blue-block"]
    assert row["frames"] == 10 and row["chance"] == 0.5
    # the blocks' colours are in the frames; the random encoder's latent is scored, not judged
    assert row["pixels_accuracy"] == 1.0 and 0 <= row["latent_accuracy"] <= 1
    table = (out / "probe.md").read_text()
    assert table in capsys.readouterr().out
    assert "| PnPBlock | pnp-red-block, pnp-blue-block | 10 |" in table


@pytest.mark.parametrize("args, message", [
    (["--tasks", "reach-qq"], "unknown task 'reach-qq'"),
    (["--suites", "Reach,Nope"], "unknown suite 'Nope'"),
    (["--suites", "Reach", "--tasks", "reach-qq"], "unknown task 'reach-qq'"),
    ([], "give --suites or --tasks"),
    (["--tasks", "reach-xy", "--frames", "5"], "--frames must be at least 10"),
    (["--tasks", "reach-xy", "--torch-threads", "-1"], "--torch-threads must be >= 0"),
    (["--tasks", "reach-xy", "--workers", "0"], "--workers must be >= 1"),
])  # fmt: skip
def test_bad_input_is_one_line_and_exit_2(args, message, encoder_path, tmp_path, capsys):
    code = main(["probe-encoder", str(encoder_path), *args, "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    code = main(["probe-encoder", str(tmp_path / "none.safetensors"), "--tasks", "reach-xy",
                 "--out", str(tmp_path / "p")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "encoder checkpoint not found" in err, err


@pytest.mark.parametrize("given, during", [([], 1), (["--torch-threads", "2"], 2)])
def test_the_probe_runs_on_the_threads_it_is_given_and_gives_them_back(
        given, during, encoder_path, tmp_path, monkeypatch):  # fmt: skip
    import torch

    import ccfit.analysis.encoder_probe as probe

    class Probed(Exception):
        pass

    seen = []

    def fake_probe(*args, **kwargs):
        seen.append(torch.get_num_threads())
        raise Probed

    before = torch.get_num_threads()
    monkeypatch.setattr(probe, "probe_encoder", fake_probe)
    with pytest.raises(Probed):
        main(["probe-encoder", str(encoder_path), "--tasks", "reach-xy", *given,
              "--out", str(tmp_path / "p")])  # fmt: skip
    assert seen == [during] and torch.get_num_threads() == before
