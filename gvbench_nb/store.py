"""A crash- and concurrency-safe key -> arrays store made of HDF5 shards.

Each writer buffers entries and commits them as a new shard file: written under a
temporary name, closed, fsynced and renamed. A killed run therefore loses only its
uncommitted buffer, a reader never sees a half-written entry, and two runs writing
the same store (two sequences sharing images, two methods at once) never touch the
same file. hloc keeps one HDF5 file a conf; we keep one folder a conf.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Iterable, Iterator, Mapping
from urllib.parse import quote, unquote

import h5py
import numpy as np

SHARD_SUFFIX = ".h5"


def _group_name(key: str) -> str:
    # Flat group names: '/' would make nested HDF5 groups.
    return quote(key, safe="")


class ShardedStore:
    """A folder of HDF5 shards; every entry is a key with a few named arrays."""

    def __init__(self, folder: str | os.PathLike[str]):
        self.folder = Path(folder)
        self._index: dict[str, Path] | None = None
        self._open: dict[Path, h5py.File] = {}

    # -- reading -----------------------------------------------------------------
    def shards(self) -> list[Path]:
        if not self.folder.is_dir():
            return []
        return sorted(p for p in self.folder.iterdir() if p.suffix == SHARD_SUFFIX and not p.name.startswith("."))

    def refresh(self) -> None:
        self.close()
        index: dict[str, Path] = {}
        for shard in self.shards():
            with h5py.File(shard, "r") as handle:
                for name in handle.keys():
                    index.setdefault(unquote(name), shard)
        self._index = index

    @property
    def index(self) -> dict[str, Path]:
        if self._index is None:
            self.refresh()
        assert self._index is not None
        return self._index

    def keys(self) -> list[str]:
        return list(self.index)

    def __contains__(self, key: str) -> bool:
        return key in self.index

    def __len__(self) -> int:
        return len(self.index)

    def read(self, key: str) -> dict[str, np.ndarray]:
        try:
            shard = self.index[key]
        except KeyError:
            raise KeyError(f"{key!r} is not in the store {self.folder}") from None
        handle = self._open.get(shard)
        if handle is None:
            handle = self._open[shard] = h5py.File(shard, "r")
        group = handle[_group_name(key)]
        entry = {name: group[name][()] for name in group.keys()}
        entry.update({f"attr:{name}": value for name, value in group.attrs.items()})
        return entry

    def close(self) -> None:
        for handle in self._open.values():
            handle.close()
        self._open.clear()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # -- writing -----------------------------------------------------------------
    def writer(self, flush_every: int = 32) -> "ShardWriter":
        return ShardWriter(self, flush_every)


class ShardWriter:
    """Buffers entries and commits them atomically as one shard every ``flush_every``."""

    def __init__(self, store: ShardedStore, flush_every: int = 32):
        self.store = store
        self.flush_every = max(1, flush_every)
        self._buffer: dict[str, tuple[Mapping[str, np.ndarray], Mapping[str, object]]] = {}

    def put(self, key: str, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, object] | None = None) -> None:
        self._buffer[key] = (arrays, attrs or {})
        if len(self._buffer) >= self.flush_every:
            self.flush()

    def flush(self) -> Path | None:
        if not self._buffer:
            return None
        folder = self.store.folder
        folder.mkdir(parents=True, exist_ok=True)
        name = f"shard-{os.getpid()}-{uuid.uuid4().hex[:12]}"
        temporary = folder / f".{name}.tmp"
        final = folder / f"{name}{SHARD_SUFFIX}"
        try:
            with h5py.File(temporary, "w") as handle:
                for key, (arrays, attrs) in self._buffer.items():
                    group = handle.create_group(_group_name(key))
                    for array_name, array in arrays.items():
                        group.create_dataset(array_name, data=np.asarray(array))
                    for attr_name, value in attrs.items():
                        group.attrs[attr_name] = value
            with open(temporary, "rb") as stream:
                os.fsync(stream.fileno())
            os.replace(temporary, final)
        except BaseException:
            if temporary.exists():
                temporary.unlink()
            raise
        index = self.store._index
        if index is not None:
            for key in self._buffer:
                index.setdefault(key, final)
        self._buffer.clear()
        return final

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        # Commit what is finished even when the loop raised: a rerun resumes from it.
        self.flush()


def iter_missing(store: ShardedStore, keys: Iterable[str]) -> Iterator[str]:
    done = store.index
    return (k for k in keys if k not in done)
