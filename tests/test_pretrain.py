"""Autoencoder pretraining of the frozen encoder (`ccfit.pretrain`) on a tiny real dataset."""

import argparse
import hashlib
import json
import shutil

import numpy as np
import pytest
import torch

from ccfit.config_base import ENCODER_RECORD, ConfigError
from ccfit.pretrain import PretrainConfig, add_pretrain_parser, config_from_args, pretrain_encoder
from ccfit.pretrain.data import episode_arrays, load_frames, split_episodes

SIZE = 32
STEPS = 40


@pytest.fixture(scope="module")
def reach_root(tmp_path_factory):
    """A real Reach suite dataset: one 8-step oracle episode per task (4 episodes), 32 px."""
    from ccdata.record import GenerateConfig, generate

    root = tmp_path_factory.mktemp("data") / "Reach"
    generate(
        GenerateConfig(suite="Reach", episodes=1, explore_episodes=0, image_size=SIZE,
                       max_steps=8, root=root),
        progress=False,
    )  # fmt: skip
    return root


def make_config(root, **overrides):
    base = dict(
        suites="Reach",
        dataset_roots={"Reach": str(root)},
        image_size=SIZE,
        steps=STEPS,
        checkpoint_interval=10,
        log_interval=5,
        holdout=0.25,
        device="cpu",
    )
    return PretrainConfig.preset("smoke", **{**base, **overrides})


def weights(path):
    from safetensors.torch import load_file

    return load_file(str(path))


def test_loss_falls_split_and_sidecar(reach_root, tmp_path):
    out = tmp_path / "enc.safetensors"
    metrics = pretrain_encoder(make_config(reach_root), out, progress=False)
    side = json.loads(out.with_suffix(".json").read_text())

    history = np.array(side["history"])
    assert history[:, 0].tolist() == list(range(5, STEPS + 1, 5))
    assert history[-2:, 1].mean() < 0.6 * history[:2, 1].mean()  # training loss falls
    held, init = metrics["heldout"], metrics["heldout_initial"]
    # 8 steps and the recorded final observation
    assert held["frames"] == 9 and held["image_mse"] < 0.7 * init["image_mse"]
    for cam in ("topview", "frontview", "gripperPOV"):
        assert 0 < held["cameras"][cam]["mse"] < init["cameras"][cam]["mse"]
        assert held["cameras"][cam]["psnr_db"] == pytest.approx(
            10 * np.log10(1 / held["cameras"][cam]["mse"])
        )

    # episode split: disjoint, complete, recorded
    data = side["data"]
    key = lambda e: (e["suite"], e["episode_index"])  # noqa: E731
    held_keys, train_keys = {key(e) for e in data["held_out"]}, {key(e) for e in data["train"]}
    assert len(held_keys) == 1 and len(train_keys) == 3 and not held_keys & train_keys
    assert held_keys | train_keys == {("Reach", i) for i in range(4)}
    assert data["frames"] == {"train": 27, "heldout": 9}  # 9 frames an episode: 8 + final
    suite = data["suites"][0]
    assert suite["repo_id"] == "ccdata/Reach" and suite["root"] == str(reach_root.resolve())
    assert sum(suite["oracle_episodes"].values()) == 4 == suite["total_episodes"]
    assert suite["generated_with"]["suite"] == "Reach"
    assert side["spec"]["latent_dim"] == make_config(reach_root).encoder_config().latent_dim
    assert side["seed"] == 0 and torch.__version__.startswith(side["versions"]["torch"])
    assert side["metrics"] == json.loads(json.dumps(metrics))

    # a finished run is not redone; other settings at the same path are refused
    mtime = out.stat().st_mtime_ns
    again = pretrain_encoder(make_config(reach_root), out, progress=False)
    assert again == side["metrics"] and out.stat().st_mtime_ns == mtime
    with pytest.raises(ValueError, match="other settings"):
        pretrain_encoder(make_config(reach_root, steps=STEPS + 1), out, progress=False)


