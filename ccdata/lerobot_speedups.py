"""Faster stand-ins for LeRobot internals that dominate ccdata's per-episode cost.

ccdata writes every episode as a small LeRobot dataset and merges them, so LeRobot's fixed cost
per dataset matters more here than in LeRobot's own use. Profiling `ccdata generate` (py-spy,
Grasp) showed:

- merging: `LeRobotDatasetMetadata` loads each source's `meta/episodes` through
  `datasets.Dataset.from_parquet`, which converts the parquet (hundreds of `stats/*` columns)
  into an on-disk arrow cache under `~/.cache/huggingface/datasets` and derives HF features for
  every column, about 1 s of CPU per source, only to drop the `stats/*` columns right after.
  The stand-in reads the same files with pyarrow without those columns into an `EpisodeTable`:
  the same rows and columns, no cache files. It is used only while our own merges run, whose
  only use of the metadata's episodes is reading columns.
- writing: `save_episode` runs `embed_images`, a per-row `datasets.map`, to embed image files
  into the parquet (~2 ms per frame). A ccdata dataset has no image features (cameras are
  videos), so the map rewrites nothing; the stand-in returns the dataset as is in that case and
  calls LeRobot's function otherwise. The parquet tables written are identical; only the
  `datasets` cache fingerprint that the map stamps into their schema metadata is absent.
- camera statistics: LeRobot's streaming encoder feeds every frame to a `RunningQuantileStats`,
  whose update recomputes a 5000-bin histogram per channel and re-bins all of them whenever a
  frame widens the range seen so far: about 1 ms per frame per camera, a quarter of the writer's
  work at 64 px. The stand-in keeps the frames and makes one update with all of them when the
  statistics are asked for, binning each channel's 256 value counts rather than every pixel.
  Min, max and count are the same; mean and std the same up to float32 rounding; the quantiles
  come from one histogram over the episode's whole range instead of one re-binned as the range
  grew, so they are no less exact.

All apply only inside `faster_lerobot()` (which also turns off the progress bars LeRobot's
merges print), and only when LeRobot still has the functions they replace (pinned lerobot 0.6);
otherwise LeRobot's own run.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path


class EpisodeTable:
    """The non-stats columns of a dataset's `meta/episodes`, read-only: `table["column"]` is a
    list, `table[i]` a row dict, `len(table)` the episodes; the access `aggregate_datasets`
    makes of `LeRobotDatasetMetadata.episodes` (a `datasets.Dataset` costs ~30 ms per column
    access, in fingerprints and feature copies)."""

    def __init__(self, table) -> None:
        self._columns = table.to_pydict()
        self._rows = table.num_rows

    def __len__(self) -> int:
        return self._rows

    @property
    def column_names(self) -> list[str]:
        return list(self._columns)

    def __getitem__(self, key):
        if isinstance(key, str):
            return self._columns[key]
        if key < 0:
            key += self._rows
        if not 0 <= key < self._rows:
            raise IndexError(key)
        return {name: values[key] for name, values in self._columns.items()}


def _load_episodes(local_dir: Path) -> EpisodeTable:
    """`lerobot.datasets.io_utils.load_episodes` without the arrow cache and stats columns."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    paths = sorted((Path(local_dir) / "meta" / "episodes").glob("*/*.parquet"))
    if not paths:
        raise FileNotFoundError(
            f"Provided directory does not contain any parquet file: "
            f"{Path(local_dir) / 'meta' / 'episodes'}"
        )
    tables = []
    for path in paths:
        columns = [c for c in pq.read_schema(path).names if not c.startswith("stats/")]
        tables.append(pq.read_table(path, columns=columns))
    return EpisodeTable(pa.concat_tables(tables))


def _embed_images_if_any(original):
    def embed_images(dataset):
        from datasets import Image

        if not any(isinstance(f, Image) for f in dataset.features.values()):
            return dataset  # nothing to embed: LeRobot's map would copy every row unchanged
        return original(dataset)

    return embed_images


def _batched_quantile_stats(original):
    import numpy as np

    class BatchedQuantileStats(original):
        """`RunningQuantileStats` that defers its updates to one update at `get_statistics`."""

        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self._pending: list = []

        def update(self, batch) -> None:
            self._pending.append(batch.reshape(-1, batch.shape[-1]))

        def get_statistics(self):
            if self._pending:
                batch = np.concatenate(self._pending)
                self._pending = []
                if batch.dtype == np.uint8 and self._count == 0:
                    self._first_update_uint8(batch)
                else:
                    original.update(self, batch)
            return super().get_statistics()

        def _first_update_uint8(self, batch) -> None:
            """`update` on a fresh tracker, for 8-bit pixels: each channel's 256 value counts
            (a bincount) stand in for its pixels, so the histograms bin 256 weighted values
            instead of searching a bin for every pixel. The same min, max, count and
            histograms as `update`; mean and mean of squares summed exactly."""
            values = np.arange(256, dtype=np.float64)
            counts = np.stack(
                [np.bincount(batch[:, c], minlength=256) for c in range(batch.shape[1])]
            ).astype(np.float64)
            n = batch.shape[0]
            self._count = n
            self._mean = (counts @ values / n).astype(np.float32)
            self._mean_of_squares = (counts @ values**2 / n).astype(np.float32)
            self._min = batch.min(axis=0).astype(np.float32)
            self._max = batch.max(axis=0).astype(np.float32)
            self._bin_edges = [
                np.linspace(lo - 1e-10, hi + 1e-10, self._num_quantile_bins + 1)
                for lo, hi in zip(self._min, self._max, strict=True)
            ]
            self._histograms = [
                np.histogram(values, bins=edges, weights=weights)[0]
                for edges, weights in zip(self._bin_edges, counts, strict=True)
            ]

    return BatchedQuantileStats


class _SilentTqdm:
    """Stands in for the `tqdm` module in `lerobot.datasets.aggregate`: its bars off (a merge
    prints two per call, hundreds per dataset, over `ccdata generate`'s own)."""

    def __init__(self, tqdm_module) -> None:
        self._tqdm = tqdm_module

    def tqdm(self, *args, **kwargs):
        return self._tqdm.tqdm(*args, **{**kwargs, "disable": True})

    def __getattr__(self, name: str):
        return getattr(self._tqdm, name)


@contextmanager
def faster_lerobot():
    """Within the block, LeRobot loads episode metadata and saves episodes the faster way.

    Only for writing pieces and merging them (`ccdata.writer`, `ccdata.journal`): episode
    metadata loaded inside the block is an `EpisodeTable`, not a `datasets.Dataset`."""
    import lerobot.datasets.aggregate as aggregate_module
    import lerobot.datasets.compute_stats as stats_module
    import lerobot.datasets.dataset_metadata as metadata_module
    import lerobot.datasets.dataset_writer as writer_module

    patches = []
    if hasattr(getattr(aggregate_module, "tqdm", None), "tqdm"):
        patches.append((aggregate_module, "tqdm", _SilentTqdm(aggregate_module.tqdm)))
    if callable(getattr(metadata_module, "load_episodes", None)):
        patches.append((metadata_module, "load_episodes", _load_episodes))
    if callable(getattr(writer_module, "embed_images", None)):
        patches.append(
            (writer_module, "embed_images", _embed_images_if_any(writer_module.embed_images))
        )
    if isinstance(getattr(stats_module, "RunningQuantileStats", None), type):
        patches.append(
            (
                stats_module,
                "RunningQuantileStats",
                _batched_quantile_stats(stats_module.RunningQuantileStats),
            )
        )
    saved = [(module, name, getattr(module, name)) for module, name, _ in patches]
    try:
        for module, name, replacement in patches:
            setattr(module, name, replacement)
        yield
    finally:
        for module, name, original in saved:
            setattr(module, name, original)
