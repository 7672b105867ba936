"""The foreground weighting of encoder pretraining (`ccfit.pretrain.foreground`)."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ccfit.pretrain import PretrainConfig
from ccfit.pretrain.foreground import (
    backgrounds,
    foreground_mask,
    weighted_image_loss,
)

SIZE = 16


def scene_with_square(rng: np.random.Generator, background: np.ndarray) -> np.ndarray:
    """The background (9, S, S) with a 2 px white square at a random place in every camera."""
    frame = background.copy()
    y, x = rng.integers(0, SIZE - 2, 2)
    frame[:, y : y + 2, x : x + 2] = 255
    return frame


def test_the_background_is_the_empty_scene_and_the_mask_the_square():
    rng = np.random.default_rng(0)
    scene = rng.integers(0, 120, (9, SIZE, SIZE)).astype(np.uint8)
    episodes = [np.stack([scene_with_square(rng, scene) for _ in range(6)]) for _ in range(20)]
    records = [{"suite": "Reach"} for _ in episodes]
    bg, suite_of = backgrounds(episodes, records, list(range(20)), seed=0)
    assert bg.shape == (1, 9, SIZE, SIZE) and suite_of.tolist() == [0] * 20
    assert np.array_equal(bg[0], scene)  # the square is elsewhere in most frames

    frame = torch.from_numpy(episodes[3][2])[None]
    mask = foreground_mask(frame, torch.from_numpy(bg), threshold=0.08)
    square = (frame[0, :3] == 255).all(0)  # the first camera's white pixels
    assert mask.shape == (1, 3, SIZE, SIZE) and mask.dtype == torch.uint8
    assert torch.equal(mask[0, 0] > 0, square) and int(square.sum()) == 4


def test_the_weighted_loss_is_mse_without_foreground_and_counts_it_with():
    rng = torch.Generator().manual_seed(0)
    target = torch.rand(2, 9, SIZE, SIZE, generator=rng)
    rec = torch.rand(2, 9, SIZE, SIZE, generator=rng)
    none = torch.zeros(2, 3, SIZE, SIZE, dtype=torch.uint8)
    assert weighted_image_loss(rec, target, none, 50.0).item() == pytest.approx(
        F.mse_loss(rec, target).item()
    )
    # an error on one foreground pixel counts 1 + weight times one on the background
    rec = target.clone()
    rec[0, 0, 0, 0] += 0.5
    on = none.clone()
    on[0, 0, 0, 0] = 255
    plain = weighted_image_loss(rec, target, none, 9.0)
    weighted = weighted_image_loss(rec, target, on, 9.0)
    total_weight = 2 * 3 * SIZE * SIZE + 9.0  # pixels of the two frames' cameras, plus 9
    assert weighted.item() == pytest.approx(10 * 0.25 / (3 * total_weight))
    assert plain.item() == pytest.approx(0.25 / (2 * 9 * SIZE * SIZE))


def test_new_settings_at_their_legacy_values_leave_the_identity_as_before():
    """An encoder pretrained before the policies and foreground settings existed is still the
    run of those settings at their legacy values (its sidecar's identity has no such keys)."""
    legacy = PretrainConfig.preset("smoke").identity()
    new = {"policies", "explore_frame_stride", "foreground_weight", "foreground_threshold",
           "keypoints", "contrastive_coef", "contrastive_temperature"}  # fmt: skip
    assert not new & set(legacy)
    weighted = PretrainConfig.preset("smoke", foreground_weight=5.0).identity()
    assert weighted["foreground_weight"] == 5.0 and "foreground_threshold" in weighted
    both = PretrainConfig.preset("smoke", policies="oracle,random").identity()
    assert both["policies"] == ["oracle", "random"] and both["explore_frame_stride"] == 5
    with pytest.raises(ValueError, match="must hold 'oracle' once"):
        PretrainConfig.preset("smoke", policies="random")


def test_the_contrastive_term_picks_the_own_episode_and_leaves_its_other_frames_out():
    from ccfit.pretrain.contrastive import episode_contrast, other_frames

    a = torch.eye(4)
    episodes = torch.tensor([0, 1, 2, 3])
    matched = episode_contrast(a, a, episodes, temperature=0.1)
    shuffled = episode_contrast(a, a[[1, 2, 0, 3]], episodes, temperature=0.1)
    assert matched.item() < 0.01 < shuffled.item()
    # rows 0 and 1 of one episode, both matched by b's row 0's view: without leaving the
    # other frame of the episode out, row 0 could not tell its positive apart (loss log 2)
    same = torch.tensor([0, 0])
    b = a[[0, 0]]
    assert episode_contrast(a[:2], b, same, 0.1).item() < 1e-6
    assert episode_contrast(a[:2], b, torch.tensor([0, 1]), 0.1).item() > 0.3
    lengths = np.array([1, 5, 3])
    pairs = np.array([[0, 0], [1, 2], [2, 1], [1, 4]])
    other = other_frames(lengths, pairs, np.random.default_rng(0))
    assert (other[:, 0] == pairs[:, 0]).all() and (other[:, 1] < lengths[other[:, 0]]).all()