def test_foreground_weighting_trains_and_reports_the_foreground(reach_root, tmp_path):
    """With `foreground_weight` the loss still falls, the sidecar records the foreground's own
    reconstruction error (it is reported for every run) and the settings; a policy the dataset
    lacks is one line naming the command that generates it."""
    out = tmp_path / "enc.safetensors"
    metrics = pretrain_encoder(make_config(reach_root, foreground_weight=10.0), out,
                               progress=False)  # fmt: skip
    side = json.loads(out.with_suffix(".json").read_text())
    fg, init = metrics["heldout"]["foreground"], metrics["heldout_initial"]["foreground"]
    assert 0 < fg["fraction"] < 1 and fg["mse"] < init["mse"]
    assert side["identity"]["foreground_weight"] == 10.0
    assert "foreground_weight" in side["objective"]
    # the episode-contrastive term: trains, is recorded, keeps its head out of the encoder
    out = tmp_path / "contrast.safetensors"
    pretrain_encoder(make_config(reach_root, contrastive_coef=1.0), out, progress=False)
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["identity"]["contrastive_coef"] == 1.0 and "InfoNCE" in side["objective"]
    assert not any(k.startswith("head") for k in weights(out))
    with pytest.raises(ValueError, match=r"no random episodes .*--explore-episodes"):
        load_frames(make_config(reach_root, policies="oracle,random"))


def test_resume_equals_uninterrupted_and_frozen_round_trip(reach_root, tmp_path):
    from ccfit.models.encoders import build_encoder, load_frozen_encoder
    from ccfit.models.tdmpc2 import TDMPC2, TDMPC2Config

    # with the recipe's terms, whose other frames are drawn from the resumed sample stream
    config = make_config(reach_root, foreground_weight=5.0, contrastive_coef=1.0)
    full = tmp_path / "full.safetensors"
    pretrain_encoder(config, full, progress=False)

    # Interrupted at step 25 (Ctrl-C writes a checkpoint); then, as after a SIGKILL, the
    # periodic checkpoint of step 20 is all that is left. Rerunning resumes from it.
    cut = tmp_path / "cut.safetensors"
    ckpt = cut.with_suffix(".ckpt.pt")
    backup = tmp_path / "step20.pt"

    def interrupt(step, loss):
        if step == 21:
            shutil.copy(ckpt, backup)
        if step == 25:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        pretrain_encoder(config, cut, progress=False, on_step=interrupt)
    assert not cut.exists() and torch.load(ckpt, weights_only=False)["step"] == 25
    shutil.copy(backup, ckpt)
    assert torch.load(ckpt, weights_only=False)["step"] == 20
    pretrain_encoder(config, cut, progress=False)
    assert not ckpt.exists()  # removed once the result is written
    a, b = weights(full), weights(cut)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    side_a = json.loads(full.with_suffix(".json").read_text())
    side_b = json.loads(cut.with_suffix(".json").read_text())
    assert side_a["history"] == side_b["history"]
    assert side_a["metrics"]["heldout"] == side_b["metrics"]["heldout"]

    # Round trip: the trained model state (a checkpoint at the last step) -> safetensors ->
    # load_frozen_encoder gives the same function, with no trainable parameter.
    last = tmp_path / "last.safetensors"

    def stop_at_end(step, loss):
        if step == STEPS:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        pretrain_encoder(config, last, progress=False, on_step=stop_at_end)
    state = torch.load(last.with_suffix(".ckpt.pt"), weights_only=False)["model"]
    trained = build_encoder(config.encoder_config())
    trained.load_state_dict({k[len("encoder."):]: v for k, v in state.items()
                             if k.startswith("encoder.")})  # fmt: skip
    trained.eval()
    pretrain_encoder(config, last, progress=False)  # finishes without further steps
    frozen, spec = load_frozen_encoder(last)
    assert not any(p.requires_grad for p in frozen.parameters())
    frozen.train()
    assert not frozen.training and not frozen.encoder.training
    gen = torch.Generator().manual_seed(0)
    obs = {"pixels": torch.randint(0, 256, (5, 9, SIZE, SIZE), dtype=torch.uint8, generator=gen),
           "proprio": torch.randn(5, 7, generator=gen)}  # fmt: skip
    with torch.no_grad():
        assert torch.equal(frozen(obs), trained(obs))
    assert torch.equal(frozen(obs), load_frozen_encoder(full)[0](obs))  # same run, same weights
    # it plugs into the TD-MPC2 preset it was made for
    model = TDMPC2(TDMPC2Config.preset("smoke", obs_mode="pixels", image_size=SIZE), device="cpu",
                   encoder=frozen)  # fmt: skip
    assert spec["latent_dim"] == model.cfg.latent_dim
    assert model.encode(obs).shape == (5, model.cfg.latent_dim)


