"""Replay on CPU tensors: whole episodes in, windows of consecutive rows out (`Batch` layout).

Rows: an episode of T transitions is stored as T+1 consecutive rows; row t holds observation
o_t, the transition taken from it (a_t, r_t, terminated_t), is_first_t (1 on the episode's
first row) and the task index; the last row holds the final observation and a zero filler
transition. Episodes follow each other in insertion order in a ring of `capacity` rows.

Sampling: a window is `seq_len` consecutive stored rows, drawn uniformly over every start row
from which that many stored rows follow. Windows cross episode boundaries (`is_first` marks
them and the models mask what lies beyond), so an episode shorter than a window is trained on
and every transition, the terminal one of a success included, lies in the same number of
possible windows (except near the newest row, which is the end of the stored sequence).

Overwriting: when the ring is full, new rows overwrite the oldest rows one by one; the oldest
surviving row then gets is_first = 1, so what is left of a partly overwritten episode is a
shorter episode starting there (its remaining transitions stay usable). Hence the oldest
stored row always has is_first = 1.

Demonstrations (`add_episode(demo=True)`) are also kept whole outside the ring, for
`sample(demo_fraction=)` to oversample as long as the buffer lives: a long run would otherwise
overwrite the seed dataset's demonstrations and have none left to oversample. In the ring they
are rows like any other. Checkpoints keep the row files that hold them (`demo_spans`).

`add_windows` stores windows taken from another buffer (`gather`), each as one stored episode
whose first row is marked is_first: what experience replay keeps of a finished task.

What a checkpoint holds of a buffer, and how it is restored from it, is `ccfit.replay_state`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping

import numpy as np
import torch

from ccfit.models.base import Batch
from ccfit.replay_state import ReplayState


def _tensor(x) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(x))


class ReplayBuffer(ReplayState):
    """Rows of episodes in a ring; uniform windows of consecutive rows.

    capacity: rows (an episode of T steps uses T+1); None: unbounded, nothing is overwritten.
    seed: seeds the sampling generator, so the same adds and seed give the same batches.
    obs_transform: applied to each episode's observations (tensors (T+1, ...)) in
        `add_episode` before they are stored, e.g. `WorldModel.replay_obs`, which swaps a
        frozen encoder's inputs for its latents.
    storage: where the rows live and batches are drawn (a GPU when replay fits in its memory:
        batches then never cross the bus; from the host, `Batch.to` copies them through
        page-locked memory).

    A bounded buffer allocates its whole capacity at its first episode (`torch.empty`: on the
    CPU the pages are only committed when rows are written), so it never grows by copying.
    """

    def __init__(
        self,
        capacity: int | None,
        seed: int = 0,
        obs_transform: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]] | None = None,
        storage: torch.device | str = "cpu",
    ) -> None:
        if capacity is not None and capacity < 2:
            raise ValueError(f"capacity must be >= 2 rows or None, got {capacity}")
        self.capacity = None if capacity is None else int(capacity)
        self.obs_transform = obs_transform
        self.storage = torch.device(storage)
        self.generator = torch.Generator().manual_seed(int(seed))
        self._obs: dict[str, torch.Tensor] = {}
        self._action = torch.empty(0, 0)
        self._reward = torch.empty(0)
        self._term = torch.empty(0)
        self._first = torch.empty(0, dtype=torch.bool)
        self._task = torch.empty(0, dtype=torch.long)
        self._written = 0  # rows ever written; row number n lives at n % capacity
        # Stored episodes, oldest first (the oldest may be partly overwritten):
        # [number of its first row ever written, rows, task index].
        self._episodes: deque[tuple[int, int, int]] = deque()
        # Every demonstration ever stored: its write numbers [first, end) and its rows (as
        # `rows` gives them), kept after the ring overwrites them.
        self.demo_spans: list[tuple[int, int]] = []
        self._demo_parts: list[dict[str, torch.Tensor]] = []
        self._demo: dict[str, torch.Tensor] | None = None  # the parts concatenated
        self._cache: dict[str, torch.Tensor] = {}

    # ----------------------------------------------------------------------------- adding

    def add_episode(
        self,
        obs: Mapping[str, np.ndarray | torch.Tensor],
        action: np.ndarray | torch.Tensor,
        reward: np.ndarray | torch.Tensor,
        terminated: np.ndarray | torch.Tensor,
        task: int = 0,
        demo: bool = False,
    ) -> None:
        """Store one episode: obs arrays (T+1, ...), action (T, A), reward (T,), terminated (T,).

        terminated may be true only at the last transition (the success that ended it).
        demo: the episode is a demonstration, which `sample(demo_fraction=)` oversamples.
        """
        action = _tensor(action).float()
        reward = _tensor(reward).float().reshape(-1)
        term = _tensor(terminated).float().reshape(-1)
        obs_t = {k: _tensor(v) for k, v in obs.items()}
        steps = action.shape[0]
        if action.dim() != 2:
            raise ValueError(f"action must be (T, A), got shape {tuple(action.shape)}")
        if steps < 1:
            raise ValueError("an episode needs at least one transition")
        if reward.shape[0] != steps or term.shape[0] != steps:
            raise ValueError(
                f"action, reward and terminated lengths differ: {steps}, {reward.shape[0]}, "
                f"{term.shape[0]}"
            )
        for k, v in obs_t.items():
            if v.shape[0] != steps + 1:
                raise ValueError(f"obs[{k!r}] has {v.shape[0]} rows, expected T+1 = {steps + 1}")
        if bool(term[:-1].any()):
            raise ValueError("terminated is set before the last transition of the episode")
        if self.capacity is not None and steps + 1 > self.capacity:
            raise ValueError(
                f"episode of {steps + 1} rows exceeds the buffer capacity {self.capacity}"
            )
        if self.obs_transform is not None:
            obs_t = self.obs_transform(obs_t)
        first = torch.zeros(steps + 1, dtype=torch.bool)
        first[0] = True
        self._append(
            obs_t,
            torch.cat([action, action.new_zeros(1, action.shape[1])]),
            torch.cat([reward, reward.new_zeros(1)]),
            torch.cat([term, term.new_zeros(1)]),
            first,
            [steps + 1],
            int(task),
            bool(demo),
        )

    def add_windows(self, windows: Batch, task: int = 0) -> None:
        """Store each window of `windows` ((L, k) rows, as `gather` returns them) as one
        episode of L rows, in order. Row 0 of each becomes is_first (nothing before it is
        stored); episode boundaries inside a window stay marked. Observations are stored as
        given (no `obs_transform`)."""
        length, k = windows.seq_len, windows.size
        if k == 0:
            return
        if self.capacity is not None and length * k > self.capacity:
            raise ValueError(f"{k} windows of {length} rows exceed the capacity {self.capacity}")

        def rows(x: torch.Tensor) -> torch.Tensor:  # (L, k, ...) -> window after window
            return x.transpose(0, 1).reshape(length * k, *x.shape[2:]).cpu()

        first = windows.is_first.squeeze(-1).bool().clone()
        first[0] = True
        self._append(
            {key: rows(v) for key, v in windows.obs.items()},
            rows(windows.action).float(),
            rows(windows.reward.squeeze(-1)).float(),
            rows(windows.terminated.squeeze(-1)).float(),
            rows(first),
            [length] * k,
            int(task),
        )

    def _append(self, obs, action, reward, term, first, episode_rows: list[int], task: int,
                demo: bool = False) -> None:  # fmt: skip
        n = action.shape[0]
        self._check_layout(obs, action)
        start = self._written
        cap = self.capacity
        self._grow(start + n if cap is None else min(start + n, cap))
        idx = self._physical(torch.arange(start, start + n)).to(self.storage)
        for k, v in obs.items():
            self._obs[k][idx] = v.to(self.storage)
        self._action[idx] = action.to(self.storage)
        self._reward[idx] = reward.to(self.storage)
        self._term[idx] = term.to(self.storage)
        self._first[idx] = first.to(self.storage)
        self._task[idx] = task
        self._written += n
        if demo:
            self._keep_demo(start, self.rows(start, start + n))
        for rows in episode_rows:
            self._episodes.append((start, rows, task))
            start += rows
        oldest = self._oldest
        while self._episodes and sum(self._episodes[0][:2]) <= oldest:
            self._episodes.popleft()
        if oldest > 0:  # the remainder of a partly overwritten episode starts here
            self._first[self._physical(torch.tensor([oldest])).to(self.storage)] = True
        self._cache.clear()

    def _keep_demo(self, start: int, cols: dict[str, torch.Tensor]) -> None:
        """Keep the demonstration written as rows start .. start + n - 1 (one episode: only
        its first row is_first, though the ring may since have marked another)."""
        cols = {k: v.to(self.storage) for k, v in cols.items()}
        cols["is_first"] = torch.zeros_like(cols["is_first"])
        cols["is_first"][0] = True
        self.demo_spans.append((start, start + cols["action"].shape[0]))
        self._demo_parts.append(cols)
        self._demo = None

    def _demo_columns(self) -> dict[str, torch.Tensor]:
        if self._demo is None:
            self._demo = {k: torch.cat([p[k] for p in self._demo_parts])
                          for k in self._demo_parts[0]}  # fmt: skip
            # The concatenation replaces the parts: both would hold the demonstrations twice.
            self._demo_parts = [self._demo]
        return self._demo

    def _check_layout(self, obs: dict[str, torch.Tensor], action: torch.Tensor) -> None:
        if not self._obs:
            for k, v in obs.items():
                self._obs[k] = torch.empty((0, *v.shape[1:]), dtype=v.dtype, device=self.storage)
            self._action = torch.empty(0, action.shape[1], device=self.storage)
            self._reward, self._term = (torch.empty(0, device=self.storage) for _ in range(2))
            self._first = torch.empty(0, dtype=torch.bool, device=self.storage)
            self._task = torch.empty(0, dtype=torch.long, device=self.storage)
            return
        if set(obs) != set(self._obs):
            raise ValueError(f"obs keys {sorted(obs)} differ from stored {sorted(self._obs)}")
        for k, v in obs.items():
            ref = self._obs[k]
            if v.shape[1:] != ref.shape[1:] or v.dtype != ref.dtype:
                raise ValueError(
                    f"obs[{k!r}] is {v.dtype} {tuple(v.shape[1:])}, stored "
                    f"{ref.dtype} {tuple(ref.shape[1:])}"
                )
        if action.shape[1] != self._action.shape[1]:
            raise ValueError(f"action size {action.shape[1]} != stored {self._action.shape[1]}")

    def _grow(self, rows: int) -> None:
        """Storage for `rows` rows: a bounded buffer's whole capacity at once, an unbounded
        one doubling (its rows are few: experience replay's kept windows). Storage only grows
        before the ring first wraps, so row n sits at index n until then."""
        size = self._action.shape[0]
        if rows <= size:
            return
        new = self.capacity if self.capacity is not None else max(rows, 2 * size, 1024)

        def grown(t: torch.Tensor) -> torch.Tensor:
            out = torch.empty((new, *t.shape[1:]), dtype=t.dtype, device=self.storage)
            out[:size] = t
            return out

        self._set_columns({k: grown(v) for k, v in self._columns().items()})

    def _columns(self) -> dict[str, torch.Tensor]:
        """Every stored column by name ('obs.<key>', action, reward, terminated, is_first,
        task), storage rows first."""
        return {**{f"obs.{k}": v for k, v in self._obs.items()}, "action": self._action,
                "reward": self._reward, "terminated": self._term, "is_first": self._first,
                "task": self._task}  # fmt: skip

    def _set_columns(self, cols: dict[str, torch.Tensor]) -> None:
        self._obs = {k[4:]: v for k, v in cols.items() if k.startswith("obs.")}
        self._action, self._reward, self._term = cols["action"], cols["reward"], cols["terminated"]
        self._first, self._task = cols["is_first"], cols["task"]

    # --------------------------------------------------------------------------- geometry

    @property
    def size(self) -> int:
        """Rows stored."""
        return self._written if self.capacity is None else min(self._written, self.capacity)

    @property
    def _oldest(self) -> int:
        """Number (in write order) of the oldest stored row."""
        return self._written - self.size

    def _physical(self, numbers: torch.Tensor) -> torch.Tensor:
        return numbers if self.capacity is None else numbers % self.capacity

    def _rows(self, logical: torch.Tensor) -> torch.Tensor:
        """Storage indices of stored rows counted from the oldest (0 .. size - 1)."""
        return self._physical(logical + self._oldest)

    @property
    def num_episodes(self) -> int:
        """Stored episodes, a partly overwritten one included."""
        return len(self._episodes)

    @property
    def num_transitions(self) -> int:
        """Real transitions stored: rows followed by a stored row of the same episode."""
        if "transitions" not in self._cache:
            first = self._first[self._rows(torch.arange(1, self.size)).to(self.storage)]
            self._cache["transitions"] = int((~first).sum())
        return self._cache["transitions"]

    def __len__(self) -> int:
        return self.num_transitions

    # ---------------------------------------------------------------------------- sampling

    def num_starts(self, seq_len: int) -> int:
        """How many distinct windows of `seq_len` rows can be sampled."""
        return max(0, self.size - seq_len + 1)

    def can_sample(self, seq_len: int) -> bool:
        return self.num_starts(seq_len) > 0

    def sample(self, batch_size: int, seq_len: int, demo_fraction: float = 0.0) -> Batch:
        """`batch_size` windows of `seq_len` rows, uniform (with replacement) over starts;
        with `demo_fraction`, the first round(demo_fraction * batch_size) of them start on a
        row of a stored demonstration instead (uniform over those rows)."""
        if seq_len < 1 or batch_size < 1:
            raise ValueError(f"seq_len and batch_size must be >= 1, got {seq_len}, {batch_size}")
        total = self.num_starts(seq_len)
        if total == 0:
            raise ValueError(f"replay holds {self.size} rows, fewer than a window of {seq_len}")
        starts = torch.randint(0, total, (batch_size,), generator=self.generator)
        demos = round(demo_fraction * batch_size)
        if demos == 0:
            return self.gather(starts, seq_len)
        pool = self.num_demo_starts(seq_len)
        if pool == 0:
            raise ValueError(f"demo_fraction > 0 but replay holds no demonstration rows to "
                             f"start a window of {seq_len} on")  # fmt: skip
        picks = torch.randint(0, pool, (demos,), generator=self.generator)
        window = torch.arange(seq_len).unsqueeze(1)
        batch = self._window(
            [
                (self._demo_columns(), picks.unsqueeze(0) + window),
                (self._columns(), self._rows(starts[demos:].unsqueeze(0) + window)),
            ]
        )
        batch.demos = demos
        return batch

    def num_demo_starts(self, seq_len: int) -> int:
        """How many windows of `seq_len` rows the kept demonstrations hold (one after another,
        each starting with is_first): `sample(demo_fraction=)` draws among them."""
        rows = sum(end - first for first, end in self.demo_spans)
        return max(0, rows - seq_len + 1)

    def gather(self, starts, seq_len: int) -> Batch:
        """The windows whose first rows are `starts` in [0, num_starts(seq_len)), counted from
        the oldest stored row (as `sample` draws them), in order."""
        pick = torch.as_tensor(starts, dtype=torch.long).reshape(-1)
        total = self.num_starts(seq_len)
        if len(pick) and (int(pick.min()) < 0 or int(pick.max()) >= total):
            raise ValueError(f"window starts must be in [0, {total}) for seq_len {seq_len}")
        logical = pick.unsqueeze(0) + torch.arange(seq_len).unsqueeze(1)
        return self._window([(self._columns(), self._rows(logical))])

    def sample_at_episode_starts(self, batch_size: int, seq_len: int) -> Batch:
        """`batch_size` windows of `seq_len` rows, each starting on an episode's first row,
        uniform over stored episodes. A window running past the newest row continues at the
        oldest (whose is_first = 1 marks the seam), so every episode is equally likely. For
        memories of short episodes (ER's 2-row transitions): every window starts on a real
        transition."""
        if seq_len < 1 or batch_size < 1:
            raise ValueError(f"seq_len and batch_size must be >= 1, got {seq_len}, {batch_size}")
        firsts = self._episode_starts()
        if len(firsts) == 0:
            raise ValueError("replay is empty")
        pick = firsts[torch.randint(0, len(firsts), (batch_size,), generator=self.generator)]
        logical = (pick.unsqueeze(0) + torch.arange(seq_len).unsqueeze(1)) % self.size
        return self._window([(self._columns(), self._rows(logical))])

    def _episode_starts(self) -> torch.Tensor:
        """First stored row of every stored episode, counted from the oldest row."""
        if "starts" not in self._cache:
            oldest = self._oldest
            self._cache["starts"] = torch.tensor(
                [max(first, oldest) - oldest for first, *_ in self._episodes], dtype=torch.long
            )
        return self._cache["starts"]

    def _window(self, parts: list[tuple[dict[str, torch.Tensor], torch.Tensor]]) -> Batch:
        """The windows of each (columns as `_columns` names them, storage rows (L, B_i)),
        side by side in the order given."""

        def take(name: str) -> torch.Tensor:
            outs = [cols[name][rows.to(self.storage)] for cols, rows in parts]
            return outs[0] if len(outs) == 1 else torch.cat(outs, dim=1)

        return Batch(
            obs={k: take(f"obs.{k}") for k in self._obs},
            action=take("action"),
            reward=take("reward").unsqueeze(-1),
            terminated=take("terminated").unsqueeze(-1),
            is_first=take("is_first").float().unsqueeze(-1),
            task=take("task"),
        )
