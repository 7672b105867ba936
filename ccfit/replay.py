"""Episode replay on CPU tensors: whole episodes in, length-(H+1) subsequences out.

Episodes are stored back to back in flat row storage (a ring of `capacity` rows): an episode of
T transitions takes T+1 rows; row t holds observation t and, for t < T, action t, reward t and
terminated t. A sampled subsequence starts at any row from which H actions remain in the same
episode, so it never crosses an episode boundary, and the terminal transition of an episode that
ended on success is sampled with terminated = 1 and nothing after it. When the ring is full the
oldest episodes are dropped whole.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import torch

from ccfit.models.base import Batch

ACTION_DIM = 4


def _tensor(x) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(x))


class ReplayBuffer:
    """Episodes of (obs dict, action, reward, terminated, task index); uniform subsequences.

    capacity: rows (about one per transition; an episode of T steps uses T+1).
    seed: seeds the sampling generator, so the same adds and seed give the same batches.
    obs_transform: applied to each episode's observations (tensors (T+1, ...)) before they
        are stored, e.g. `WorldModel.replay_obs`, which swaps a frozen encoder's inputs for
        its latents.
    """

    def __init__(
        self,
        capacity: int,
        seed: int = 0,
        obs_transform: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]] | None = None,
    ) -> None:
        if capacity < 2:
            raise ValueError(f"capacity must be >= 2 rows, got {capacity}")
        self.capacity = int(capacity)
        self.obs_transform = obs_transform
        self.generator = torch.Generator().manual_seed(int(seed))
        self._obs: dict[str, torch.Tensor] = {}
        self._action = torch.empty(0, ACTION_DIM)
        self._reward = torch.empty(0)
        self._term = torch.empty(0)
        self._cursor = 0
        self._high = 0  # rows ever written (for compact checkpoints)
        # Live episodes, oldest first: [first row, transitions T, task index].
        self._episodes: list[tuple[int, int, int]] = []
        self._index_cache: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}

    # ----------------------------------------------------------------------------- adding

    def add_episode(
        self,
        obs: Mapping[str, np.ndarray | torch.Tensor],
        action: np.ndarray | torch.Tensor,
        reward: np.ndarray | torch.Tensor,
        terminated: np.ndarray | torch.Tensor,
        task: int = 0,
    ) -> None:
        """Store one episode: obs arrays (T+1, ...), action (T, 4), reward (T,), terminated (T,).

        terminated may be true only at the last transition (the success that ended it).
        """
        action = _tensor(action).float().reshape(-1, ACTION_DIM)
        steps = action.shape[0]
        reward = _tensor(reward).float().reshape(-1)
        term = _tensor(terminated).float().reshape(-1)
        obs_t = {k: _tensor(v) for k, v in obs.items()}
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
        if self.obs_transform is not None:
            obs_t = self.obs_transform(obs_t)
        rows = steps + 1
        if rows > self.capacity:
            raise ValueError(f"episode of {rows} rows exceeds the buffer capacity {self.capacity}")
        self._check_layout(obs_t)

        if self._cursor + rows > self.capacity:
            self._cursor = 0  # wrap; the tail rows stay unused this lap
        lo, hi = self._cursor, self._cursor + rows
        self._episodes = [e for e in self._episodes if e[0] + e[1] + 1 <= lo or e[0] >= hi]
        self._grow(hi)
        for k, v in obs_t.items():
            self._obs[k][lo:hi] = v
        self._action[lo : hi - 1] = action
        self._reward[lo : hi - 1] = reward
        self._term[lo : hi - 1] = term
        self._action[hi - 1] = 0.0  # filler row after the last observation: never sampled
        self._reward[hi - 1] = 0.0
        self._term[hi - 1] = 0.0
        self._episodes.append((lo, steps, int(task)))
        self._cursor = hi
        self._high = max(self._high, hi)
        self._index_cache.clear()

    def _check_layout(self, obs: dict[str, torch.Tensor]) -> None:
        if not self._obs:
            for k, v in obs.items():
                self._obs[k] = torch.empty((0, *v.shape[1:]), dtype=v.dtype)
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

    def _grow(self, rows: int) -> None:
        """Allocate lazily (doubling, up to capacity) so small runs stay small."""
        size = self._action.shape[0]
        if rows <= size:
            return
        new = min(self.capacity, max(rows, 2 * size, 1024))

        def grown(t: torch.Tensor) -> torch.Tensor:
            out = torch.zeros((new, *t.shape[1:]), dtype=t.dtype)
            out[:size] = t
            return out

        self._obs = {k: grown(v) for k, v in self._obs.items()}
        self._action = grown(self._action)
        self._reward = grown(self._reward)
        self._term = grown(self._term)

    # ---------------------------------------------------------------------------- sampling

    @property
    def num_episodes(self) -> int:
        return len(self._episodes)

    @property
    def num_transitions(self) -> int:
        return sum(e[1] for e in self._episodes)

    def __len__(self) -> int:
        return self.num_transitions

    def _index(self, horizon: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per episode: first row, number of valid starts, cumulative starts."""
        if horizon not in self._index_cache:
            ep = torch.tensor(self._episodes, dtype=torch.long).reshape(-1, 3)
            counts = (ep[:, 1] - horizon + 1).clamp(min=0)
            self._index_cache[horizon] = (ep, counts, counts.cumsum(0))
        return self._index_cache[horizon]

    def num_starts(self, horizon: int) -> int:
        """How many distinct subsequences of `horizon` actions can be sampled."""
        _, _, cum = self._index(horizon)
        return int(cum[-1]) if len(cum) else 0

    def can_sample(self, horizon: int) -> bool:
        return self.num_starts(horizon) > 0

    def sample(self, batch_size: int, horizon: int) -> Batch:
        """`batch_size` subsequences of H = `horizon` actions, uniform over valid starts."""
        if horizon < 1 or batch_size < 1:
            raise ValueError(f"horizon and batch_size must be >= 1, got {horizon}, {batch_size}")
        total = self.num_starts(horizon)
        if total == 0:
            raise ValueError(f"no stored episode has {horizon} transitions to sample from")
        starts = torch.randint(0, total, (batch_size,), generator=self.generator)
        return self.gather(starts, horizon)

    def gather(self, starts, horizon: int) -> Batch:
        """The subsequences at start numbers `starts` in [0, num_starts(horizon)), in order
        (start numbers count valid starts episode by episode, as `sample` draws them)."""
        ep, counts, cum = self._index(horizon)
        pick = torch.as_tensor(starts, dtype=torch.long).reshape(-1)
        total = int(cum[-1]) if len(cum) else 0
        if len(pick) and (int(pick.min()) < 0 or int(pick.max()) >= total):
            raise ValueError(f"start numbers must be in [0, {total}) for horizon {horizon}")
        which = torch.searchsorted(cum, pick, right=True)
        offset = pick - (cum[which] - counts[which])
        first = ep[which, 0] + offset
        rows = first.unsqueeze(0) + torch.arange(horizon + 1).unsqueeze(1)  # (H+1, B)
        act_rows = rows[:-1]
        return Batch(
            obs={k: v[rows] for k, v in self._obs.items()},
            action=self._action[act_rows],
            reward=self._reward[act_rows].unsqueeze(-1),
            terminated=self._term[act_rows].unsqueeze(-1),
            task=ep[which, 2].clone(),
        )

    # ------------------------------------------------------------------------- checkpoints

    def state_dict(self) -> dict:
        """Everything needed to continue identically, storing only rows ever written."""
        high = self._high
        return {
            "capacity": self.capacity,
            "cursor": self._cursor,
            "high": high,
            "episodes": torch.tensor(self._episodes, dtype=torch.long).reshape(-1, 3),
            # clone: saving a view would write the whole preallocated storage
            "obs": {k: v[:high].clone() for k, v in self._obs.items()},
            "action": self._action[:high].clone(),
            "reward": self._reward[:high].clone(),
            "terminated": self._term[:high].clone(),
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        if int(state["capacity"]) != self.capacity:
            raise ValueError(
                f"checkpoint buffer capacity {state['capacity']} != configured {self.capacity}"
            )
        self._obs = {k: v.clone() for k, v in state["obs"].items()}
        self._action = state["action"].clone()
        self._reward = state["reward"].clone()
        self._term = state["terminated"].clone()
        self._cursor = int(state["cursor"])
        self._high = int(state["high"])
        self._episodes = [tuple(int(x) for x in row) for row in state["episodes"].tolist()]
        self.generator.set_state(state["generator"])
        self._index_cache.clear()