def test_dataset_frames_match_live_render(reach_root):
    """A dataset frame and the live render of the same step give (nearly) the same encoder
    input: same layout through `ccfit.obs`, only the video codec's rounding differs."""
    from ccdata import make_env
    from ccdata.dataset_format import read_ccdata_metadata
    from ccdata.render import RenderSettings
    from ccfit.data import load_episodes
    from ccfit.obs import obs_to_arrays

    episode = load_episodes(reach_root, task="reach-xz", policy="oracle")[0]
    pixels, proprio = episode_arrays(episode)
    render = RenderSettings(**read_ccdata_metadata(reach_root)["render"])
    env = make_env("reach-xz", image_size=SIZE, render_settings=render)
    try:
        obs, _ = env.reset(seed=int(episode["episode_seed"][0]))
        diffs = []
        for t, action in enumerate(episode["action"]):
            live = obs_to_arrays(obs, "pixels")
            assert live["pixels"].shape == pixels[t].shape == (9, SIZE, SIZE)
            assert live["pixels"].dtype == pixels[t].dtype == np.uint8
            np.testing.assert_allclose(live["proprio"], proprio[t], atol=1e-6)
            diffs.append(np.abs(live["pixels"].astype(int) - pixels[t].astype(int)))
            obs, *_ = env.step(action)
    finally:
        env.close()
    diffs = np.stack(diffs)
    assert diffs.mean() < 0.5 and diffs.max() <= 3, (diffs.mean(), diffs.max())
    # the cameras are in the same channel slots (a swap would give large errors)
    per_cam = diffs.reshape(len(diffs), 3, 3, SIZE, SIZE).mean(axis=(0, 2, 3, 4))
    assert per_cam.max() < 0.5


def test_missing_datasets_name_the_command(reach_root, tmp_path):
    config = PretrainConfig.preset(
        "smoke", suites="Reach,Grasp,BinPnP", image_size=SIZE,
        dataset_roots={"Reach": str(reach_root), "Grasp": str(tmp_path / "no" / "Grasp"),
                       "BinPnP": str(tmp_path / "no" / "BinPnP")},
    )  # fmt: skip
    with pytest.raises(ValueError) as err:
        pretrain_encoder(config, tmp_path / "enc.safetensors", progress=False)
    msg = str(err.value)
    assert "\n" not in msg
    assert f"ccdata generate --suite Grasp --root {tmp_path / 'no' / 'Grasp'}" in msg
    assert f"ccdata generate --suite BinPnP --root {tmp_path / 'no' / 'BinPnP'}" in msg
    assert "Reach" not in msg.split("run:")[1]
    assert not (tmp_path / "enc.safetensors").exists()
    # at the default location the command needs no --root
    default = PretrainConfig.preset("smoke", suites="PnPBlock")
    if not (default.resolved_roots()["PnPBlock"] / "meta").exists():
        with pytest.raises(ValueError, match=r"run: ccdata generate --suite PnPBlock$"):
            pretrain_encoder(default, tmp_path / "enc.safetensors", progress=False)
    # a dataset at another image size is refused with the fix
    with pytest.raises(ValueError, match="--image-size 64"):
        load_frames(make_config(reach_root, image_size=64))


VALID_SUITES = "Reach, Grasp, BinPnP, PnPBlock, DrawerPnP, PnPBoxClose or 'all'"


