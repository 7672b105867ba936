"""A replay buffer's state as a checkpoint holds it: its rows by write number, the kept
demonstrations' rows, and the rest (`meta_state`), from which `load_state` restores it.

`ReplayState` is the part of `ccfit.replay.ReplayBuffer` that reads and restores that state;
it works on the buffer's ring (`_columns`, `_physical`, `_oldest`, `_grow`, `_check_layout`)
and its kept demonstrations (`_demo_columns`, `_keep_demo`). `ccfit.replay_store` writes the
rows of a large buffer to files a chunk at a time instead of in one state dict.
"""

from __future__ import annotations

from collections import deque

import torch


def uncovered(first: int, end: int, spans: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The ranges of rows first .. end - 1 that none of the (start, end) `spans` holds."""
    gaps, row = [], first
    for start, stop in sorted(spans):
        if start > row:
            gaps.append((row, min(start, end)))
        row = max(row, stop)
        if row >= end:
            break
    if row < end:
        gaps.append((row, end))
    return [(a, b) for a, b in gaps if a < b]


def _rows_of(chunks: list[tuple[int, dict[str, torch.Tensor]]], first: int, end: int
             ) -> dict[str, torch.Tensor]:  # fmt: skip
    """Rows first .. end - 1 (write numbers) out of (first write number, columns) chunks,
    which may overlap."""
    pieces, row = [], first
    for start, cols in sorted(chunks, key=lambda chunk: chunk[0]):
        a, b = max(row, start), min(end, start + cols["action"].shape[0])
        if a < b:
            pieces.append({k: v[a - start : b - start] for k, v in cols.items()})
            row = b
    if row != end:
        raise ValueError(f"the checkpoint's rows lack rows {row}..{end} of a demonstration")
    return {k: torch.cat([p[k] for p in pieces]) for k in pieces[0]}


class ReplayState:
    """Reading and restoring a `ReplayBuffer`'s state (see the module's docstring)."""

    @property
    def written(self) -> int:
        """Rows ever written (row number n of the write order is stored while n >= oldest)."""
        return self._written

    @property
    def oldest(self) -> int:
        """Write number of the oldest row still stored."""
        return self._oldest

    def rows(self, start: int, end: int) -> dict[str, torch.Tensor]:
        """Columns of the rows written as numbers start .. end - 1 (all still stored), copied
        to the CPU: what `ccfit.replay_store` writes to disk."""
        if not self._oldest <= start <= end <= self._written:
            raise ValueError(f"rows {start}..{end} not stored ({self._oldest}..{self._written})")
        idx = self._physical(torch.arange(start, end)).to(self.storage)
        return {k: v[idx].cpu() for k, v in self._columns().items()}

    def demo_rows(self, start: int, end: int) -> dict[str, torch.Tensor]:
        """Columns of rows start .. end - 1 (write numbers) of one kept demonstration, copied to
        the CPU, whether or not the ring still stores them."""
        cols, offset = self._demo_columns(), 0
        for first, stop in self.demo_spans:
            if first <= start <= end <= stop:
                a = offset + start - first
                return {k: v[a : a + end - start].cpu() for k, v in cols.items()}
            offset += stop - first
        raise ValueError(f"rows {start}..{end} are not within one kept demonstration")

    def meta_state(self) -> dict:
        """The state besides the rows (see `rows`): with the rows it restores the buffer."""
        return {
            "capacity": self.capacity,
            "written": self._written,
            "episodes": torch.tensor(list(self._episodes), dtype=torch.long).reshape(-1, 3),
            "demo_spans": torch.tensor(self.demo_spans, dtype=torch.long).reshape(-1, 2),
            "generator": self.generator.get_state(),
        }

    def load_state(self, meta: dict, chunks: list[tuple[int, dict[str, torch.Tensor]]]) -> None:
        """Restore from `meta_state` and (first write number, `rows`) chunks covering every
        stored row and every kept demonstration's, oldest first."""
        if meta["capacity"] != self.capacity:
            raise ValueError(
                f"checkpoint buffer capacity {meta['capacity']} != configured {self.capacity}"
            )
        self._obs, self._written, self._cache = {}, int(meta["written"]), {}
        oldest = self._oldest
        episodes = meta["episodes"].tolist()
        # Checkpoints written before demonstrations were kept marked them by a 4th episode
        # column (those before that by none): the ones still stored are kept.
        spans = (meta["demo_spans"].tolist() if "demo_spans" in meta else
                 [(max(first, oldest), first + n) for first, n, _, *demo in episodes
                  if demo and demo[0]])  # fmt: skip
        self.demo_spans, self._demo_parts, self._demo = [], [], None
        for first, end in spans:
            self._keep_demo(first, _rows_of(chunks, first, end))
        gaps = uncovered(
            oldest,
            self._written,
            [(start, start + cols["action"].shape[0]) for start, cols in chunks],
        )
        if gaps:
            raise ValueError(f"the checkpoint's rows lack rows {gaps[0][0]}..{gaps[0][1]} of "
                             f"the {oldest}..{self._written} stored")  # fmt: skip
        for start, cols in chunks:
            keep = max(oldest, start) - start
            cols = {k: v[keep:] for k, v in cols.items()}
            n = cols["action"].shape[0]
            if not self._obs:
                obs = {k[4:]: v for k, v in cols.items() if k.startswith("obs.")}
                self._check_layout(obs, cols["action"])
                self._grow(self._written if self.capacity is None
                           else min(self._written, self.capacity))  # fmt: skip
            idx = self._physical(torch.arange(start + keep, start + keep + n)).to(self.storage)
            for k, v in self._columns().items():
                v[idx] = cols[k].to(self.storage)
        if oldest > 0 and self._obs:  # as `_append` marks it (after its row was saved)
            self._first[self._physical(torch.tensor([oldest])).to(self.storage)] = True
        self._episodes = deque(tuple(int(x) for x in row[:3]) for row in episodes)
        self.generator.set_state(meta["generator"])

    def state_dict(self) -> dict:
        """Everything needed to continue identically, in one dict (the rows stored, not the
        storage allocated); `ccfit.replay_store` writes large buffers incrementally instead."""
        demos = self._demo_columns() if self.demo_spans else {}
        return {**self.meta_state(), "rows": self.rows(self._oldest, self._written),
                "demo_rows": {k: v.cpu() for k, v in demos.items()}}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        written, rows = int(state["written"]), state["rows"]
        chunks = [(written - rows["action"].shape[0], rows)]
        offset = 0  # the kept demonstrations' rows, one span after another
        for first, end in state.get("demo_spans", torch.zeros(0, 2)).tolist():
            chunks.append(
                (
                    first,
                    {k: v[offset : offset + end - first] for k, v in state["demo_rows"].items()},
                )
            )
            offset += end - first
        self.load_state(state, chunks)
