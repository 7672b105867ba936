"""Sequence replay: rows in the Batch layout, windows across episode boundaries, ring overwrite,
transitions, determinism and checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ccfit.models.base import Batch
from ccfit.replay import ReplayBuffer

A = 4


class Source:
    """Episodes whose observations name themselves: obs['id'] = (episode, step, row number in
    write order); actions and rewards are functions of the same numbers."""

    def __init__(self) -> None:
        self.episodes = 0
        self.rows = 0
        self.lengths: list[int] = []

    def episode(self, steps: int, success: bool = False) -> dict:
        ep, base = self.episodes, self.rows
        self.episodes += 1
        self.rows += steps + 1
        self.lengths.append(steps)
        t = np.arange(steps + 1, dtype=np.float32)
        ids = np.stack([np.full_like(t, ep), t, base + t], axis=1)
        action = np.stack([ep + t[:-1] / 100 + j for j in range(A)], axis=1).astype(np.float32)
        terminated = np.zeros(steps, np.float32)
        terminated[-1] = float(success)
        return {"obs": {"id": ids}, "action": action, "reward": -(t[:-1] + 1) / 100,
                "terminated": terminated, "task": ep % 3}  # fmt: skip


def filled(lengths, capacity=1000, seed=0, successes=()) -> tuple[ReplayBuffer, Source]:
    buf, src = ReplayBuffer(capacity, seed=seed), Source()
    for i, steps in enumerate(lengths):
        buf.add_episode(**src.episode(steps, success=i in successes))
    return buf, src


def columns(batch: Batch, pick: slice) -> Batch:
    """The windows `pick` of `batch`."""
    return Batch(
        obs={k: v[:, pick] for k, v in batch.obs.items()},
        action=batch.action[:, pick],
        reward=batch.reward[:, pick],
        terminated=batch.terminated[:, pick],
        is_first=batch.is_first[:, pick],
        task=batch.task[:, pick],
    )


def check_windows(batch, src: Source, oldest: int = 0) -> None:
    """Every row of every window is what the source wrote at that row, consecutive in write
    order, with is_first exactly on episode starts (and on the `oldest` stored row of a ring
    that wrapped) and the filler transition on last rows."""
    ids = batch.obs["id"]  # (L, B, 3): episode, step, row
    episode, step, row = ids[..., 0], ids[..., 1], ids[..., 2]
    assert torch.equal(row[1:] - row[:-1], torch.ones_like(row[1:]))
    assert torch.equal(batch.is_first[..., 0], ((step == 0) | (row == oldest)).float())
    last = step == torch.tensor(src.lengths, dtype=step.dtype)[episode.long()]
    expected_action = episode.unsqueeze(-1) + step.unsqueeze(-1) / 100 + torch.arange(A)
    expected_action[last] = 0.0
    torch.testing.assert_close(batch.action[~last], expected_action[~last])
    assert torch.all(batch.action[last] == 0) and torch.all(batch.reward[last] == 0)
    torch.testing.assert_close(batch.reward[~last, 0], -(step[~last] + 1) / 100)
    assert torch.equal(batch.task, episode.long() % 3)


# ------------------------------------------------------------------------------ sampling


def test_windows_cross_episode_boundaries_marked_by_is_first():
    buf, src = filled([3, 1, 5, 2, 6])
    assert (buf.num_episodes, buf.num_transitions, buf.size) == (5, 17, 22)
    assert buf.num_starts(4) == 19 and buf.can_sample(22) and not buf.can_sample(23)
    batch = buf.sample(256, 4)
    assert batch.obs["id"].shape == (4, 256, 3) and batch.action.shape == (4, 256, A)
    assert batch.reward.shape == batch.terminated.shape == batch.is_first.shape == (4, 256, 1)
    assert batch.task.shape == (4, 256) and batch.task.dtype == torch.long
    check_windows(batch, src)
    crossing = (batch.is_first[1:] > 0).any(0).squeeze(-1)
    assert crossing.float().mean() > 0.5  # most windows of 4 rows cross a boundary here
    # The rollout mask stops at the first boundary.
    mask = batch.rollout_mask()[..., 0]
    step = batch.obs["id"][..., 1]
    for b in range(256):
        reach = [int(mask[t, b]) for t in range(3)]
        expected = np.cumprod([int(step[t + 1, b] != 0) for t in range(3)]).tolist()
        assert reach == expected


def test_episode_shorter_than_the_window_is_sampled():
    buf, src = filled([9, 1, 9])  # episode 1: one transition, two rows
    batch = buf.gather(torch.arange(buf.num_starts(6)), 6)
    check_windows(batch, src)
    ep, step = batch.obs["id"][0, :, 0], batch.obs["id"][0, :, 1]
    starts_short = (ep == 1) & (step == 0)
    assert starts_short.sum() == 1
    b = int(torch.nonzero(starts_short)[0])
    assert batch.rollout_mask()[:, b, 0].tolist() == [1, 0, 0, 0, 0]  # its one transition
    # With only a short episode stored there is no window of 6 rows.
    alone = ReplayBuffer(100)
    alone.add_episode(**Source().episode(1))
    assert alone.num_starts(6) == 0
    with pytest.raises(ValueError, match="fewer than a window"):
        alone.sample(4, 6)


def test_every_transition_is_equally_likely_terminal_ones_included():
    lengths, successes, seq_len = [4, 2, 7, 1, 5, 3], {0, 1, 3}, 4
    buf, src = filled(lengths, successes=successes)
    size = buf.size
    # Exactly: over all window starts, the transition at row r (rows r and r+1 of one episode)
    # is a valid transition of every window holding both rows: L - 1 windows, fewer only at
    # the two ends of the stored sequence.
    windows = buf.gather(torch.arange(buf.num_starts(seq_len)), seq_len)
    rows = windows.obs["id"][..., 2].long()
    valid = windows.valid()[..., 0] > 0
    counts = torch.bincount(rows[:-1][valid], minlength=size)
    real = torch.ones(size, dtype=torch.bool)
    ends = np.cumsum([n + 1 for n in lengths]) - 1
    real[torch.as_tensor(ends)] = False
    assert torch.all(counts[~real] == 0)
    last_start = size - seq_len
    expected = torch.tensor([min(r, last_start) - max(0, r - seq_len + 2) + 1 for r in range(size)])
    assert torch.equal(counts[real], expected[real])
    assert torch.all(expected[seq_len : size - seq_len] == seq_len - 1)
    terminal = torch.as_tensor(ends - 1)[sorted(successes)]
    assert windows.terminated[:-1][valid].sum() == 3 * len(successes)
    assert torch.all(counts[terminal] == seq_len - 1)  # successes: as often as any transition
    # Sampled: the empirical frequency of every row matches its share of windows.
    n = 30_000
    sample = buf.sample(n, seq_len).obs["id"][..., 2].long()
    freq = torch.bincount(sample.reshape(-1), minlength=size).float() / n
    share = torch.bincount(rows.reshape(-1), minlength=size).float() / rows.shape[1]
    sd = (share * (1 - share) / n).sqrt()
    assert torch.all((freq - share).abs() < 5 * sd + 1e-9), (freq, share)


def test_same_seed_same_batches():
    a, _ = filled([5, 3, 8], seed=3)
    b, _ = filled([5, 3, 8], seed=3)
    c, _ = filled([5, 3, 8], seed=4)
    for _ in range(3):
        x, y, z = a.sample(16, 3), b.sample(16, 3), c.sample(16, 3)
        assert torch.equal(x.obs["id"], y.obs["id"]) and torch.equal(x.is_first, y.is_first)
    assert not torch.equal(x.obs["id"], z.obs["id"])


def test_demonstrations_are_oversampled_by_demo_fraction(tmp_path):
    """The first round(demo_fraction * B) windows start on a demonstration's rows, uniform over
    them, and run through the demonstrations only; the rest stay uniform over replay;
    demo_fraction 0 draws exactly what it drew before demonstrations were marked. The
    demonstrations are kept whole when the ring overwrites them, and through a checkpoint."""

    def build(seed=5):
        buf, src = ReplayBuffer(26, seed=seed), Source()
        for i, steps in enumerate([6, 4, 7, 5, 8]):
            buf.add_episode(**src.episode(steps), demo=i in (1, 3))
        return buf, src

    buf, src = build()
    demo_rows = [
        r
        for e in (1, 3)
        for r in range(sum(src.lengths[:e]) + e, sum(src.lengths[: e + 1]) + e + 1)
    ]
    assert len(demo_rows) == 5 + 6
    # A ring of 26 rows holding 35: episode 0 is gone and demo 1 lost its first 2 rows there.
    assert buf.oldest == 9 and demo_rows[0] == 7
    firsts = [[], []]
    for _ in range(300):
        batch = buf.sample(8, 3, demo_fraction=0.5)  # round(0.5 * 8) = 4 demo windows, first
        assert batch.demos == 4 and batch.to("cpu").demos == 4
        check_windows(columns(batch, slice(4, None)), src, buf.oldest)
        ids = batch.obs["id"][..., 2].long()
        for j in range(4):  # consecutive demonstration rows, is_first where one starts
            at = demo_rows.index(int(ids[0, j]))
            assert ids[:, j].tolist() == demo_rows[at : at + 3]
            assert batch.is_first[:, j, 0].tolist() == [
                float(batch.obs["id"][t, j, 1] == 0) for t in range(3)
            ]
        firsts[0] += ids[0, :4].tolist()
        firsts[1] += ids[0, 4:].tolist()
    assert set(firsts[0]) == set(demo_rows[:-2])  # the overwritten rows 7, 8 included
    assert len(set(firsts[1]) - set(demo_rows)) > 10  # the rest: anywhere in the ring
    assert min(firsts[1]) >= buf.oldest
    plain, _ = filled([6, 4, 7, 5, 8], capacity=26, seed=5)
    marked, _ = build()
    for _ in range(3):
        assert torch.equal(plain.sample(8, 3).obs["id"], marked.sample(8, 3).obs["id"])
    assert marked.sample(8, 3).demos == 0

    torch.save(buf.state_dict(), tmp_path / "replay.pt")
    other = ReplayBuffer(26)
    other.load_state_dict(torch.load(tmp_path / "replay.pt", weights_only=False))
    for _ in range(3):
        a, b = other.sample(8, 3, 0.5), buf.sample(8, 3, 0.5)
        assert torch.equal(a.obs["id"], b.obs["id"]) and torch.equal(a.is_first, b.is_first)
    old = buf.state_dict()  # as written before demonstrations were marked: 3 columns
    old["episodes"] = old["episodes"][:, :3]
    del old["demo_spans"], old["demo_rows"]
    legacy = ReplayBuffer(26)
    legacy.load_state_dict(old)
    assert legacy.num_episodes == buf.num_episodes and legacy.num_demo_starts(3) == 0
    # As written when demonstrations were marked (a 4th episode column) but not kept: what
    # the ring still stores of them is kept (demo 1 from row 9, demo 3 whole).
    marked = {**old, "episodes": torch.cat([old["episodes"], torch.tensor([[1], [0], [1], [0]])],
                                           dim=1)}  # fmt: skip
    kept = ReplayBuffer(26)
    kept.load_state_dict(marked)
    assert kept.demo_spans == [(9, 12), (20, 26)] and kept.num_demo_starts(3) == 7
    assert kept.meta_state()["episodes"].tolist() == buf.meta_state()["episodes"].tolist()
    with pytest.raises(ValueError, match="no demonstration"):
        filled([6])[0].sample(4, 2, demo_fraction=0.5)


def test_checkpoints_keep_the_rows_of_overwritten_demonstrations(tmp_path):
    """A run longer than its ring oversamples its seed demonstrations to the end: once the ring
    overwrote the row file holding them, their rows alone stay on disk (a file of their own,
    written from the buffer's copy; the rest of that file goes), and a resumed buffer draws
    what the uninterrupted one draws."""
    from ccfit.replay_store import ROWS_DIR, disk_rows, load_rows, save_rows

    buf, src = ReplayBuffer(24, seed=3), Source()
    buf.add_episode(**src.episode(5), demo=True)  # rows 0..5
    buf.add_episode(**src.episode(6))  # rows 6..12
    manifest, _ = save_rows(buf, tmp_path, [])
    gone = []
    for steps in (9, 9, 9):  # 42 rows written: every row of the first file is overwritten
        buf.add_episode(**src.episode(steps))
        manifest, stale = save_rows(buf, tmp_path, manifest)
        gone += [p.name for p in stale]
        for path in stale:
            path.unlink()
    assert buf.oldest > 12 and gone == ["rows-000000000000-000000000013.pt"]
    assert manifest[0] == {"file": "rows-000000000000-000000000006-demo.pt", "start": 0,
                           "end": 6, "demo": True}  # fmt: skip
    assert sum(f["end"] - f["start"] for f in manifest) <= disk_rows(24, 6)
    assert sorted(p.name for p in (tmp_path / ROWS_DIR).iterdir()) == sorted(
        f["file"] for f in manifest
    )
    other = ReplayBuffer(24, seed=0)
    load_rows(other, tmp_path, buf.meta_state(), manifest)
    for _ in range(3):
        a, b = buf.sample(6, 3, demo_fraction=0.5), other.sample(6, 3, demo_fraction=0.5)
        assert torch.equal(a.obs["id"], b.obs["id"]) and torch.equal(a.is_first, b.is_first)
        assert set(a.obs["id"][:, :3, 2].flatten().tolist()) <= set(range(6))


def test_a_demonstration_the_ring_overwrote_before_any_checkpoint_is_saved_from_its_copy(
    tmp_path,
):
    """A seed dataset larger than the ring overwrites a demonstration before the first
    checkpoint: the checkpoint writes its rows from the buffer's copy, and a resumed buffer
    draws what the uninterrupted one draws."""
    from ccfit.replay_store import load_rows, save_rows

    buf, src = ReplayBuffer(12, seed=3), Source()
    buf.add_episode(**src.episode(5), demo=True)  # rows 0..5
    buf.add_episode(**src.episode(4), demo=True)  # rows 6..10
    buf.add_episode(**src.episode(7))  # rows 11..18: rows 0..6 overwritten
    assert buf.oldest == 7
    manifest, _ = save_rows(buf, tmp_path, [])
    assert [(f["start"], f["end"]) for f in manifest] == [(0, 6), (6, 7), (7, 19)]
    buf.add_episode(**src.episode(3))  # rows 19..22
    manifest, stale = save_rows(buf, tmp_path, manifest)
    assert not stale and [(f["start"], f["end"]) for f in manifest][-1] == (19, 23)
    other = ReplayBuffer(12, seed=0)
    load_rows(other, tmp_path, buf.meta_state(), manifest)
    for _ in range(3):
        a, b = buf.sample(6, 3, demo_fraction=0.5), other.sample(6, 3, demo_fraction=0.5)
        assert torch.equal(a.obs["id"], b.obs["id"]) and torch.equal(a.is_first, b.is_first)
        assert torch.equal(a.action, b.action) and torch.equal(a.task, b.task)


def test_row_files_are_bounded_so_the_disk_holds_little_more_than_the_ring(tmp_path, monkeypatch):
    """A checkpoint splits what it writes into files of at most `file_rows` rows, so the one
    file the ring has partly overwritten (kept whole until it has overwritten all of it) adds
    at most that to the disk: never more rows on disk than `disk_rows` says."""
    from ccfit import replay_store
    from ccfit.replay_store import disk_rows, file_rows, load_rows, save_rows

    monkeypatch.setattr(replay_store, "MIN_FILE_ROWS", 4)
    buf, src = ReplayBuffer(64, seed=1), Source()
    assert file_rows(64) == 4 and file_rows(None) is None
    buf.add_episode(**src.episode(40))  # a preloaded dataset: 41 rows at once
    manifest, _ = save_rows(buf, tmp_path, [])
    assert [f["end"] - f["start"] for f in manifest] == [4] * 10 + [1]
    for steps in (20, 9, 30, 6):
        buf.add_episode(**src.episode(steps))
        manifest, stale = save_rows(buf, tmp_path, manifest)
        for path in stale:
            path.unlink()
        assert all(f["end"] - f["start"] <= 4 for f in manifest)
        assert manifest[0]["start"] <= buf.oldest < manifest[0]["end"]
        assert sum(f["end"] - f["start"] for f in manifest) <= disk_rows(64)
    other = ReplayBuffer(64, seed=0)
    load_rows(other, tmp_path, buf.meta_state(), manifest)
    a, b = buf.sample(8, 3), other.sample(8, 3)
    assert torch.equal(a.obs["id"], b.obs["id"]) and torch.equal(a.is_first, b.is_first)


# ------------------------------------------------------------------------------ ring


def test_ring_overwrite_keeps_is_first_on_the_oldest_row():
    buf, src = filled([7, 7], capacity=20)  # 16 rows
    assert buf.size == 16
    buf.add_episode(**src.episode(6))  # 7 rows: wraps, overwrites rows 0..2 of episode 0
    assert buf.size == 20 and buf.num_episodes == 3
    oldest = buf.gather(torch.tensor([0]), 1).obs["id"][0, 0]
    assert oldest.tolist() == [0.0, 3.0, 3.0]
    # The remainder of episode 0 is an episode starting at its oldest row.
    everything = buf.gather(torch.tensor([0]), 20)
    ids, first = everything.obs["id"][:, 0], everything.is_first[:, 0, 0]
    assert torch.equal(ids[:, 2], torch.arange(3, 23, dtype=torch.float32))  # write order
    assert first[0] == 1 and torch.equal(first[1:], (ids[1:, 1] == 0).float())
    assert buf.num_transitions == 20 - 3
    # Two more episodes (32 rows written) overwrite episode 0 and rows 8..11 of episode 1.
    buf.add_episode(**src.episode(4))
    buf.add_episode(**src.episode(3))
    assert buf.num_episodes == 4 and buf.size == 20
    windows = buf.gather(torch.arange(buf.num_starts(5)), 5)
    ids = windows.obs["id"]
    assert torch.equal(ids[1:, :, 2] - ids[:-1, :, 2], torch.ones(4, windows.size))
    oldest = buf.gather(torch.tensor([0]), 1)
    assert oldest.obs["id"][0, 0].tolist() == [1.0, 4.0, 12.0] and oldest.is_first.item() == 1
    step = ids[..., 1]
    expected = (step == 0).float()
    expected[0, 0] = 1.0  # window 0 starts on the oldest row
    assert torch.equal(windows.is_first[..., 0], expected)
    assert buf.num_transitions == 20 - 4
    # Real transitions (2-row windows inside one episode) follow the ring too.
    pairs = buf.gather(torch.arange(buf.num_starts(2)), 2)
    real = pairs.valid()[0, :, 0].bool()
    assert int(real.sum()) == buf.num_transitions
    assert torch.equal(pairs.obs["id"][1, real, 2], pairs.obs["id"][0, real, 2] + 1)
    assert torch.equal(pairs.obs["id"][1, real, 0], pairs.obs["id"][0, real, 0])


def test_episode_longer_than_the_ring_is_refused():
    with pytest.raises(ValueError, match="exceeds the buffer capacity"):
        ReplayBuffer(5).add_episode(**Source().episode(5))


# ------------------------------------------------------------------------------ windows


def test_windows_kept_elsewhere_replay_as_they_were():
    buf, _ = filled([3, 1, 4], successes={1})
    assert buf.num_transitions == 8
    kept = buf.gather(torch.tensor([2, 5, 0]), 3)  # rows 2-4 and 5-7 cross a boundary
    memory = ReplayBuffer(None, seed=1)
    memory.add_windows(kept, task=2)
    assert (memory.size, memory.num_episodes) == (9, 3)
    assert memory.num_transitions == 4  # 1 + 1 + 2: the boundaries inside windows stay
    batch = memory.sample_at_episode_starts(300, 3)
    assert torch.all(batch.task == 2)
    ids = batch.obs["id"]
    windows = {tuple(map(tuple, ids[:, j].tolist())) for j in range(300)}
    assert windows == {tuple(map(tuple, kept.obs["id"][:, j].tolist())) for j in range(3)}
    for j in range(300):  # each replayed window is one kept window, reward and flags included
        w = next(i for i in range(3) if torch.equal(kept.obs["id"][:, i], ids[:, j]))
        assert torch.equal(batch.reward[:, j], kept.reward[:, w])
        assert torch.equal(batch.terminated[:, j], kept.terminated[:, w])
        expected_first = kept.is_first[:, w].clone()
        expected_first[0] = 1.0
        assert torch.equal(batch.is_first[:, j], expected_first)
    with pytest.raises(ValueError, match="exceed the capacity"):
        ReplayBuffer(8).add_windows(kept)


# ------------------------------------------------------------------------------ state


def test_state_dict_round_trip_continues_identically(tmp_path):
    buf, src = filled([6, 2, 9], capacity=24, seed=7)
    buf.add_episode(**src.episode(5))  # wrapped ring
    buf.sample(8, 4)
    torch.save(buf.state_dict(), tmp_path / "replay.pt")
    state = torch.load(tmp_path / "replay.pt", weights_only=False)
    assert state["rows"]["obs.id"].shape[0] == 24
    other = ReplayBuffer(24, seed=0)
    other.load_state_dict(state)
    more = src.episode(3)
    for _ in range(2):
        a, b = buf.sample(8, 4), other.sample(8, 4)
        assert torch.equal(a.obs["id"], b.obs["id"]) and torch.equal(a.is_first, b.is_first)
        assert torch.equal(a.action, b.action) and torch.equal(a.task, b.task)
    buf.add_episode(**more)
    other.add_episode(**more)
    a, b = buf.sample(8, 4), other.sample(8, 4)
    assert torch.equal(a.obs["id"], b.obs["id"])
    assert (other.num_episodes, other.num_transitions) == (buf.num_episodes, buf.num_transitions)
    # Compact: a small buffer saves the rows it holds, not its capacity.
    small, _ = filled([3], capacity=100_000)
    assert small.state_dict()["rows"]["obs.id"].shape[0] == 4
    with pytest.raises(ValueError, match="capacity"):
        ReplayBuffer(25).load_state_dict(state)
    # Chunks that leave stored rows out (a manifest missing a file) are refused, not loaded
    # as zeros.
    meta = buf.meta_state()
    first = buf.oldest
    rows = buf.rows(first, buf.written)
    head = {k: v[:10] for k, v in rows.items()}
    tail = {k: v[12:] for k, v in rows.items()}
    with pytest.raises(ValueError, match=f"lack rows {first + 10}.."):
        ReplayBuffer(24).load_state(meta, [(first, head), (first + 12, tail)])
    with pytest.raises(ValueError, match="lack rows"):
        ReplayBuffer(24).load_state(meta, [(first, head)])
    ReplayBuffer(24).load_state(meta, [(first + 12, tail), (first, rows)])  # overlaps are fine


def test_obs_transform_applied_before_storing():
    def transform(obs):
        return {"latent": obs["id"][:, :2] * 10}

    buf = ReplayBuffer(100, obs_transform=transform)
    buf.add_episode(**Source().episode(4))
    batch = buf.sample(5, 3)
    assert set(batch.obs) == {"latent"} and batch.obs["latent"].shape == (3, 5, 2)
    assert torch.equal(batch.obs["latent"][..., 1], batch.obs["latent"][..., 1].round())
    assert set(batch.obs["latent"][..., 1].flatten().tolist()) <= {0.0, 10.0, 20.0, 30.0, 40.0}
    assert buf.gather(torch.tensor([0]), 1).obs["latent"][0].tolist() == [[0.0, 0.0]]


def test_bad_episodes_are_refused():
    buf = ReplayBuffer(100)
    ep = Source().episode(4)
    bad = dict(ep, terminated=np.array([1, 0, 0, 0], np.float32))
    with pytest.raises(ValueError, match="before the last"):
        buf.add_episode(**bad)
    with pytest.raises(ValueError, match="lengths differ"):
        buf.add_episode(**dict(ep, reward=ep["reward"][:2]))
    with pytest.raises(ValueError, match="expected T\\+1"):
        buf.add_episode(**dict(ep, obs={"id": ep["obs"]["id"][:3]}))
    buf.add_episode(**ep)
    with pytest.raises(ValueError, match="differ from stored"):
        buf.add_episode(**dict(ep, obs={"x": ep["obs"]["id"]}))
    with pytest.raises(ValueError, match="action size"):
        buf.add_episode(**dict(ep, action=ep["action"][:, :2]))


# ------------------------------------------------------------------- incremental on disk


def test_checkpoints_write_only_new_rows_and_restore_the_buffer(tmp_path):
    from ccfit.replay_store import ROWS_DIR, load_rows, save_rows

    buf, src = filled([6, 2, 9], capacity=24, seed=7)
    manifest, stale = save_rows(buf, tmp_path, [])
    assert [(f["start"], f["end"]) for f in manifest] == [(0, 20)] and not stale
    buf.add_episode(**src.episode(5))  # 26 rows written: the ring wrapped over rows 0, 1
    manifest, stale = save_rows(buf, tmp_path, manifest)
    assert [(f["start"], f["end"]) for f in manifest] == [(0, 20), (20, 26)]
    buf.add_episode(**src.episode(15))  # 42 written: rows 0..17 are gone, file 0..20 kept
    buf.sample(8, 4)
    manifest, stale = save_rows(buf, tmp_path, manifest)
    assert [(f["start"], f["end"]) for f in manifest] == [(0, 20), (20, 26), (26, 42)]
    buf.add_episode(**src.episode(5))  # 48 written: every row of the first file is gone
    manifest, stale = save_rows(buf, tmp_path, manifest)
    assert [(f["start"], f["end"]) for f in manifest] == [(20, 26), (26, 42), (42, 48)]
    assert [p.name for p in stale] == ["rows-000000000000-000000000020.pt"]
    for path in stale:  # what the trainer does once the checkpoint listing `manifest` is saved
        path.unlink()
    (tmp_path / ROWS_DIR / "rows-000000000048-000000000060.pt").write_bytes(b"from a crash")
    other = ReplayBuffer(24, seed=0)
    load_rows(other, tmp_path, buf.meta_state(), manifest)
    assert sorted(p.name for p in (tmp_path / ROWS_DIR).iterdir()) == [f["file"] for f in manifest]
    assert (other.num_episodes, other.num_transitions) == (buf.num_episodes, buf.num_transitions)
    for _ in range(3):
        a, b = buf.sample(8, 4), other.sample(8, 4)
        assert torch.equal(a.obs["id"], b.obs["id"]) and torch.equal(a.is_first, b.is_first)
        assert torch.equal(a.reward, b.reward) and torch.equal(a.task, b.task)