@pytest.mark.parametrize("args, message", [
    (["--suites", "Reach"], "missing suite dataset(s) Reach (looked in {home}/ccdata/Reach); "
                            "run: ccdata generate --suite Reach"),
    (["--suites", "Nope"], f"unknown suite(s) ['Nope']; valid: {VALID_SUITES}"),
    (["--preset", "huge"], "unknown preset 'huge'; valid: smoke, cpu, paper"),
    (["--steps", "0"], "PretrainConfig.steps must be >= 1, got 0"),
    (["--device", "tpu"], "PretrainConfig: device must be 'auto', 'cpu', 'cuda' or 'cuda:N', "
                          "got 'tpu'"),
    (["--out", "{home}/enc.pt"], "--out must end in .safetensors, got {home}/enc.pt"),
    (["--model", "dreamerv3"], "model 'dreamerv3' does not build the shared pixel encoder; "
                               "models that do: pwm, tdmpc2"),
    (["--model", "nope"], "unknown model 'nope'; valid: {models}"),
    (["--batch-from", "task"], "PretrainConfig: batch_from must be one of ('all', 'suite')"),
])  # fmt: skip
def test_bad_input_is_one_line_and_exit_2(args, message, tmp_path, monkeypatch, capsys):
    """With no dataset in LeRobot's cache ($HF_LEROBOT_HOME, read when LeRobot is imported)."""
    from ccfit.cli import main

    monkeypatch.setattr("lerobot.utils.constants.HF_LEROBOT_HOME", tmp_path)
    monkeypatch.chdir(tmp_path)  # the default --out is relative
    from ccfit.models import model_names

    args = [a.format(home=tmp_path) for a in args]
    assert main(["pretrain-encoder", "--quiet", *args]) == 2
    message = message.format(home=tmp_path, models=", ".join(model_names()))
    assert capsys.readouterr().err == f"ccfit: error: {message}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_bad_datasets_and_outputs_are_one_line_and_exit_2(
    reach_root, tmp_path, monkeypatch, capsys
):
    """A dataset of another image size or with a corrupt meta/ccdata.json in LeRobot's cache,
    and an --out whose sidecar is corrupt."""
    from ccfit.cli import main

    home = tmp_path / "home"
    shutil.copytree(reach_root, home / "ccdata" / "Reach")
    monkeypatch.setattr("lerobot.utils.constants.HF_LEROBOT_HOME", home)
    out = str(tmp_path / "enc.safetensors")
    command = ["pretrain-encoder", "--quiet", "--preset", "smoke", "--out", out]

    def error(*args: str) -> str:
        assert main([*command, *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith("ccfit: error: ") and err.count("\n") == 1
        return err

    reach = str(home / "ccdata" / "Reach")
    assert f"dataset {reach} (Reach) has 32 px images but the encoder is for 64 px" in error(
        "--suites", "Reach"
    )
    (home / "ccdata" / "Grasp" / "meta").mkdir(parents=True)
    (home / "ccdata" / "Grasp" / "meta" / "ccdata.json").write_text("{")
    assert f"cannot read dataset {home / 'ccdata/Grasp'} (Grasp)" in error(
        "--suites", "Grasp", "--image-size", str(SIZE)
    )
    (tmp_path / "enc.safetensors").write_bytes(b"")
    (tmp_path / "enc.json").write_text("{")
    assert f"cannot read encoder sidecar {tmp_path / 'enc.json'}" in error("--suites", "Reach")


def test_shared_task_counted_once(reach_root, tmp_path):
    """A suite whose tasks were already read from an earlier suite adds no episodes (the
    pnp-cube case). A copy of the Reach dataset, relabelled, stands in for a later suite here;
    `test_shared_pnp_cube_read_once` (slow) checks the real suites."""
    later = tmp_path / "Later"
    shutil.copytree(reach_root, later)
    meta_path = later / "meta" / "ccdata.json"
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({**meta, "suite": "Grasp"}))
    with pytest.raises(ValueError, match="holds suite 'Grasp', not 'BinPnP'"):
        load_frames(make_config(reach_root, suites="BinPnP", dataset_roots={"BinPnP": str(later)}))
    config = make_config(
        reach_root,
        suites="Reach,Grasp",
        dataset_roots={"Reach": str(reach_root), "Grasp": str(later)},
    )
    store, manifest = load_frames(config)
    assert len(store.episodes) == 4 and {e["suite"] for e in store.episodes} == {"Reach"}
    assert [m["suite"] for m in manifest] == ["Reach", "Grasp"]
    assert manifest[1]["oracle_episodes"] == {}
    assert set(manifest[1]["shared_tasks_read_elsewhere"]) == {
        "reach-xy",
        "reach-xz",
        "reach-yz",
        "reach-xyz",
    }


@pytest.mark.slow
def test_shared_pnp_cube_read_once(tmp_path):
    """pnp-cube is in Grasp and DrawerPnP: its episodes come from Grasp only."""
    from ccdata.record import GenerateConfig, generate

    roots = {}
    for suite in ("DrawerPnP", "Grasp"):
        roots[suite] = str(tmp_path / suite)
        generate(GenerateConfig(suite=suite, episodes=1, explore_episodes=0, image_size=SIZE,
                                max_steps=2, root=roots[suite]), progress=False)  # fmt: skip
    config = make_config(tmp_path, suites="DrawerPnP,Grasp", dataset_roots=roots)
    store, manifest = load_frames(config)
    tasks = [(e["suite"], e["task_id"]) for e in store.episodes]
    assert sorted(tasks) == sorted([("Grasp", "pick-cube"), ("Grasp", "place-cube"),
                                    ("Grasp", "pnp-cube"), ("DrawerPnP", "drawer-open"),
                                    ("DrawerPnP", "drawer-pnp")])  # fmt: skip
    assert manifest[1]["shared_tasks_read_elsewhere"] == {"pnp-cube": "Grasp"}


def test_split_is_seeded_per_task_and_disjoint():
    eps = [{"task_id": t, "episode_index": i} for i, t in enumerate(["a"] * 10 + ["b"] * 20)]
    train, held = split_episodes(eps, 0.1, seed=0)
    assert sorted(train + held) == list(range(30)) and not set(train) & set(held)
    assert sum(eps[i]["task_id"] == "a" for i in held) == 1
    assert sum(eps[i]["task_id"] == "b" for i in held) == 2
    assert split_episodes(eps, 0.1, seed=0) == (train, held)
    assert any(split_episodes(eps, 0.1, seed=s)[1] != held for s in range(1, 5))
    assert split_episodes(eps, 0.0, seed=0) == (list(range(30)), [])
    # too few episodes per task for the fraction: still one held out overall
    assert len(split_episodes(eps[:1] + eps[10:11], 0.1, seed=0)[1]) == 1


def test_batch_sampler_draws_one_suite_per_batch_in_proportion():
    from ccfit.pretrain.data import BatchSampler, FrameStore

    lengths = {"Reach": [30, 10], "Grasp": [20]}  # frames: Reach 40, Grasp 20
    eps = [{"suite": s, "task_id": f"{s}-{i}"} for s, ls in lengths.items() for i in range(len(ls))]
    sizes = [n for ls in lengths.values() for n in ls]
    store = FrameStore([np.zeros((n, 1, 1, 1), np.uint8) for n in sizes],
                       [np.zeros((n, 7), np.float32) for n in sizes], eps)  # fmt: skip
    pairs = store.index([0, 1, 2])
    suite_of = np.array([e["suite"] for e in eps])
    # 'all' draws exactly as uniform indexing into the pairs did (encoders made before it)
    a, b = np.random.default_rng(0), np.random.default_rng(0)
    assert np.array_equal(BatchSampler(store, pairs, "all")(16, a), pairs[b.integers(0, 60, 16)])
    sample, rng = BatchSampler(store, pairs, "suite"), np.random.default_rng(0)
    batches = [sample(8, rng) for _ in range(600)]
    assert all(len(set(suite_of[batch[:, 0]])) == 1 for batch in batches)
    reach = np.mean([suite_of[batch[0, 0]] == "Reach" for batch in batches])
    assert abs(reach - 40 / 60) < 0.06  # in proportion to the suites' frames
    counts = np.bincount(np.concatenate(batches)[:, 0], minlength=3) / (600 * 8)
    assert np.allclose(counts, [30 / 60, 10 / 60, 20 / 60], atol=0.04)  # each frame as likely


def test_config_and_parser():
    from ccfit.models.tdmpc2 import TDMPC2Config

    parser = argparse.ArgumentParser()
    add_pretrain_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["pretrain-encoder", "--preset", "smoke", "--steps", "7",
                              "--seed", "3", "--suites", "Reach,Grasp"])  # fmt: skip
    config = config_from_args(args)
    assert (config.steps, config.seed, config.suites) == (7, 3, ("Reach", "Grasp"))
    assert callable(args.func)
    args = parser.parse_args(["pretrain-encoder", "--decoder-channels", "32", "--augment-shift",
                              "0", "--lr", "1e-3", "--batch-size", "8",
                              "--batch-from", "suite"])  # fmt: skip
    config = config_from_args(args)
    assert (config.decoder_channels, config.augment_shift, config.lr, config.batch_size,
            config.steps) == (32, 0, 1e-3, 8, PretrainConfig.preset("cpu").steps)  # fmt: skip
    assert config.batch_from == "suite" and "batch_from" in config.identity()
    assert "batch_from" not in PretrainConfig.preset("cpu").identity()  # older encoders' value
    # the model named as `ccfit run` names it, or as scripts have
    for spelt in ("--model.type", "--model"):
        assert parser.parse_args(["pretrain-encoder", spelt, "pwm"]).model == "pwm"
    args = parser.parse_args(["pretrain-encoder"])
    config = config_from_args(args)
    assert config.decoder_channels == PretrainConfig.preset("cpu").decoder_channels == 16
    # the recipe's trunk, recorded as the encoder's (a stacked encoder's sidecar has none)
    assert config.encoder_config().image_trunk == "per-camera"
    assert config.identity()["image_trunk"] == "per-camera"
    assert PretrainConfig.preset("paper").image_trunk == "per-camera"
    assert config.suites == tuple(__import__("ccdata").SUITES) and config.model_preset == "cpu"
    enc, ref = config.encoder_config(), TDMPC2Config.preset("cpu", obs_mode="pixels")
    assert (enc.latent_dim, enc.enc_dim, enc.num_channels, enc.num_enc_layers) == (
        ref.latent_dim,
        ref.enc_dim,
        ref.num_channels,
        ref.num_enc_layers,
    )
    with pytest.raises(ValueError, match="valid: Reach"):
        config_from_args(parser.parse_args(["pretrain-encoder", "--suites", "Nope"]))
    with pytest.raises(ValueError, match="valid: smoke, cpu, paper"):
        config_from_args(parser.parse_args(["pretrain-encoder", "--preset", "huge"]))
    with pytest.raises(ValueError, match="steps must be >= 1"):
        PretrainConfig.preset("smoke", steps=0)
    with pytest.raises(ValueError, match="must end in .safetensors"):
        pretrain_encoder(PretrainConfig.preset("smoke"), "enc.pt", progress=False)


