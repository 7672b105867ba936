"""Read back what W&B wrote in offline mode: the records of a `run-<id>.wandb` file.

The file is W&B's record log (LevelDB's log format: a 7-byte file header, then 32 KiB blocks
of chunks, each with a 7-byte header: CRC-32, length, type FULL/FIRST/MIDDLE/LAST) whose
payloads are `wandb_internal_pb2.Record` protobufs. The W&B package no longer ships a Python
reader of it, so the tests carry this one.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

BLOCK = 32 * 1024
HEADER = 7
FULL, FIRST, MIDDLE, LAST = 1, 2, 3, 4


def records(path: str | Path) -> list:
    from wandb.proto import wandb_internal_pb2 as pb

    data = Path(path).read_bytes()
    if data[:4] != b":W&B":
        raise ValueError(f"{path} is not a W&B record log")
    out, pos, pending = [], HEADER, b""
    while pos + HEADER <= len(data):
        if BLOCK - pos % BLOCK < HEADER:  # a block's trailer, too short for a chunk header
            pos += BLOCK - pos % BLOCK
            continue
        _crc, length, kind = struct.unpack("<IHB", data[pos : pos + HEADER])
        pos += HEADER
        pending += data[pos : pos + length]
        pos += length
        if kind in (FULL, LAST):
            record = pb.Record()
            record.ParseFromString(pending)
            out.append(record)
            pending = b""
    return out


def history(path: str | Path) -> list[dict]:
    """Every logged row: {key: value} (values decoded from JSON)."""
    rows = []
    for r in records(path):
        if r.WhichOneof("record_type") == "history":
            rows.append({item.key or "/".join(item.nested_key): json.loads(item.value_json)
                         for item in r.history.item})  # fmt: skip
    return rows


def config(path: str | Path) -> dict:
    """The run's config as the run record states it."""
    for r in records(path):
        if r.WhichOneof("record_type") == "run":
            return {item.key: json.loads(item.value_json) for item in r.run.config.update}
    return {}