@pytest.mark.integration
def test_frozen_encoder_through_a_pixel_curriculum(reach_root, tmp_path, monkeypatch):
    """PWM + experts on pixels with a frozen encoder, seeded from the dataset: replay holds the
    encoder's latents (dataset and live episodes alike) and the encoder ends bit-identical."""
    import ccfit.curriculum as C
    import ccfit.train.run as R
    from ccfit.config import CurriculumConfig
    from ccfit.config_parse import resolve
    from ccfit.models.base import LATENT_KEY
    from ccfit.models.encoders import build_encoder, load_frozen_encoder, save_encoder
    from ccfit.models.tdmpc2 import TDMPC2Config
    from ccfit.runner import run_reference

    enc_cfg = TDMPC2Config.preset("smoke", obs_mode="pixels", image_size=SIZE)
    torch.manual_seed(0)
    path = tmp_path / "enc.safetensors"
    save_encoder(build_encoder(enc_cfg), enc_cfg, path)
    buffers = []

    class SpyBuffer(R.ReplayBuffer):
        def add_episode(self, *args, **kwargs):
            super().add_episode(*args, **kwargs)
            buffers.append(self)

    monkeypatch.setattr(R, "ReplayBuffer", SpyBuffer)
    cfg = resolve(CurriculumConfig, {
        "suite": "Reach", "obs": "pixels", "image_size": SIZE, "preset": "smoke",
        "seed_dataset": str(reach_root), "encoder": f"frozen:{path}",
        "model": {"type": "pwm"}, "method": {"type": "experts"},
        "train": dict(steps=40, seed_steps=20, eval_interval=40, checkpoint_interval=40,
                      episode_steps=20),
    })  # fmt: skip
    result = C.Curriculum(cfg, tmp_path / "run", tmp_path / "scratch", progress=False).run()
    assert len(set(map(id, buffers))) == 5  # four tasks and the from-scratch reference
    for buf in buffers:
        assert set(buf._obs) == {LATENT_KEY}
        assert buf._obs[LATENT_KEY].shape[1:] == (enc_cfg.latent_dim,)
    assert all(np.isfinite(result[k]) for k in ("bwt", "fwt"))
    state = torch.load(tmp_path / "run" / C.STATE, map_location="cpu", weights_only=False)
    frozen, _ = load_frozen_encoder(path)
    for name, value in frozen.state_dict().items():
        assert torch.equal(state["model"][f"backbone.encoder.{name}"], value), name
    # The run and its reference record the encoder's bytes; another file at the same path is
    # refused on resume, by the run and by its finished reference alike.
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert json.loads((tmp_path / "run" / "config.json").read_text())[ENCODER_RECORD] == digest
    (reference,) = [p.parent for p in (tmp_path / "scratch").rglob("config.json")]
    assert json.loads((reference / "config.json").read_text())[ENCODER_RECORD] == digest
    torch.manual_seed(1)
    save_encoder(build_encoder(enc_cfg), enc_cfg, path)
    for run in (lambda: C.Curriculum(cfg, tmp_path / "run", tmp_path / "scratch",
                                     progress=False).run(),
                lambda: run_reference(C.OnlineTrack(cfg), reference, progress=False)):  # fmt: skip
        with pytest.raises(ConfigError, match="through another encoder file: .*enc.safetensors"):
            run()
    # validation reads no file: the run's start does
    other_size = resolve(
        CurriculumConfig,
        {
            "suite": "Reach",
            "obs": "pixels",
            "image_size": 48,
            "preset": "smoke",
            "encoder": f"frozen:{path}",
        },
    )
    with pytest.raises(ValueError, match="reads 32 px images but the run renders 48 px"):
        C.OnlineTrack(other_size)


def test_a_damaged_encoder_file_is_one_value_error_naming_it(tmp_path):
    """An encoder file with the right format tag but no settings or weights, settings that
    are not JSON, or weights of another size than its settings say: one line naming the file
    (before: a KeyError, an unnamed JSON error, torch's key list over several lines)."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    from ccfit.models.encoders import (
        ENCODER_FORMAT,
        build_encoder,
        load_frozen_encoder,
        save_encoder,
    )
    from ccfit.models.tdmpc2 import TDMPC2Config

    cfg = TDMPC2Config.preset("smoke", obs_mode="pixels", image_size=SIZE)
    good = tmp_path / "good.safetensors"
    save_encoder(build_encoder(cfg), cfg, good)
    with safe_open(str(good), framework="pt") as f:
        state = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - not a dict
        spec = json.loads(f.metadata()["spec"])
    wider = json.dumps({**spec, "latent_dim": spec["latent_dim"] * 2})
    cases = {
        "bare.pt": (lambda p: torch.save({"format": ENCODER_FORMAT}, p), "lacks its encoder"),
        "spec.safetensors": (lambda p: save_file(
            state, p, metadata={"format": ENCODER_FORMAT, "spec": "{nope"}),
            "its settings are not JSON"),
        "wider.safetensors": (lambda p: save_file(
            state, p, metadata={"format": ENCODER_FORMAT, "spec": wider}),
            "does not match its settings"),
    }  # fmt: skip
    for name, (write, needle) in cases.items():
        write(tmp_path / name)
        with pytest.raises(ValueError, match=needle) as err:
            load_frozen_encoder(tmp_path / name)
        assert str(tmp_path / name) in str(err.value) and "\n" not in str(err.value), name
